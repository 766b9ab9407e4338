"""Rotation helpers, batched over leading axes.

``R_AB`` is frame B's axes expressed in frame A. Angles in radians.
Base attitude follows shared/spec/recording-csv.md: ``R_WB = Rz(yaw) Ry(pitch) Rx(roll)``.
"""

from __future__ import annotations

import math

import numpy as np

GRAVITY_MPS2 = 9.80665
UP_W = np.array([0.0, 0.0, 1.0])
DEG = np.pi / 180.0  # radians per degree: ``5 * DEG`` is 5 degrees in rad
TWO_PI = 2.0 * np.pi


def wrap_angle(a):
    """Angle(s) in rad wrapped to [-pi, pi) (``%`` takes the sign of the divisor, so pi
    maps to -pi). A float, a NumPy scalar or an array; the same type comes back.

    Plain arithmetic only, so that numba compiles this same function for its kernels
    (``armfusion.fusion.tracking.ukf_kernels`` does): one definition for NumPy and compiled code alike.
    """
    return (a + np.pi) % TWO_PI - np.pi


def rot_x(angle_rad: np.ndarray | float) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(angle_rad: np.ndarray | float) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(angle_rad: np.ndarray | float) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def skew(v: np.ndarray) -> np.ndarray:
    """``skew(v) @ w == cross(v, w)``, batched over leading axes of ``v (..., 3)``; for row
    vectors ``u``, ``u @ skew(v) == cross(u, v)``."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:  # one vector: the literal is 10x faster than the stacks (startup's loops)
        x, y, w = v
        return np.array([[0.0, -w, y], [w, 0.0, -x], [-y, x, 0.0]])
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def exp_so3(rotvec_rad: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle), batched (Rodrigues)."""
    v = np.asarray(rotvec_rad, dtype=float)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a * K + b * (K @ K)


def skew_into(x: float, y: float, z: float, K: np.ndarray) -> None:
    """:func:`skew` of one vector ``(x, y, z)`` written into ``K (3, 3)``.

    Scalar arithmetic only, so that numba compiles this same function for its kernels
    (``armfusion.fusion.tracking.frame_kernels`` does).
    """
    K[0, 0], K[0, 1], K[0, 2] = 0.0, -z, y
    K[1, 0], K[1, 1], K[1, 2] = z, 0.0, -x
    K[2, 0], K[2, 1], K[2, 2] = -y, x, 0.0


def exp_so3_into(x: float, y: float, z: float, E: np.ndarray) -> None:
    """:func:`exp_so3` of one rotation vector ``(x, y, z)`` written into ``E (3, 3)``, in
    the batched form's own order of arithmetic (``(I + a K) + b K K``, the same series below
    1e-8 rad), so that the compiled chain equals :func:`exp_so3` to the bit.

    Scalar arithmetic only, so that numba compiles this same function for its kernels
    (``armfusion.models.chain_kernels`` does). :func:`exp_so3_one` is the faster plain-Python form
    for one vector, which rounds differently.
    """
    ang = math.sqrt(x * x + y * y + z * z)
    if ang < 1e-8:
        a = 1.0 - ang**2 / 6.0
        b = 0.5 - ang**2 / 24.0
    else:
        a = math.sin(ang) / ang
        b = (1.0 - math.cos(ang)) / ang**2
    # skew(x, y, z) as a tuple (no array made: compiled, this runs allocation-free)
    K = ((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0))
    for r in range(3):
        for s in range(3):
            kk = K[r][0] * K[0][s] + K[r][1] * K[1][s] + K[r][2] * K[2][s]
            E[r, s] = ((1.0 if r == s else 0.0) + a * K[r][s]) + b * kk


