"""The base IMU's gyro and magnetometer errors, and the arm's own magnetic disturbance of
the compass: gyro offset and scale, hard and soft iron, a dipole that moves with a link.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.effects.base import SensorEffect, TargetError
from armfusion.models.effects.shapes import XYZ, AxisOffset, AxisScale
from armfusion.models.kinematics import chain_poses
from armfusion.models.motion import cross
from armfusion.models.rotations import DEG


class _ImuEffect(SensorEffect):
    target_kind = "imu"
    stream_name = ""

    @property
    def streams(self):
        return (self.stream_name,)


class GyroBias(AxisOffset, _ImuEffect):
    name = "gyro_bias"
    rank = 40
    key = "bias_rad_s"
    units = "rad/s"
    bound = 30 * DEG
    stream_name = "imu_gyro"
    summary = "gyro reads a rate while still (zero-rate offset)"
    description = (
        "The gyroscope reads a small constant turning rate on each axis even when nothing "
        "turns. Integrated, it makes the heading wander by that many degrees per second.")
    seen_in = "MPU-9150 zero-rate offset up to ±20 °/s (σ taken as 5 °/s)"

    def default_sigma(self):
        return np.full(3, 5.0 * DEG)

    def draw(self, rng):
        return np.clip(super().draw(rng), -20 * DEG, 20 * DEG)


class GyroScale(AxisScale, _ImuEffect):
    name = "gyro_scale"
    rank = 30
    units = "1 (fraction)"
    bound = 0.15
    stream_name = "imu_gyro"
    summary = "gyro sensitivity off by a fraction"
    description = (
        "Each gyro axis turns rate into counts a little off the nominal 131 LSB per °/s: "
        "a full turn of the chair then reads as slightly more or less than 360°.")
    seen_in = "MPU-9150 sensitivity tolerance ±3 %"

    def default_sigma(self):
        return np.full(3, 0.015)


class MagHardIron(AxisOffset, _ImuEffect):
    name = "mag_hard_iron"
    rank = 40
    key = "offset_ut"
    units = "µT"
    bound = 500.0
    stream_name = "imu_mag"
    summary = "constant magnetic field from magnets and steel near the IMU"
    description = (
        "Magnets and magnetised steel that travel with the IMU (wheelchair motors, "
        "screws, the battery) add a constant field on top of Earth's. As the chair turns, "
        "the compass reading circles around this offset instead of around zero.")
    seen_in = "steel and motors near the IMU: tens of µT"

    def default_sigma(self):
        return np.full(3, 15.0)


_SOFT = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def soft_iron_matrix(theta: np.ndarray) -> np.ndarray:
    S = np.eye(3)
    for (a, b), v in zip(_SOFT, theta, strict=True):
        S[a, b] += v
        if a != b:
            S[b, a] += v
    return S


class MagSoftIron(_ImuEffect):
    name = "mag_soft_iron"
    rank = 30
    key = "matrix_error"
    shape = (6,)
    units = "1"
    labels = ("xx", "yy", "zz", "xy", "xz", "yz")
    bound = 0.5
    stream_name = "imu_mag"
    summary = "soft steel near the IMU bends and stretches Earth's field"
    description = (
        "Unmagnetised steel near the IMU (the chair frame) gathers Earth's field and bends "
        "it, so the compass sees the field stretched more along some directions than "
        "others: turning the chair, the readings trace an ellipse instead of a circle. "
        "The symmetric matrix I + S multiplies the field; S's six entries are the "
        "parameters.")
    seen_in = "the chair's steel frame: a few %"

    def default_sigma(self):
        return np.array([0.05, 0.05, 0.05, 0.02, 0.02, 0.02])

    def apply(self, y, theta, ctx, stream):
        return y @ soft_iron_matrix(theta).T

    def jac_params(self, y, theta, ctx, stream):
        N = y.shape[0]
        J = np.zeros((N, 3, 6))
        for c, (a, b) in enumerate(_SOFT):
            J[:, a, c] += y[:, b]
            if a != b:
                J[:, b, c] += y[:, a]
        return J

    def jac_input(self, y, theta, ctx, stream):
        return np.broadcast_to(soft_iron_matrix(theta), (y.shape[0], 3, 3))


MU0_OVER_4PI_UT_M3_PER_AM2 = 0.1
"""µ0/4π = 1e-7 T·m/A, i.e. 0.1 µT·m³ per A·m² of dipole moment."""


def dipole_field(r: np.ndarray, m: np.ndarray):
    """Field ``B (N, 3)`` µT at offset ``r`` (m) from a dipole of moment ``m`` (A·m²), its
    derivative w.r.t. ``m`` (``D``, ``(N, 3, 3)``) and w.r.t. ``r`` (``G``, ``(N, 3, 3)``)."""
    k = MU0_OVER_4PI_UT_M3_PER_AM2
    d = np.linalg.norm(r, axis=-1)
    rh = r / d[:, None]
    eye = np.eye(3)
    D = k * (3.0 * rh[:, :, None] * rh[:, None, :] - eye) / d[:, None, None] ** 3
    B = np.einsum("nij,nj->ni", D, m)
    rm = np.einsum("ni,ni->n", r, m)
    G = 3.0 * k / d[:, None, None] ** 5 * (
        rm[:, None, None] * eye + r[:, :, None] * m[:, None, :] + m[:, :, None] * r[:, None, :]
        - 5.0 * (rm / d**2)[:, None, None] * r[:, :, None] * r[:, None, :])
    return B, D, G


class MagArmDisturbance(SensorEffect):
    name = "mag_arm_disturbance"
    rank = 5
    key = "moment_am2"
    shape = (3,)
    units = "A·m²"
    labels = XYZ
    bound = 2.0
    target_kind = "joint"
    MIN_DISTANCE_M = 0.03
    summary = "the arm's own motors and steel disturb the compass as it moves"
    description = (
        "The motor and steel that turn with a link act like a small bar magnet. As the "
        "arm moves, that magnet moves and turns relative to the IMU, so the compass "
        "reading changes with the arm's pose even though the chair's heading does not. "
        "Modelled as a magnetic dipole fixed at the origin of the link after the joint, "
        "its moment in that link's axes.")
    seen_in = "the arm's own motors and steel: a few µT at the IMU"

    def __init__(self, arm, target=None):
        super().__init__(arm, target)
        self.j = arm.joint_names.index(self.target)
        if arm.imu is None:
            raise TargetError("mag_arm_disturbance needs the base IMU's magnetometer")
        p = chain_poses(arm, arm.ready_pose_rad).p_0L_m[0, self.j + 1]
        d = float(np.linalg.norm(p - arm.imu.p_L_m))
        if d < self.MIN_DISTANCE_M:
            raise TargetError(
                f"mag_arm_disturbance on {self.target}: the origin of the link after it is "
                f"only {d * 100:.1f} cm from the IMU; a dipole there is not a usable model")

    @property
    def streams(self):
        return ("imu_mag",)

    def default_sigma(self):
        return np.full(3, 0.05)

    def _geometry(self, ctx):
        lm, sm = ctx.lm, ctx.sm
        i = ctx.sensor(self.arm.imu.name)
        R_0I, p_I = sm.R_0S[:, i], sm.p_0S_m[:, i]
        R_0L, p_d = lm.R_0L[:, self.j + 1], lm.p_0L_m[:, self.j + 1]
        return R_0I, p_I - p_d, R_0L, p_d

    def apply(self, y, theta, ctx, stream):
        R_0I, r, R_0L, _ = self._geometry(ctx)
        m0 = R_0L @ theta
        B, _, _ = dipole_field(r, m0)
        return y + np.einsum("nji,nj->ni", R_0I, B)

    def jac_params(self, y, theta, ctx, stream):
        R_0I, r, R_0L, _ = self._geometry(ctx)
        _, D, _ = dipole_field(r, R_0L @ theta)
        return np.swapaxes(R_0I, -1, -2) @ D @ R_0L

    def jac_sensor_position(self, y, theta, ctx):
        """``d reading / d p_0I``: the IMU moved (base axes) relative to the dipole, ``(N, 3, 3)``."""
        R_0I, r, R_0L, _ = self._geometry(ctx)
        _, _, G = dipole_field(r, R_0L @ theta)
        return np.swapaxes(R_0I, -1, -2) @ G

    def jac_q(self, y, theta, ctx, stream):
        R_0I, r, R_0L, p_d = self._geometry(ctx)
        m0 = R_0L @ theta
        _, D, G = dipole_field(r, m0)
        N, n = y.shape[0], self.arm.n_joints
        J = np.zeros((N, 3, n))
        for i in range(self.j + 1):
            z, o = ctx.lm.axis_0[:, i], ctx.lm.origin_0_m[:, i]
            dm = cross(z, m0)
            dr = -cross(z, p_d - o)
            dB = np.einsum("nij,nj->ni", D, dm) + np.einsum("nij,nj->ni", G, dr)
            J[:, :, i] = np.einsum("nji,nj->ni", R_0I, dB)
        return J
