"""The tracker's process and measurement models written in NumPy, as a filterpy user writes them.

The filterpy baseline of ``tools/bench_track.py`` calls these one sigma point at a time
(its "NumPy fx/hx" row); tests/fusion/test_tracker_kernels.py holds the tracker's compiled
kernels (:mod:`fusion.tracking.tracker_kernels`, whose equations are :mod:`models.sensor_kernels`'
and :mod:`models.chain_kernels`') to them. They are a second coding of the same equations on
purpose (a reference and a baseline), so they live here, outside the production packages.

Same arguments and columns as the compiled kernels; the state layout is
:class:`fusion.tracking.tracker.StateLayout`'s.
"""

from __future__ import annotations

import numpy as np

from models.rotations import TWO_PI, up_from_tilt


def accel_points_numpy(X: np.ndarray, sel: np.ndarray, links: np.ndarray, axes: np.ndarray,
                       offset_ref: np.ndarray, motion_mps2: np.ndarray, R_0S: np.ndarray, imu_index: int,
                       roll: int, accel: int, imu_bias: int, g_mps2: float) -> np.ndarray:
    """The accelerometer columns of :func:`fusion.tracking.tracker_kernels.measurement_points`,
    in NumPy: each joint's ``E_j = I + sin d_j K_j + (1 - cos d_j) K_j²`` for every point,
    multiplied out per sensor."""
    N, n_joints = X.shape[0], axes.shape[0]
    up = up_from_tilt(X[:, roll], X[:, roll + 1])  # (N, 3)
    base = g_mps2 * up + X[:, accel:accel + 3]  # (N, 3)
    Kj = np.zeros((n_joints, 3, 3))
    Kj[:, 0, 1], Kj[:, 0, 2], Kj[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    Kj -= Kj.transpose(0, 2, 1)
    d = X[:, :n_joints] - offset_ref  # (N, n)
    E = (np.eye(3) + np.sin(d)[..., None, None] * Kj
         + (1.0 - np.cos(d))[..., None, None] * (Kj @ Kj))  # (N, n, 3, 3)
    out = np.empty((N, 3 * len(sel)))
    for c, s in enumerate(np.asarray(sel).tolist()):
        v = (motion_mps2[s] + base)[:, None, :]  # rows (N, 1, 3)
        for j in range(int(links[s])):
            v = v @ E[:, j]
        f = (v[:, 0] @ R_0S[s]) / g_mps2
        if s == imu_index:
            f = f + X[:, imu_bias:imu_bias + 3]
        out[:, 3 * c:3 * c + 3] = f
    return out


def process_points_numpy(X: np.ndarray, dt: float, w: np.ndarray, have_w: bool, roll: int, yaw: int,
                         bias: int, accel: int, accel_decay: float) -> np.ndarray:
    """:func:`fusion.tracking.tracker_kernels.process_points` in NumPy. The Euler-angle rates
    turn the body rates' (y, z) pair by the roll: with ``u = e^{i roll} (w_y + i w_z)``, roll rate
    ``w_x + Im u tan(pitch)``, pitch rate ``Re u``, yaw rate ``Im u / cos(pitch)``."""
    Y = X.copy()
    if have_w:
        wb = w - X[:, bias:bias + 3]
        wyz = wb[:, 1] + 1j * wb[:, 2]
        u = np.exp(1j * X[:, roll]) * wyz
        r_mid = X[:, roll] + 0.5 * dt * (wb[:, 0] + u.imag * np.tan(X[:, roll + 1]))
        p_mid = X[:, roll + 1] + 0.5 * dt * u.real
        u = np.exp(1j * r_mid) * wyz
        Y[:, roll] += dt * (wb[:, 0] + u.imag * np.tan(p_mid))
        Y[:, roll + 1] += dt * u.real
        Y[:, yaw] += dt * (u.imag / np.cos(p_mid))
    Y[:, accel:accel + 3] *= accel_decay
    return Y


def measurement_points_numpy(X, sel, links, axes, offset_ref, motion_mps2, R_0S, imu_index, roll, accel,
                             yaw, imu_bias, g_mps2, still, m_B, heading_shift) -> np.ndarray:
    """:func:`fusion.tracking.tracker_kernels.measurement_points` in NumPy (same arguments, same columns)."""
    parts = [accel_points_numpy(X, sel, links, axes, offset_ref, motion_mps2, R_0S, imu_index, roll, accel,
                                imu_bias, g_mps2)]
    if still:
        parts.append(X[:, accel:accel + 3])
    if np.all(np.isfinite(m_B)):
        sr, cr = np.sin(X[:, roll]), np.cos(X[:, roll])
        sp, cp = np.sin(X[:, roll + 1]), np.cos(X[:, roll + 1])
        mx, my, mz = m_B
        heading = np.arctan2(cr * my - sr * mz, cp * mx + sp * (sr * my + cr * mz))
        parts.append((((X[:, yaw] + heading - heading_shift) % TWO_PI) - np.pi)[:, None])
    return np.concatenate(parts, axis=1)
