"""The pieces every effect is made of: parameter blocks, stages, targets, the context.

An effect is a small object bound to one target (a sensor, a joint, the IMU, a device's
stream) that owns one named parameter block and changes one stage of a prediction:

========  =========================================================================
stage     what it changes
========  =========================================================================
joints    the geometric joint angles the kinematics uses, from the controller's ones
          (``q_geom = q + Σ delta(q)``): zero offsets, sag, gearbox play
mounts    where a sensor sits on its link, before the kinematics (lever arm)
sensor    a stream's physical value in the sensor's own axes, in a fixed physical
          order (frame, axes, scale, bias, drift), before the conversion to counts
time      the instant a stream's samples were really taken
========  =========================================================================

Every block's identity (the value that changes nothing) is zero, so the prior mean of
an effect nobody has measured yet is zero and "adding an effect" never changes a
prediction until its parameters move.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.motion import (
    DEFAULT_MASSES,
    MassModel,
    MotionState,
    gravity_torques,
    lever_arm_jacobian,
)
from armfusion.models.sensor_models import IMU_STREAM_PARTS
from armfusion.sensors.samples import link_gyro_stream

STAGES = ("joints", "mounts", "sensor", "time")
ENCODER_DEVICE = "enc"


class TargetError(ValueError):
    """An effect was bound to a target it cannot apply to (the message says which exist)."""


@dataclass(frozen=True)
class ParamBlock:
    """One named parameter block: ``acc3.mount_rotation``, its key in config files
    (``rotvec_rad``), shape, units, prior and bounds (flat arrays of ``size``)."""

    name: str
    effect: str
    target: str
    key: str
    shape: tuple[int, ...]
    units: str
    labels: tuple[str, ...]
    prior_mean: np.ndarray
    prior_sigma: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def element_names(self) -> list[str]:
        """``acc3.mount_rotation[x]``… one per element, for tables and reports."""
        return [f"{self.name}[{lab}]" for lab in self.labels]


def accelerometer_names(arm: ArmModel) -> tuple[str, ...]:
    names = tuple(s.name for s in arm.link_accelerometers)
    return names + ((arm.imu.name,) if arm.imu is not None else ())


def accel_stream(arm: ArmModel, sensor: str) -> str:
    """The stream of an accelerometer: the link accelerometer's name, or ``imu_acc``."""
    return "imu_acc" if arm.imu is not None and sensor == arm.imu.name else sensor


def device_names(arm: ArmModel) -> tuple[str, ...]:
    """Devices whose samples share an instant: each accelerometer, the IMU, the encoders."""
    return accelerometer_names(arm) + (ENCODER_DEVICE,)


def device_streams(arm: ArmModel, device: str) -> tuple[str, ...]:
    """The streams one device gives, as its description says: the base IMU's parts
    (``imu_acc``, ``imu_gyro``, and ``imu_mag``, ``imu_temp`` when it has them); a link
    sensor's accelerometer and, when it has one, its gyroscope (``<name>_gyro``)."""
    imu = arm.imu
    if imu is not None and device == imu.name:
        return tuple(s for s, part in IMU_STREAM_PARTS.items() if imu.description.has(part))
    if device in arm.sensor_names and arm.sensor(device).has_link_gyro:
        return (device, link_gyro_stream(device))
    return (device,)


TARGET_KINDS = {
    "link_accelerometer": ("a link accelerometer",
                           lambda arm: tuple(s.name for s in arm.link_accelerometers)),
    "accelerometer": ("an accelerometer (a link accelerometer or the IMU)", accelerometer_names),
    "imu": ("the base IMU", lambda arm: (arm.imu.name,) if arm.imu is not None else ()),
    "joint": ("a joint", lambda arm: arm.joint_names),
    "geared_joint": ("a joint whose encoder turns through a gear or belt (not arm.joints.encoder_on_joint)",
                     lambda arm: tuple(j.name for j in arm.joints if not j.encoder_on_joint)),
    "device": ("a sensor device (an accelerometer, the IMU, or the encoders 'enc')", device_names),
}


