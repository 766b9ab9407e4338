"""The arm model: a serial chain of revolute joints and the sensors mounted on its links.

Every arm description (modified DH, standard DH, URDF) becomes the same chain. Joint i
carries frame i-1 to frame i as

    T_{i-1,i} = T_pre_i · Rot(axis_i, q_i + offset_i) · T_post_i

- modified (Craig) DH: ``T_pre = Rx(alpha) Tx(a)``, axis z, ``T_post = Tz(d)``;
- standard DH: ``T_pre = I``, axis z, ``T_post = Tz(d) Tx(a) Rx(alpha)``;
- URDF: ``T_pre`` = the joint's origin, axis = the joint's axis, ``T_post = I``.

Link k is rigidly attached to frame k (frame 0 is the arm base); a sensor on link k
depends on joints 1..k only. Lengths are metres and angles radians inside.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Literal

import numpy as np
from armfusion.models.rotations import rot_x, rot_z, wrap_angle
from armfusion.models.sensor_description import SensorDescription, describe

DhConvention = Literal["modified", "standard", "urdf"]


def _frozen(a) -> np.ndarray:
    arr = np.array(a, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class Joint:
    name: str
    R_pre: np.ndarray  # (3, 3) rotation before the joint, in frame i-1
    p_pre_m: np.ndarray  # (3,)
    axis: np.ndarray  # (3,) unit axis, in the frame after T_pre
    R_post: np.ndarray  # (3, 3) rotation after the joint
    p_post_m: np.ndarray  # (3,)
    offset_rad: float
    min_rad: float
    max_rad: float
    counts_per_rev: float
    encoder_on_joint: bool = False
    """The encoder reads the joint itself (on its shaft): its counts per revolution are
    exact, with no gear ratio or belt between to be off (no ``encoder_scale``)."""

    @property
    def counts_per_rad(self) -> float:
        return self.counts_per_rev / (2.0 * np.pi)


@dataclass(frozen=True)
class SensorMount:
    """A sensor rigidly mounted on a link: ``R_LS`` (its axes in the link frame), ``p_L_m``."""

    name: str
    type: str
    link: int
    R_LS: np.ndarray
    p_L_m: np.ndarray
    bus: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    description: SensorDescription | None = None
    """What the sensor is and how its values arrive (default: its ``type``'s datasheet one)."""

    def __post_init__(self) -> None:
        if self.description is None:
            object.__setattr__(self, "description", describe(self.type, None, None, self.settings))

    @property
    def is_base_imu(self) -> bool:
        """An IMU on the base (link 0): the one whose streams are ``imu_*``."""
        return self.link == 0 and self.description.kind == "imu"

    @property
    def is_link_accelerometer(self) -> bool:
        return self.description.has("accelerometer") and not self.is_base_imu

    @property
    def has_link_gyro(self) -> bool:
        """A gyroscope on a link (stream ``<name>_gyro``)."""
        return self.description.has("gyroscope") and not self.is_base_imu


@dataclass(frozen=True)
class DhTable:
    """The DH parameters as the config gave them (for display), SI units."""

    convention: DhConvention
    alpha_rad: np.ndarray
    a_m: np.ndarray
    d_m: np.ndarray
    offset_rad: np.ndarray


@dataclass(frozen=True)
class JointReference:
    """A one-time joint reference a calibration rests on (``calibrate sensors --reference``):
    the joint's geometric angle an installer gave, with its sigma and where it was taken."""

    joint: str
    angle_deg: float
    sigma_deg: float
    where: str


@dataclass(frozen=True)
class CorrectionCovariance:
    """The fit's covariance of one sensor stream's correction: ``matrix_`` over the named
    model elements ``elements`` (``calibrate sensors --write`` gives it)."""

    elements: tuple[str, ...]
    matrix: np.ndarray  # (k, k), in the elements' own units


@dataclass(frozen=True)
class ArmCalibration:
    """The config's ``calibration:`` block, typed: how far the sensors' model is trusted.

    ``accel_unmodelled_g``: every accelerometer's unmodelled error, 1 sigma per axis [g],
    unless ``accel_unmodelled_g_per_sensor`` names the sensor; the base IMU's accelerometer
    uses ``imu_accel_unmodelled_g`` when given. It is an error that stays (an offset, a
    board's tilt): averaging does not lower it. ``accel_fast_error_g_per_sensor``: per
    accelerometer (the IMU's by its sensor name), the fast error one sample carries beyond
    its datasheet noise (vibration, aliasing) [g]: it joins each reading's noise and averages
    away as noise does. ``mag_unmodelled_ut``: the compass's [µT].
    ``gyro_scale_unmodelled``: the gyro's scale-and-axes error left (a fraction, 1 sigma per
    axis), where the config states it (a factory-calibrated module); None: the tracker's
    datasheet figure where the IMU is not exact
    (:func:`armfusion.fusion.tracking.calibrated.heading_scale_sigma`).
    ``correction_covariance``: per stream, what the fit could not pin. ``references``: the
    one-time joint references the calibration's joint zeros rest on;
    ``joint_zero_conventions``: the elements the calibration held to fix a gauge (its joint
    zeros and mounts are fitted relative to them). An empty block (an uncalibrated config)
    is all zeros and empty; the config loader fills in each sensor's datasheet-typical floor
    where the block gives none, and names them in ``floors_by_default`` (where each came
    from: ``{"forearm": "custom accelerometer, 0.05 g"}``).
    """

    accel_unmodelled_g: float = 0.0
    accel_unmodelled_g_per_sensor: Mapping[str, float] = field(default_factory=dict)
    accel_fast_error_g_per_sensor: Mapping[str, float] = field(default_factory=dict)
    imu_accel_unmodelled_g: float | None = None
    mag_unmodelled_ut: float = 0.0
    gyro_scale_unmodelled: float | None = None
    correction_covariance: Mapping[str, CorrectionCovariance] = field(default_factory=dict)
    references: tuple[JointReference, ...] = ()
    joint_zero_conventions: tuple[str, ...] = ()
    floors_by_default: Mapping[str, str] = field(default_factory=dict)

    def accel_floor_g(self, sensor: str) -> float:
        """A link accelerometer's unmodelled error [g]: its own, else the common one."""
        return float(self.accel_unmodelled_g_per_sensor.get(sensor, self.accel_unmodelled_g))

    def accel_fast_error_g(self, sensor: str) -> float:
        """An accelerometer's fast error beyond its datasheet noise [g] (0 unless given)."""
        return float(self.accel_fast_error_g_per_sensor.get(sensor, 0.0))

    @property
    def imu_accel_floor_g(self) -> float:
        """The base IMU accelerometer's unmodelled error [g]."""
        own = self.imu_accel_unmodelled_g
        return float(self.accel_unmodelled_g if own is None else own)

    def with_accel_floor(self, accel_unmodelled_g: float) -> ArmCalibration:
        """The same calibration with one unmodelled error for every accelerometer (the
        per-sensor ones dropped, and the base IMU's where it was a default), as ``track
        --unmodelled-g`` and the benchmarks set it."""
        imu_own = None if "imu_acc" in self.floors_by_default else self.imu_accel_unmodelled_g
        return replace(self, accel_unmodelled_g=float(accel_unmodelled_g),
                       accel_unmodelled_g_per_sensor={}, imu_accel_unmodelled_g=imu_own,
                       floors_by_default={k: v for k, v in self.floors_by_default.items() if k == "imu_mag"})

    def as_exact(self) -> ArmCalibration:
        """The same calibration with nothing unmodelled (no accelerometer floor, no compass
        floor): sensors exactly as modelled, as a simulation with noise only draws them."""
        return replace(self.with_accel_floor(0.0), imu_accel_unmodelled_g=None, mag_unmodelled_ut=0.0,
                       gyro_scale_unmodelled=None, floors_by_default={}, accel_fast_error_g_per_sensor={})


@dataclass(frozen=True)
class BaseMotion:
    """How the base moves when it does, as the tracker models its own acceleration: a
    first-order Gauss-Markov process of steady-state spread ``accel_sigma_mps2`` and
    correlation time ``accel_tau_s``. Without one the tracker's settings hold a wheelchair's
    (0.7 m/s², 5 s); an IMU held in a hand moves faster and more briefly. With
    ``speed_sigma_mps`` the base's speed is bounded too (a hand's, not a chair's that may
    cruise for minutes): the acceleration is then a velocity's derivative, with that spread
    (:attr:`armfusion.fusion.tracking.settings.TrackerSettings.base_speed_sigma_mps`)."""

    accel_sigma_mps2: float
    accel_tau_s: float
    speed_sigma_mps: float | None = None
    pivot_sigma_m: float | None = None
    """Where the base turns about a point off its origin (a hand about its wrist), the
    prior spread of the origin's offset from it, m per axis
    (:attr:`armfusion.fusion.tracking.settings.TrackerSettings.base_pivot_sigma_m`); None: no pivot."""
    turns_about: str = "vertical"
    """``vertical``: the base turns about its vertical (a chair), and the gyro's scale error
    that matters is its vertical axis's; ``any``: it turns about every axis (a hand), and
    every axis's does (:attr:`armfusion.fusion.tracking.settings.TrackerSettings.base_turns_about_any`)."""


@dataclass(frozen=True)
class FixedBase:
    """An arm bolted down (the config's ``base: fixed``): its base does not move. Its tilt
    (roll, pitch, rad) where an installer's level gave it; None: level, the link
    accelerometers reading the rest as the arm moves. ``tilt_sigma_rad``: the tilt's 1 sigma
    either way (the startup's level-base prior, :func:`armfusion.fusion.startup.problem.make_problem`)."""

    roll_rad: float | None = None
    pitch_rad: float | None = None
    tilt_sigma_rad: float = 1.0 * np.pi / 180.0


@dataclass(frozen=True)
class ArmModel:
    """A validated arm: joints, sensors, limits and poses. Built once from a config."""

    name: str
    joints: tuple[Joint, ...]
    sensors: tuple[SensorMount, ...]
    ready_pose_rad: np.ndarray
    dh: DhTable | None = None
    source: str = ""
    effects: tuple = ()
    calibration: ArmCalibration = field(default_factory=ArmCalibration)
    base_motion: BaseMotion | None = None
    magnetic_declination_deg: float | None = None
    """The site's magnetic declination (true north east of magnetic north, deg), from the
    config's ``site:`` block; None: not given, headings are from magnetic north."""
    base_from_turning_centre_m: np.ndarray | None = None
    """Where the arm's base origin sits from the point its wheelchair turns about (the
    mid-point of the drive wheels' axle), chair axes, m (the config's ``chair:`` block).
    The tracker then predicts what the chair's rotation adds to the base's acceleration
    (:mod:`armfusion.fusion.tracking.frame_kernels`); the simulator's chair turns about it. None: not
    given (the tracker's acceleration state carries that part too)."""
    fixed_base: FixedBase | None = None
    """The config's ``base: fixed`` (a bolted base: no base motion, its tilt given or read
    once); None: the base moves (a wheelchair, or as ``base_motion`` says)."""

    # -- derived views -------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def convention(self) -> str:
        return self.dh.convention if self.dh is not None else "urdf"

    @property
    def min_rad(self) -> np.ndarray:
        return np.array([j.min_rad for j in self.joints])

    @property
    def max_rad(self) -> np.ndarray:
        return np.array([j.max_rad for j in self.joints])

    @cached_property
    def _limits_middle_rad(self) -> np.ndarray:
        """Each joint's limits' middle, once per arm (the live estimate reads it every instant)."""
        return 0.5 * (self.min_rad + self.max_rad)

    @cached_property
    def _wide_joints(self) -> np.ndarray:
        """Per joint: do its limits span more than a turn (a UR's ±360°)?"""
        return (self.max_rad - self.min_rad) > 2.0 * np.pi

    def angles_in_range(self, q_rad: np.ndarray, encoder_rad: np.ndarray | None = None) -> np.ndarray:
        """Joint angles ``(..., n)`` rad, each in its joint's own range: a revolute joint at
        ``q`` and at ``q + 2 pi`` is in the same pose, and a controller reads the one inside its
        limits. A joint whose limits span at most a turn: moved by whole turns to the angle
        nearest the middle of its limits (within half a turn of it: unchanged, to the bit). A
        joint whose limits span more (one turn holds two angles inside them): the turn its
        encoder counts, ``encoder_rad`` (what the encoders read, rad, the estimate within half
        a turn of it), so the angle runs on continuously past ±180°; moved by whole turns
        only where that lies outside the limits. Without ``encoder_rad`` such a joint's angle
        is kept as it is where inside its limits."""
        q = np.asarray(q_rad, dtype=float)
        mid = self._limits_middle_rad
        d = q - mid
        out = np.where(np.abs(d) > np.pi, mid + wrap_angle(d), q)
        wide = self._wide_joints
        if not wide.any():
            return out
        ref = q if encoder_rad is None else np.asarray(encoder_rad, float) + wrap_angle(q - encoder_rad)
        lo, hi = self.min_rad, self.max_rad
        two_pi = 2.0 * np.pi
        ref = np.where(ref > hi, ref - two_pi * np.ceil((ref - hi) / two_pi), ref)
        ref = np.where(ref < lo, ref + two_pi * np.ceil((lo - ref) / two_pi), ref)
        return np.where(wide, ref, out)

    @property
    def offset_rad(self) -> np.ndarray:
        return np.array([j.offset_rad for j in self.joints])

    @property
    def counts_per_rad(self) -> np.ndarray:
        return np.array([j.counts_per_rad for j in self.joints])

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.sensors)

    def sensor(self, name: str) -> SensorMount:
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(f"arm {self.name!r} has no sensor {name!r}; it has {list(self.sensor_names)}")

    @property
    def link_accelerometers(self) -> tuple[SensorMount, ...]:
        return tuple(s for s in self.sensors if s.is_link_accelerometer)

    @property
    def imu(self) -> SensorMount | None:
        for s in self.sensors:
            if s.is_base_imu:
                return s
        return None

    def joints_seen_by(self, sensor_name: str) -> tuple[int, ...]:
        """0-based indices of the joints whose angles move this sensor."""
        return tuple(range(self.sensor(sensor_name).link))

    def within_limits(self, q_rad: np.ndarray, margin_rad: float = 0.0) -> np.ndarray:
        q = np.asarray(q_rad, dtype=float)
        return (q >= self.min_rad - margin_rad) & (q <= self.max_rad + margin_rad)

    # -- chain arrays, stacked for the batched kinematics -------------------------
    @property
    def chain(self) -> ChainArrays:
        c = self.__dict__.get("_chain")
        if c is None:
            c = ChainArrays.from_joints(self.joints)
            object.__setattr__(self, "_chain", c)
        return c


