"""The library of physical effects: what makes a real arm and its sensors differ from the
config, each as a small object with one parameter block, a vectorised ``apply`` and its
analytic Jacobians. Units are in the parameter keys; every identity is zero.

Magnitudes (the 1-σ of ``default_sigma``, used as prior and by ``--realistic``) come from
the datasheets where they give them (ADXL345, MPU-9150, AK8975), else from what such
arms show; each class says where its numbers come from.
"""

from __future__ import annotations

import numpy as np

from models.arm import ArmModel
from models.effects.base import (
    JointEffect,
    MountEffect,
    SensorEffect,
    TargetError,
    TimeEffect,
    accel_stream,
    device_streams,
)
from models.kinematics import chain_poses
from models.motion import cross
from models.rotations import DEG, exp_so3, skew, so3_right_jacobian

XYZ = ("x", "y", "z")


def _sensor_type(arm: ArmModel, name: str) -> str:
    return arm.sensor(name).type


def _by_type(arm: ArmModel, name: str, table: dict[str, np.ndarray]) -> np.ndarray:
    return np.array(table.get(_sensor_type(arm, name), table["default"]), dtype=float)


def _eye_batch(N: int, k: int) -> np.ndarray:
    return np.broadcast_to(np.eye(k), (N, k, k))


def _diag(v: np.ndarray) -> np.ndarray:
    """``(N, k)`` -> ``(N, k, k)`` diagonal matrices."""
    N, k = v.shape
    out = np.zeros((N, k, k))
    idx = np.arange(k)
    out[:, idx, idx] = v
    return out


# ========================================================================================
# accelerometers (link accelerometers and the IMU's)
# ========================================================================================
class _AccelEffect(SensorEffect):
    target_kind = "accelerometer"

    @property
    def streams(self) -> tuple[str, ...]:
        return (accel_stream(self.arm, self.target),)


class AccelBias(_AccelEffect):
    name = "accel_bias"
    rank = 40
    key = "bias_g"
    shape = (3,)
    units = "g"
    labels = XYZ
    bound = 0.3
    summary = "constant offset on each accelerometer axis"
    description = (
        "The accelerometer reads a constant extra amount on each axis, even when it is "
        "perfectly still (its '0 g offset'). Typical ADXL345 boards are a few hundredths "
        "of a g off; the error looks like a tilt that changes with the pose.")
    seen_in = ("ADXL345 0 g offset ±35 mg x/y, ±40 mg z typical; MPU-9150 accelerometer "
               "±80 mg x/y, ±150 mg z initial tolerance (σ taken as half)")

    def default_sigma(self):
        return _by_type(self.arm, self.target, {
            "adxl345": [0.035, 0.035, 0.040], "mpu9150": [0.040, 0.040, 0.075], "default": [0.02] * 3})

    def apply(self, y, theta, ctx, stream):
        return y + theta

    def jac_params(self, y, theta, ctx, stream):
        return _eye_batch(y.shape[0], 3)


class AccelScale(_AccelEffect):
    input_is_diagonal = True
    name = "accel_scale"
    rank = 30
    key = "scale_error"
    shape = (3,)
    units = "1 (fraction: 0.01 = reads 1 % more)"
    labels = XYZ
    bound = 0.15
    summary = "sensitivity of each accelerometer axis off by a fraction"
    description = (
        "Each axis turns g into counts with its own sensitivity, a little off the nominal "
        "256 LSB/g: a 1 % error reads 1.01 g for 1 g. It shows as a reading that is "
        "slightly too large (or small) in proportion to what the axis feels.")
    seen_in = ("ADXL345 sensitivity 230-282 LSB/g at ±2 g (about ±1 % typical after trim); "
               "MPU-9150 ±3 % tolerance")

    def default_sigma(self):
        return _by_type(self.arm, self.target, {"adxl345": [0.01] * 3, "mpu9150": [0.015] * 3,
                                                "default": [0.01] * 3})

    def apply(self, y, theta, ctx, stream):
        return y * (1.0 + theta)

    def jac_params(self, y, theta, ctx, stream):
        return _diag(y)

    def jac_input(self, y, theta, ctx, stream):
        return _diag(np.broadcast_to(1.0 + theta, y.shape))