class Context:
    """What an effect may read while it changes a prediction; filled in stage by stage.

    ``state`` is the input motion; ``q_geom`` the geometric joint angles after the joint
    stage; ``lm``/``sm`` the link and sensor motion of the kinematics (sensor order in
    ``sensor_index``); ``earth_field_0_ut`` Earth's field in base axes ``(N, 3)``.
    """

    def __init__(self, arm: ArmModel, state: MotionState, masses: MassModel = DEFAULT_MASSES,
                 earth_field_W_ut: np.ndarray | None = None):
        self.arm = arm
        self.state = state
        self.masses = masses
        self.q_geom: np.ndarray = state.q_rad
        self.q_torque: np.ndarray = state.q_rad
        """The angles the gravity torque is evaluated at: the controller's plus the joints'
        zero offsets (the model sets it after the offsets; gravity pulls on a link where it
        really stands, not where the controller's zero says)."""
        self.lm = None
        self.sm = None
        self.sensor_index: dict[str, int] = {}
        self._tau = None
        self._dtau = None
        self._lever = None
        B = np.zeros(3) if earth_field_W_ut is None else np.asarray(earth_field_W_ut, float)
        self.earth_field_0_ut = np.einsum("nji,j->ni", state.R_WB, B)

    @property
    def N(self) -> int:
        return self.state.N

    def set_torque_angles(self, q_rad: np.ndarray) -> None:
        """Evaluate the gravity torque at ``q_rad (N, n)`` from now on."""
        self.q_torque = q_rad
        self._tau = self._dtau = None

    def gravity_torque(self) -> np.ndarray:
        """Static gravity torque on every joint at ``q_torque``, N·m ``(N, n)``."""
        if self._tau is None:
            self._tau = gravity_torques(self.arm, self.q_torque, self.state.up_0, self.masses)
        return self._tau

    def gravity_torque_jacobian(self) -> np.ndarray:
        """``dτ/dq (N, n, n)`` at ``q_torque``."""
        if self._dtau is None:
            self._tau, self._dtau = gravity_torques(self.arm, self.q_torque, self.state.up_0,
                                                    self.masses, jacobian=True)
        return self._dtau

    def sensor(self, name: str) -> int:
        return self.sensor_index[name]

    def lever_arm_jacobian(self) -> np.ndarray:
        """``df/dp_LS`` of every sensor in ``sm``, g per m, ``(N, S, 3, 3)`` (memoised)."""
        if self._lever is None:
            self._lever = lever_arm_jacobian(self.sm, self.lm)
        return self._lever


class Effect:
    """Base of every effect: one target, one parameter block, one stage.

    Subclasses set the class attributes below and implement their stage's methods.
    """

    name: ClassVar[str]
    stage: ClassVar[str]
    rank: ClassVar[int] = 0  # order inside the stage (physical order of the signal chain)
    key: ClassVar[str]
    shape: ClassVar[tuple[int, ...]]
    units: ClassVar[str]
    labels: ClassVar[tuple[str, ...]]
    target_kind: ClassVar[str]
    summary: ClassVar[str]
    description: ClassVar[str]
    seen_in: ClassVar[str]
    nonnegative: ClassVar[bool] = False
    bound: ClassVar[float] = np.inf

    def __init__(self, arm: ArmModel, target: str | None = None):
        self.arm = arm
        valid = self.valid_targets(arm)
        what = TARGET_KINDS[self.target_kind][0]
        if not valid:
            raise TargetError(f"{self.name} applies to {what}, and arm {arm.name!r} has none")
        if target is None:
            if len(valid) != 1:
                raise TargetError(f"{self.name} needs a target: {what}, one of {', '.join(valid)}")
            target = valid[0]
        if target not in valid:
            raise TargetError(f"{self.name} applies to {what}: one of {', '.join(valid)}; "
                              f"not {target!r}")
        self.target = target
        self._sigma = None

    # -- targets and streams -------------------------------------------------------------
    @classmethod
    def valid_targets(cls, arm: ArmModel) -> tuple[str, ...]:
        return TARGET_KINDS[cls.target_kind][1](arm)

    @property
    def streams(self) -> tuple[str, ...]:
        """The raw streams whose prediction this effect changes."""
        raise NotImplementedError

    # -- the parameter block -----------------------------------------------------------
    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def block_name(self) -> str:
        return f"{self.target}.{self.name}"

    def default_sigma(self) -> np.ndarray:
        """Datasheet-typical 1-σ magnitude of every element (flat)."""
        raise NotImplementedError

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        hi = np.full(self.size, float(self.bound))
        lo = np.zeros(self.size) if self.nonnegative else -hi
        return lo, hi

    def block(self, sigma: np.ndarray | None = None) -> ParamBlock:
        lo, hi = self.bounds()
        s = self.default_sigma() if sigma is None else np.broadcast_to(np.asarray(sigma, float), (self.size,))
        return ParamBlock(self.block_name, self.name, self.target, self.key, tuple(self.shape),
                          self.units, tuple(self.labels), np.zeros(self.size),
                          np.array(s, dtype=float), lo, hi)

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """Parameters drawn at datasheet-typical magnitudes (for ``--realistic``), flat."""
        lo, hi = self.bounds()
        x = rng.standard_normal(self.size) * self.default_sigma()
        if self.nonnegative:
            x = np.abs(x)
        return np.clip(x, lo, hi)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.block_name})"