@dataclass(frozen=True)
class ChainArrays:
    R_pre: np.ndarray  # (n, 3, 3)
    p_pre_m: np.ndarray  # (n, 3)
    axis: np.ndarray  # (n, 3)
    R_post: np.ndarray  # (n, 3, 3)
    p_post_m: np.ndarray  # (n, 3)
    offset_rad: np.ndarray  # (n,)
    axis_is_z: bool  # every joint turns about its local z (DH): a faster path

    @classmethod
    def from_joints(cls, joints: tuple[Joint, ...]) -> ChainArrays:
        # a zero-joint arm (an IMU alone) has empty arrays of the same trailing shapes
        def stack(values, shape):
            return np.stack(values) if values else np.zeros((0, *shape))
        axis = stack([j.axis for j in joints], (3,))
        return cls(
            R_pre=_frozen(stack([j.R_pre for j in joints], (3, 3))),
            p_pre_m=_frozen(stack([j.p_pre_m for j in joints], (3,))),
            axis=_frozen(axis),
            R_post=_frozen(stack([j.R_post for j in joints], (3, 3))),
            p_post_m=_frozen(stack([j.p_post_m for j in joints], (3,))),
            offset_rad=_frozen(np.array([j.offset_rad for j in joints], dtype=float)),
            axis_is_z=bool(np.allclose(axis, [0.0, 0.0, 1.0])),
        )