# the article's eq. 4-6: axis k is e_x turned by beta about y, then gamma about z, carried
# onto the nominal axis by the cyclic permutation x -> y -> z -> x
_CYCLE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_CYCLE_POW = (np.eye(3), _CYCLE, _CYCLE @ _CYCLE)


def axis_directions(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensing directions ``M (3, 3)`` (rows) of the three axes for angles ``theta (3, 2)``
    (β, γ per axis), and ``dM/dβ``, ``dM/dγ`` (row k: derivative of row k)."""
    M = np.empty((3, 3))
    dB = np.empty((3, 3))
    dG = np.empty((3, 3))
    for k in range(3):
        b, g = theta[k]
        P = np.array([np.cos(g) * np.cos(b), np.sin(g) * np.cos(b), -np.sin(b)])
        Pb = np.array([-np.cos(g) * np.sin(b), -np.sin(g) * np.sin(b), -np.cos(b)])
        Pg = np.array([-np.sin(g) * np.cos(b), np.cos(g) * np.cos(b), 0.0])
        C = _CYCLE_POW[k]
        M[k], dB[k], dG[k] = C @ P, C @ Pb, C @ Pg
    return M, dB, dG


class AccelAxes(_AccelEffect):
    name = "accel_axes"
    rank = 20
    key = "axis_angles_rad"
    shape = (3, 2)
    units = "rad"
    labels = ("x.beta", "x.gamma", "y.beta", "y.gamma", "z.beta", "z.gamma")
    bound = 0.2
    summary = "accelerometer axes not exactly at right angles (cross-axis sensitivity)"
    description = (
        "The three sensing axes inside the chip are not exactly at right angles to each "
        "other, so each axis also feels a little of what the others feel (cross-axis "
        "sensitivity). Each axis's real direction is given by two small angles, as in the "
        "sensor-calibration article (eq. 4-6): gamma tilts it toward the next axis "
        "(x toward y, y toward z, z toward x), beta away from the one after (x toward -z, "
        "y toward -x, z toward -y).")
    seen_in = "ADXL345 cross-axis sensitivity ±1 %; MPU-9150 ±2 %"

    def default_sigma(self):
        return _by_type(self.arm, self.target, {"adxl345": [0.01] * 6, "mpu9150": [0.02] * 6,
                                                "default": [0.01] * 6})

    def apply(self, y, theta, ctx, stream):
        M, _, _ = axis_directions(theta)
        return y @ M.T

    def jac_params(self, y, theta, ctx, stream):
        _, dB, dG = axis_directions(theta)
        N = y.shape[0]
        J = np.zeros((N, 3, 6))
        for k in range(3):
            J[:, k, 2 * k] = y @ dB[k]
            J[:, k, 2 * k + 1] = y @ dG[k]
        return J

    def jac_input(self, y, theta, ctx, stream):
        M, _, _ = axis_directions(theta)
        return np.broadcast_to(M, (y.shape[0], 3, 3))


class TemperatureDrift(_AccelEffect):
    name = "temperature_drift"
    rank = 50
    key = "drift_g_per_c"
    shape = (3,)
    units = "g/°C"
    labels = XYZ
    bound = 0.01
    T_REF_C = 25.0
    summary = "accelerometer offset that changes with temperature"
    description = (
        "The accelerometer's zero point moves as it warms up: each axis reads an extra "
        "amount proportional to how far the temperature is from 25 °C. It shows as a slow "
        "drift over the first minutes after power-up, or between a cold and a warm day.")
    seen_in = ("ADXL345 0 g offset vs temperature ±0.4 mg/°C x/y, ±1.2 mg/°C z; MPU-9150 "
               "±35 mg x/y, ±60 mg z over 0-70 °C (≈ ±0.5 / ±0.9 mg/°C)")

    def default_sigma(self):
        return _by_type(self.arm, self.target, {
            "adxl345": [0.0004, 0.0004, 0.0012], "mpu9150": [0.0005, 0.0005, 0.0009],
            "default": [0.0004] * 3})

    def apply(self, y, theta, ctx, stream):
        dT = ctx.state.temperature_c - self.T_REF_C
        return y + dT[:, None] * theta

    def jac_params(self, y, theta, ctx, stream):
        dT = ctx.state.temperature_c - self.T_REF_C
        return _diag(np.broadcast_to(dT[:, None], y.shape))


# ========================================================================================
# sensor frames
# ========================================================================================
def _rotate_value(y, theta):
    """``exp(-ρ) y`` for every row: the reading of a sensor turned by ρ on its own axes."""
    return y @ exp_so3(-theta).T


def _rotate_jac(y, theta):
    R = exp_so3(-theta)
    Jr = so3_right_jacobian(-theta)
    return R @ skew(y) @ Jr  # (N, 3, 3)


class MountRotation(SensorEffect):
    name = "mount_rotation"
    rank = 10
    key = "rotvec_rad"
    shape = (3,)
    units = "rad"
    labels = XYZ
    bound = 0.35
    target_kind = "link_accelerometer"
    summary = "accelerometer board turned on its link"
    description = (
        "The accelerometer board is glued or screwed onto its link turned by a degree or "
        "two from where the config says. Its axes then see gravity from a slightly "
        "different direction. The rotation is a small rotation vector about the board's "
        "own x, y, z axes (the real mount is R_LS·exp(ρ)).")
    seen_in = "a board glued 1-3° off"

    @property
    def streams(self):
        return (self.target,)

    def default_sigma(self):
        return np.full(3, 2.0 * DEG)

    def apply(self, y, theta, ctx, stream):
        return _rotate_value(y, theta)

    def jac_params(self, y, theta, ctx, stream):
        return _rotate_jac(y, theta)

    def jac_input(self, y, theta, ctx, stream):
        return np.broadcast_to(exp_so3(-theta), (y.shape[0], 3, 3))


class BaseMount(SensorEffect):
    name = "base_mount"
    rank = 10
    key = "rotvec_rad"
    shape = (3,)
    units = "rad"
    labels = XYZ
    bound = 0.35
    target_kind = "imu"
    summary = "IMU not parallel to the arm's base"
    description = (
        "The IMU sits on the chair and the arm's base on its own bracket: the two are not "
        "exactly parallel, so the tilt the IMU measures is not quite the tilt of the arm's "
        "base. A small rotation vector about the IMU's own axes; it turns the IMU's "
        "accelerometer, gyro and compass together.")
    seen_in = "the thesis found the WMRA not level across the chair's base (ch. 4)"

    @property
    def streams(self):
        return ("imu_acc", "imu_gyro", "imu_mag")

    def default_sigma(self):
        return np.full(3, 1.0 * DEG)

    def apply(self, y, theta, ctx, stream):
        return _rotate_value(y, theta)

    def jac_params(self, y, theta, ctx, stream):
        return _rotate_jac(y, theta)

    def jac_input(self, y, theta, ctx, stream):
        return np.broadcast_to(exp_so3(-theta), (y.shape[0], 3, 3))


# ========================================================================================
# joints
# ========================================================================================
class JointOffset(JointEffect):
    name = "joint_offset"
    rank = 10
    key = "offset_rad"
    shape = (1,)
    units = "rad"
    labels = ("offset",)
    bound = 0.35
    summary = "joint's zero not where the config puts it"
    description = (
        "The joint's real zero is a little off the zero in the arm's description (an "
        "encoder index or a part assembled a tooth off): the link really stands at the "
        "controller's angle plus this offset.")
    seen_in = "encoder index / assembly error, about a degree"

    def default_sigma(self):
        return np.array([1.0 * DEG])

    def delta(self, q, theta, ctx):
        return np.full(q.shape[0], theta[0])

    def delta_jac_params(self, q, theta, ctx):
        return np.ones((q.shape[0], 1))


class LinkCompliance(JointEffect):
    name = "link_compliance"
    rank = 20
    key = "compliance_rad_per_nm"
    shape = (1,)
    units = "rad/(N·m)"
    labels = ("compliance",)
    bound = 5e-3
    nonnegative = True
    summary = "link and gearbox sag under gravity"
    description = (
        "The gearbox and the link are not perfectly stiff: gravity's pull on everything "
        "beyond the joint bends it a little, more when the arm is stretched out "
        "horizontally than when it hangs down. The joint really stands at the controller's "
        "angle plus compliance times the gravity torque (from a nominal mass model).")
    seen_in = "harmonic drives and long aluminium links: tenths of a degree at full reach"

    def default_sigma(self):
        return np.array([2e-4])

    def delta(self, q, theta, ctx):
        return theta[0] * ctx.gravity_torque()[:, self.j]

    def delta_jac_params(self, q, theta, ctx):
        return ctx.gravity_torque()[:, self.j, None]

    def delta_jac_q(self, q, theta, ctx):
        return theta[0] * ctx.gravity_torque_jacobian()[:, self.j, :]


class Backlash(JointEffect):
    name = "backlash"
    rank = 30
    key = "play_rad"
    shape = (1,)
    units = "rad"
    labels = ("play",)
    bound = 0.05
    nonnegative = True
    TORQUE_SCALE_NM = 1.0
    summary = "gearbox play, taken up by gravity"
    description = (
        "The gears have a little play. Gravity pushes the link against one side of it, so "
        "the link sits half the play away from where the motor's encoder says, on the side "
        "gravity pulls; where the gravity torque is near zero (the joint's load balanced) it "
        "floats in the middle. Modelled as play/2 · tanh(torque / 1 N·m).")
    seen_in = "gearbox backlash, about 0.1°"

    def default_sigma(self):
        return np.array([0.1 * DEG])

    def delta(self, q, theta, ctx):
        return 0.5 * theta[0] * np.tanh(ctx.gravity_torque()[:, self.j] / self.TORQUE_SCALE_NM)

    def delta_jac_params(self, q, theta, ctx):
        return 0.5 * np.tanh(ctx.gravity_torque()[:, self.j, None] / self.TORQUE_SCALE_NM)

    def delta_jac_q(self, q, theta, ctx):
        u = ctx.gravity_torque()[:, self.j] / self.TORQUE_SCALE_NM
        sech2 = 1.0 / np.cosh(u) ** 2
        return (0.5 * theta[0] * sech2 / self.TORQUE_SCALE_NM)[:, None] * \
            ctx.gravity_torque_jacobian()[:, self.j, :]


class EncoderScale(SensorEffect):
    input_is_diagonal = True
    name = "encoder_scale"
    rank = 30
    key = "scale_error"
    shape = (1,)
    units = "1 (fraction)"
    labels = ("scale",)
    bound = 0.1
    target_kind = "joint"
    summary = "encoder counts per joint revolution off"
    description = (
        "The joint's encoder gives a few more (or fewer) counts per joint revolution than "
        "the config says (a wrong gear ratio, a slipping belt): angles measured from "
        "power-up grow too fast by this fraction.")
    seen_in = "wrong gear ratio or counts per rev"

    def __init__(self, arm, target=None):
        super().__init__(arm, target)
        self.j = arm.joint_names.index(self.target)

    @property
    def streams(self):
        return ("enc",)

    def default_sigma(self):
        return np.array([1e-3])

    def apply(self, y, theta, ctx, stream):
        out = np.array(y, dtype=float, copy=True)
        out[:, self.j] *= 1.0 + theta[0]
        return out

    def jac_params(self, y, theta, ctx, stream):
        J = np.zeros(y.shape + (1,))
        J[:, self.j, 0] = y[:, self.j]
        return J

    def jac_input(self, y, theta, ctx, stream):
        d = np.ones(y.shape)
        d[:, self.j] = 1.0 + theta[0]
        return _diag(d)


# ========================================================================================
# motion and time
# ========================================================================================
class MotionAcceleration(MountEffect):
    name = "motion_acceleration"
    key = "lever_arm_offset_m"
    shape = (3,)
    units = "m"
    labels = XYZ
    bound = 0.25
    target_kind = "accelerometer"
    summary = "sensor's lever arm off: wrong centripetal and tangential acceleration"
    description = (
        "When the arm swings or the chair turns, an accelerometer feels centripetal and "
        "tangential acceleration in proportion to its distance from the axes that turn. "
        "If the sensor sits a few centimetres from where the config says, those motion "
        "terms come out wrong while standing still is unaffected. The offset is in the "
        "link's axes.")
    seen_in = "arm motion and chair driving; a sensor position measured by eye"

    @property
    def streams(self):
        return (accel_stream(self.arm, self.target),)

    def default_sigma(self):
        return np.full(3, 0.02)

    def apply_mount(self, R_LS, p_LS_m, theta):
        return R_LS, p_LS_m + theta

    def jac_params(self, ctx):
        return ctx.lever_arm_jacobian()[:, ctx.sensor(self.target)]


class TimeOffset(TimeEffect):
    name = "time_offset"
    key = "offset_s"
    shape = (1,)
    units = "s"
    labels = ("offset",)
    bound = 0.25
    target_kind = "device"
    summary = "samples stamped late (or early)"
    description = (
        "The device's samples carry a time stamp a little later than the instant they were "
        "measured (bus latency, a FIFO, buffering in the driver): what is stamped t was "
        "true at t - offset. Invisible while still; while moving it looks like the sensor "
        "lags the others.")
    seen_in = "I2C/SPI latency and FIFO buffering, a few ms"

    @property
    def streams(self):
        return device_streams(self.arm, self.target)

    def default_sigma(self):
        return np.array([0.005])


# ========================================================================================
# IMU gyro and magnetometer
# ========================================================================================
class _ImuEffect(SensorEffect):
    target_kind = "imu"
    stream_name = ""

    @property
    def streams(self):
        return (self.stream_name,)


class GyroBias(_ImuEffect):
    name = "gyro_bias"
    rank = 40
    key = "bias_rad_s"
    shape = (3,)
    units = "rad/s"
    labels = XYZ
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

    def apply(self, y, theta, ctx, stream):
        return y + theta

    def jac_params(self, y, theta, ctx, stream):
        return _eye_batch(y.shape[0], 3)


class GyroScale(_ImuEffect):
    input_is_diagonal = True
    name = "gyro_scale"
    rank = 30
    key = "scale_error"
    shape = (3,)
    units = "1 (fraction)"
    labels = XYZ
    bound = 0.15
    stream_name = "imu_gyro"
    summary = "gyro sensitivity off by a fraction"
    description = (
        "Each gyro axis turns rate into counts a little off the nominal 131 LSB per °/s: "
        "a full turn of the chair then reads as slightly more or less than 360°.")
    seen_in = "MPU-9150 sensitivity tolerance ±3 %"

    def default_sigma(self):
        return np.full(3, 0.015)

    def apply(self, y, theta, ctx, stream):
        return y * (1.0 + theta)

    def jac_params(self, y, theta, ctx, stream):
        return _diag(y)

    def jac_input(self, y, theta, ctx, stream):
        return _diag(np.broadcast_to(1.0 + theta, y.shape))


class MagHardIron(_ImuEffect):
    name = "mag_hard_iron"
    rank = 40
    key = "offset_ut"
    shape = (3,)
    units = "µT"
    labels = XYZ
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

    def apply(self, y, theta, ctx, stream):
        return y + theta

    def jac_params(self, y, theta, ctx, stream):
        return _eye_batch(y.shape[0], 3)


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


EFFECT_CLASSES = (
    AccelBias, AccelScale, AccelAxes, MountRotation, JointOffset, BaseMount, LinkCompliance,
    MotionAcceleration, TimeOffset, EncoderScale, Backlash, GyroBias, GyroScale, MagHardIron,
    MagSoftIron, MagArmDisturbance, TemperatureDrift,
)
EFFECTS: dict[str, type] = {c.name: c for c in EFFECT_CLASSES}
"""Every effect of the library, by name."""