def exp_so3_one(rotvec_rad) -> np.ndarray:
    """:func:`exp_so3` for ONE rotation vector (an array or three floats), in plain float
    arithmetic: about 9x faster than the batched form for a single 3x3 (the tracker calls
    it every sample). Below 1e-12 rad it returns the identity (the batched form uses the
    series); elsewhere the two agree to a few 1e-18 (different rounding order), which is
    why both stay.
    """
    x, y, z = rotvec_rad.tolist() if isinstance(rotvec_rad, np.ndarray) else rotvec_rad
    th = math.sqrt(x * x + y * y + z * z)
    if th < 1e-12:
        return np.eye(3)
    a = math.sin(th) / th
    b = (1.0 - math.cos(th)) / (th * th)
    return np.array([[1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
                     [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
                     [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)]])


def R_from_rpy(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """``R_WB = Rz(yaw) Ry(pitch) Rx(roll)`` (the recording spec's base attitude)."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def R_from_rpy_into(roll_rad: float, pitch_rad: float, yaw_rad: float, R: np.ndarray) -> None:
    """:func:`R_from_rpy` of one attitude written into ``R (3, 3)``, its product multiplied
    out. Scalar arithmetic only, so that numba compiles this same function for its kernels
    (``armfusion.fusion.tracking.process_kernels`` does)."""
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    sy, cy = math.sin(yaw_rad), math.cos(yaw_rad)
    R[0, 0], R[0, 1], R[0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[1, 0], R[1, 1], R[1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[2, 0], R[2, 1], R[2, 2] = -sp, cp * sr, cp * cr


def rpy_from_R(R_WB: np.ndarray) -> np.ndarray:
    """Inverse of :func:`R_from_rpy`: ``(..., 3)`` roll, pitch, yaw in rad."""
    R = np.asarray(R_WB, dtype=float)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def up_from_tilt(roll_rad, pitch_rad) -> np.ndarray:
    """World 'up' ``[0, 0, 1]`` expressed in the base frame, for a base at (roll, pitch):
    ``[-sp, sr cp, cr cp]`` (the third row of :func:`R_from_rpy`), batched: roll and pitch
    broadcast against each other, ``(..., 3)`` comes back.

    Yaw does not change it. At rest an accelerometer aligned with the base reads this
    vector in g (specific force opposes gravity). Inverse: :func:`tilt_from_up`.
    """
    r, p = np.asarray(roll_rad, dtype=float), np.asarray(pitch_rad, dtype=float)
    out = np.empty(np.broadcast(r, p).shape + (3,))
    out[..., 0], out[..., 1], out[..., 2] = up_from_sines(np.sin(r), np.cos(r), np.sin(p), np.cos(p))
    return out


def up_from_sines(sin_roll, cos_roll, sin_pitch, cos_pitch):
    """The equation of :func:`up_from_tilt`, from the sines and cosines of roll and pitch:
    ``(-sp, sr cp, cr cp)``, three floats or three arrays.

    Plain arithmetic, so that numba compiles this same function for its kernels
    (``armfusion.models.sensor_kernels``, ``armfusion.models.gravity_kernels``): up is written once.
    """
    return -sin_pitch, sin_roll * cos_pitch, cos_roll * cos_pitch


def up_and_tilt_derivatives_into(roll_rad: float, pitch_rad: float, V: np.ndarray,
                                 col_up: int, col_roll: int, col_pitch: int) -> None:
    """:func:`up_from_tilt` of one (roll, pitch) and its derivatives by roll and by pitch,
    written into the columns ``col_up``, ``col_roll``, ``col_pitch`` of ``V (3, w)``.

    Scalar arithmetic only, so that numba compiles this same function for its kernels
    (``armfusion.models.gravity_kernels`` does): the compiled form of up and its tilt Jacobian.
    """
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    srcp, crcp = sr * cp, cr * cp  # up_from_sines, inline: a compiled function calls no plain one
    V[0, col_up], V[1, col_up], V[2, col_up] = -sp, srcp, crcp
    V[0, col_roll], V[1, col_roll], V[2, col_roll] = 0.0, crcp, -srcp
    V[0, col_pitch], V[1, col_pitch], V[2, col_pitch] = -cp, -sr * sp, -cr * sp


def tilt_from_up(up_B: np.ndarray) -> np.ndarray:
    """Roll and pitch (rad) of a base whose accelerometer reads ``up_B`` (any length).

    Inverse of :func:`up_from_tilt`; ``(..., 2)`` comes back (one vector: shape ``(2,)``,
    ``roll, pitch = tilt_from_up(u)`` unpacks NumPy floats). This is the thesis's eq. 4.1
    in the spec's convention.
    """
    u = np.asarray(up_B, dtype=float)
    roll = np.arctan2(u[..., 1], u[..., 2])
    pitch = np.arctan2(-u[..., 0], np.hypot(u[..., 1], u[..., 2]))
    return np.stack([roll, pitch], -1)


def rotation_problem(R: np.ndarray, tol: float = 1e-6) -> str | None:
    """Why ``R`` is not a proper rotation matrix, or None if it is."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        return f"expected a 3x3 matrix, got shape {R.shape}"
    if not np.all(np.isfinite(R)):
        return "contains a non-finite number"
    big = float(np.max(np.abs(R)))
    if big > 1.0 + tol:  # (and R^T R of 1e154 overflows)
        return f"has an entry of {big:.3g}; a rotation's are within ±1"
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > tol:
        return f"not orthonormal (max |R^T R - I| = {err:.3g}, tolerance {tol:g})"
    det = float(np.linalg.det(R))
    if det < 0:
        return f"a reflection, not a rotation (det = {det:.3g})"
    return None


def so3_right_jacobian(rotvec_rad: np.ndarray) -> np.ndarray:
    """Right Jacobian ``J_r`` of SO(3), batched: ``exp(v + d) ≈ exp(v) exp(J_r(v) d)``.

    ``J_r(v) = I - (1 - cos θ)/θ² [v]x + (θ - sin θ)/θ³ [v]x²`` (θ = |v|), so that
    ``d(exp(v) w)/dv = -exp(v) [w]x J_r(v)``.
    """
    v = np.asarray(rotvec_rad, dtype=float)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - np.sin(th)) / th**3)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye - a * K + b * (K @ K)