def joints_from_dh(
    dh: DhTable,
    names: list[str],
    min_rad: np.ndarray,
    max_rad: np.ndarray,
    counts_per_rev: np.ndarray,
) -> tuple[Joint, ...]:
    """Chain joints from a DH table in its convention, each joint with its name, limits and
    encoder resolution."""
    convention, alpha_rad, a_m, d_m, offset_rad = dh.convention, dh.alpha_rad, dh.a_m, dh.d_m, dh.offset_rad
    out = []
    eye = np.eye(3)
    zero = np.zeros(3)
    z = np.array([0.0, 0.0, 1.0])
    for i, name in enumerate(names):
        Rx = rot_x(float(alpha_rad[i]))
        if convention == "modified":
            R_pre, p_pre = Rx, np.array([a_m[i], 0.0, 0.0])
            R_post, p_post = eye, np.array([0.0, 0.0, d_m[i]])
        elif convention == "standard":
            R_pre, p_pre = eye, zero
            # Tz(d) Tx(a) Rx(alpha): translation d along z then a along x, then rotate
            R_post, p_post = Rx, np.array([a_m[i], 0.0, d_m[i]])
        else:
            raise ValueError(f"unknown DH convention {convention!r}")
        out.append(
            Joint(
                name=name,
                R_pre=_frozen(R_pre),
                p_pre_m=_frozen(p_pre),
                axis=_frozen(z),
                R_post=_frozen(R_post),
                p_post_m=_frozen(p_post),
                offset_rad=float(offset_rad[i]),
                min_rad=float(min_rad[i]),
                max_rad=float(max_rad[i]),
                counts_per_rev=float(counts_per_rev[i]),
            )
        )
    return tuple(out)


def dh_transform(convention: str, alpha: float, a: float, d: float, theta: float) -> np.ndarray:
    """One 4x4 DH transform, written out plainly: the reference the chain is tested against."""

    def T(R=None, p=None):
        M = np.eye(4)
        if R is not None:
            M[:3, :3] = R
        if p is not None:
            M[:3, 3] = p
        return M

    if convention == "modified":
        return T(rot_x(alpha)) @ T(p=[a, 0, 0]) @ T(rot_z(theta)) @ T(p=[0, 0, d])
    return T(rot_z(theta)) @ T(p=[0, 0, d]) @ T(p=[a, 0, 0]) @ T(rot_x(alpha))