# ----------------------------------------------------------------------------------------
class JointEffect(Effect):
    """Adds a small angle to joint ``target``'s geometric angle: ``q_geom[j] += delta``."""

    stage = "joints"
    target_kind = "joint"

    def __init__(self, arm: ArmModel, target: str | None = None):
        super().__init__(arm, target)
        self.j = arm.joint_names.index(self.target)

    @property
    def streams(self) -> tuple[str, ...]:
        # every accelerometer beyond the joint
        out = [s.name for s in self.arm.link_accelerometers if s.link > self.j]
        return tuple(out)

    def delta(self, q: np.ndarray, theta: np.ndarray, ctx: Context) -> np.ndarray:
        """The change of joint j's geometric angle, rad, ``(N,)``."""
        raise NotImplementedError

    def delta_jac_params(self, q, theta, ctx) -> np.ndarray:
        """``d delta / d theta``, ``(N, p)``."""
        raise NotImplementedError

    def delta_jac_q(self, q, theta, ctx) -> np.ndarray | None:
        """``d delta / d q``, ``(N, n)``, or None where delta does not depend on q."""
        return None

    # the uniform value-in, value-out view (for tests and for estimators)
    def apply(self, q: np.ndarray, theta: np.ndarray, ctx: Context) -> np.ndarray:
        out = np.array(q, dtype=float, copy=True)
        out[:, self.j] += self.delta(q, theta, ctx)
        return out

    def jac_params(self, q, theta, ctx) -> np.ndarray:
        J = np.zeros((q.shape[0], q.shape[1], self.size))
        J[:, self.j, :] = self.delta_jac_params(q, theta, ctx)
        return J

    def jac_input(self, q, theta, ctx) -> np.ndarray | None:
        d = self.delta_jac_q(q, theta, ctx)
        if d is None:
            return None
        A = np.broadcast_to(np.eye(q.shape[1]), (q.shape[0], q.shape[1], q.shape[1])).copy()
        A[:, self.j, :] += d
        return A


class MountEffect(Effect):
    """Changes where a sensor sits on its link (its lever arm), before the kinematics."""

    stage = "mounts"

    def apply_mount(self, R_LS: np.ndarray, p_LS_m: np.ndarray, theta: np.ndarray):
        raise NotImplementedError

    def jac_params(self, ctx: Context) -> np.ndarray:
        """``d reading / d theta`` for the sensor's stream, ``(N, 3, p)`` (in g per unit)."""
        raise NotImplementedError


class SensorEffect(Effect):
    """Changes a stream's physical value ``y (N, k)`` in the sensor's own axes."""

    stage = "sensor"
    input_is_diagonal: ClassVar[bool] = False  # jac_input is diagonal (a per-axis scale)

    def apply(self, y: np.ndarray, theta: np.ndarray, ctx: Context, stream: str) -> np.ndarray:
        raise NotImplementedError

    def jac_params(self, y, theta, ctx, stream) -> np.ndarray:
        """``dy'/dtheta``, ``(N, k, p)``."""
        raise NotImplementedError

    def jac_input(self, y, theta, ctx, stream) -> np.ndarray | None:
        """``dy'/dy``, ``(N, k, k)``; None means the identity."""
        return None

    def jac_q(self, y, theta, ctx, stream) -> np.ndarray | None:
        """``dy'/dq_geom``, ``(N, k, n)``, for effects that depend on the arm's pose."""
        return None


class TimeEffect(Effect):
    """Shifts the instant a device's samples were taken: stamped t, measured at t - offset."""

    stage = "time"
