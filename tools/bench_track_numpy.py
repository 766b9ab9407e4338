"""The tracker's process and measurement models written in NumPy, as a filterpy user writes them.

The filterpy baseline of ``tools/bench_track.py`` calls these one sigma point at a time
(its "NumPy fx/hx" row); tests/fusion/test_tracker_kernels.py holds the tracker's compiled
kernels (:mod:`armfusion.fusion.tracking.tracker_kernels`, whose equations are :mod:`armfusion.models.sensor_kernels`'
and :mod:`armfusion.models.chain_kernels`') to them. They are a second coding of the same equations on
purpose (a reference and a baseline), so they live here, outside the production packages.

Same arguments and columns as the compiled kernels; the state layout is
:class:`armfusion.fusion.tracking.tracker.StateLayout`'s.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.rotations import TWO_PI, R_from_rpy, exp_so3, rpy_from_R, up_from_tilt, wrap_angle


def accel_points_numpy(X: np.ndarray, sel: np.ndarray, links: np.ndarray, axes: np.ndarray,
                       offset_ref: np.ndarray, motion_mps2: np.ndarray, R_0S: np.ndarray, imu_index: int,
                       roll: int, accel: int, imu_bias: int, g_mps2: float) -> np.ndarray:
    """The accelerometer columns of :func:`armfusion.fusion.tracking.tracker_kernels.measurement_points`,
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
                         bias: int, accel: int, scale: int, accel_decay: float, jerk: int = -1,
                         jerk_decay: float = 1.0) -> np.ndarray:
    """:func:`armfusion.fusion.tracking.process_kernels.process_points` in NumPy: each point's attitude
    ``R_from_rpy`` turned by ``exp_so3`` of its bias- (and z scale-) corrected rates times ``dt``, read back
    by ``rpy_from_R`` and put in the chart nearest the point's (of the two Euler triples of
    the rotation, the closer, roll and yaw unwrapped onto the old ones)."""
    Y = X.copy()
    if have_w:
        r, p, y = X[:, roll], X[:, roll + 1], X[:, yaw]
        R = np.stack([R_from_rpy(a, b, c) for a, b, c in zip(r, p, y, strict=True)])
        om = w - X[:, bias:bias + 3]
        if scale >= 0:  # the gyro's z reads (1 + s) times the true rate
            om[:, 2] /= 1.0 + X[:, scale]
        R2 = R @ exp_so3(dt * om)
        r1, p1, y1 = rpy_from_R(R2).T
        dr1, dy1 = wrap_angle(r1 - r), wrap_angle(y1 - y)
        p2 = np.copysign(np.pi, p1) - p1
        dr2, dy2 = wrap_angle(dr1 + np.pi), wrap_angle(dy1 + np.pi)
        first = dr1**2 + (p1 - p) ** 2 + dy1**2 <= dr2**2 + (p2 - p) ** 2 + dy2**2
        Y[:, roll] = r + np.where(first, dr1, dr2)
        Y[:, roll + 1] = np.where(first, p1, p2)
        Y[:, yaw] = y + np.where(first, dy1, dy2)
    Y[:, accel:accel + 3] *= accel_decay
    if jerk >= 0:
        Y[:, accel:accel + 3] += dt * X[:, jerk:jerk + 3]
        Y[:, jerk:jerk + 3] = X[:, jerk:jerk + 3] * jerk_decay
    return Y


def measurement_points_numpy(X, sel, links, axes, offset_ref, motion_mps2, R_0S, imu_index, roll, accel,
                             yaw, imu_bias, g_mps2, still, m_B, heading_shift) -> np.ndarray:
    """:func:`armfusion.fusion.tracking.tracker_kernels.measurement_points` in NumPy (same arguments, same columns)."""
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
