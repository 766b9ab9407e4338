"""The tracker's process and measurement models, compiled (numba), for every sigma point.

A tracker step evaluates its models at 2n + 1 = 39 sigma points of a 19-state filter: a
few thousand floating-point operations, which as NumPy array calls cost far more in
interpreter overhead than in arithmetic. These kernels do the same arithmetic in one
compiled loop per call. :mod:`fusion.tracking.tracker` calls them; its tests hold them to the
motion model computed from scratch (:func:`models.motion.specific_force`) and to the
NumPy form of the same equations (:func:`accel_points_numpy`, which the filterpy baseline
of ``tools/bench_track.py`` also calls, one point at a time, as a filterpy user would
write it).

The state layout (see :class:`fusion.tracking.tracker.StateLayout`): joint offsets ``0 … n-1``,
roll, pitch, the base's linear acceleration (3), yaw, the gyro bias (3), the IMU
accelerometer's bias (3). Kernels take the first index of each block.

Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from models.rotations import TWO_PI


@njit(cache=True, nogil=True)
def process_points(X, dt, w, have_w, roll, yaw, bias, accel, accel_decay):  # pragma: no cover - compiled
    """The process model at every sigma point ``X (N, n)`` -> ``(N, n)``.

    With a gyro reading ``w`` (rad/s, body axes; ``have_w``), each point's rates minus its
    own gyro bias turn its attitude over ``dt`` (midpoint rule on the rates of
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``: roll rate ``w_x + (sin r w_y + cos r w_z) tan p``,
    pitch rate ``cos r w_y - sin r w_z``, yaw rate ``(sin r w_y + cos r w_z) / cos p``);
    the base's acceleration decays by ``accel_decay``; everything else stays. Yaw is not
    wrapped here (the unscented mean wraps it)."""
    N, n = X.shape
    Y = X.copy()
    for i in range(N):
        if have_w:
            w0 = w[0] - X[i, bias]
            w1 = w[1] - X[i, bias + 1]
            w2 = w[2] - X[i, bias + 2]
            r, p = X[i, roll], X[i, roll + 1]
            sr, cr = math.sin(r), math.cos(r)
            # the rates at the start, half a step, then the rates at the midpoint
            b = sr * w1 + cr * w2
            r_mid = r + 0.5 * dt * (w0 + b * math.tan(p))
            p_mid = p + 0.5 * dt * (cr * w1 - sr * w2)
            sr, cr = math.sin(r_mid), math.cos(r_mid)
            b = sr * w1 + cr * w2
            Y[i, roll] = r + dt * (w0 + b * math.tan(p_mid))
            Y[i, roll + 1] = p + dt * (cr * w1 - sr * w2)
            Y[i, yaw] = X[i, yaw] + dt * (b / math.cos(p_mid))
        for c in range(3):
            Y[i, accel + c] = X[i, accel + c] * accel_decay
    return Y


@njit(cache=True, nogil=True)
def measurement_points(X, sel, links, axes, offset_ref, motion_mps2, R_0S, imu_index, roll, accel, yaw,
                       imu_bias, g_mps2, still, m_B, heading_shift):  # pragma: no cover - compiled
    """Every measurement of one update at every sigma point ``X (N, n)`` -> ``(N, m)``.

    Columns: the accelerometers ``sel`` (indices into the tracker's accelerometers; three
    columns each, specific force in g, in ``sel``'s order), then with ``still`` the base's
    acceleration (three columns: a parked chair's is zero), then, when ``m_B`` (the
    magnetometer's mean field, base axes, µT) is finite, the heading residual
    ``yaw - tilt-compensated heading`` wrapped to [-pi, pi) (``heading_shift``:
    declination - pi).

    The accelerometers: each point's base-axis specific force is the frame's motion
    acceleration (at the mean pose) plus the point's base acceleration plus gravity turned
    by its roll and pitch (``g up``, ``up = [-sin p, sin r cos p, cos r cos p]``), carried
    to the sensor by the joints between the base and its link. The point's joint angles
    differ from the frame's by ``d_j = offset_j - offset_ref_j``, so its rotation is the
    frame's times ``exp([a_j]x d_j)`` for each joint ``j`` below the link (product of
    exponentials about the base-axis joint axes ``axes`` of the frame): in row form
    ``f^T = v^T E_0 … E_(link-1) R_0S / g``, each ``v^T E_j`` being
    ``v - sin d (a x v) + (1 - cos d) a x (a x v)``. The IMU (``imu_index``) adds its bias.
    """
    N = X.shape[0]
    k = sel.shape[0]
    n_joints = axes.shape[0]
    have_mag = math.isfinite(m_B[0]) and math.isfinite(m_B[1]) and math.isfinite(m_B[2])
    m = 3 * k + (3 if still else 0) + (1 if have_mag else 0)
    Z = np.empty((N, m))
    sd = np.empty(n_joints)
    omc = np.empty(n_joints)
    for i in range(N):
        sr, cr = math.sin(X[i, roll]), math.cos(X[i, roll])
        sp, cp = math.sin(X[i, roll + 1]), math.cos(X[i, roll + 1])
        b0 = -sp * g_mps2 + X[i, accel]
        b1 = sr * cp * g_mps2 + X[i, accel + 1]
        b2 = cr * cp * g_mps2 + X[i, accel + 2]
        for j in range(n_joints):
            d = X[i, j] - offset_ref[j]
            sd[j] = math.sin(d)
            omc[j] = 1.0 - math.cos(d)
        for c in range(k):
            s = sel[c]
            v0 = motion_mps2[s, 0] + b0
            v1 = motion_mps2[s, 1] + b1
            v2 = motion_mps2[s, 2] + b2
            for j in range(links[s]):
                a0, a1, a2 = axes[j, 0], axes[j, 1], axes[j, 2]
                # a x v, then a x (a x v)
                c0 = a1 * v2 - a2 * v1
                c1 = a2 * v0 - a0 * v2
                c2 = a0 * v1 - a1 * v0
                e0 = a1 * c2 - a2 * c1
                e1 = a2 * c0 - a0 * c2
                e2 = a0 * c1 - a1 * c0
                v0 = v0 - sd[j] * c0 + omc[j] * e0
                v1 = v1 - sd[j] * c1 + omc[j] * e1
                v2 = v2 - sd[j] * c2 + omc[j] * e2
            for r in range(3):
                Z[i, 3 * c + r] = (v0 * R_0S[s, 0, r] + v1 * R_0S[s, 1, r] + v2 * R_0S[s, 2, r]) / g_mps2
            if s == imu_index:
                for r in range(3):
                    Z[i, 3 * c + r] += X[i, imu_bias + r]
        col = 3 * k
        if still:
            for r in range(3):
                Z[i, col + r] = X[i, accel + r]
            col += 3
        if have_mag:
            mx, my, mz = m_B[0], m_B[1], m_B[2]
            y1 = cr * my - sr * mz
            hx = cp * mx + sp * (sr * my + cr * mz)
            d = X[i, yaw] + math.atan2(y1, hx) - heading_shift
            Z[i, col] = (d % TWO_PI) - math.pi
    return Z


# --------------------------------------------------------------------------------------
# the same equations in NumPy (the reference the kernels are tested against, and what a
# filterpy user would write: the benchmark's baseline calls it one point at a time)
def accel_points_numpy(X: np.ndarray, sel: np.ndarray, links: np.ndarray, axes: np.ndarray,
                       offset_ref: np.ndarray, motion_mps2: np.ndarray, R_0S: np.ndarray, imu_index: int,
                       roll: int, accel: int, imu_bias: int, g_mps2: float) -> np.ndarray:
    """The accelerometer columns of :func:`measurement_points`, in NumPy: each joint's
    ``E_j = I + sin d_j K_j + (1 - cos d_j) K_j²`` for every point, multiplied out per sensor."""
    N, n_joints = X.shape[0], axes.shape[0]
    r, p = X[:, roll], X[:, roll + 1]
    up = np.stack([-np.sin(p), np.sin(r) * np.cos(p), np.cos(r) * np.cos(p)], axis=1)
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
    """:func:`process_points` in NumPy. The Euler-angle rates turn the body rates' (y, z)
    pair by the roll: with ``u = e^{i roll} (w_y + i w_z)``, roll rate
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
    """:func:`measurement_points` in NumPy (same arguments, same columns)."""
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
