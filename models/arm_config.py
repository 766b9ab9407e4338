"""Arm config schema and validation: a parsed YAML mapping in, an :class:`ArmModel` out.

Validation runs once, here, and reports every problem together, each naming the file,
the key and the bad value. File reading lives in ``armfusion.fusion.configfile`` (models do no I/O).

Units are in the key names: ``_deg``, ``_mm``. Inside the model everything is SI.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Annotated, Any, Literal

import numpy as np
from armfusion.models.arm import (
    ArmCalibration,
    ArmModel,
    BaseMotion,
    CorrectionCovariance,
    DhTable,
    FixedBase,
    Joint,
    JointReference,
    SensorMount,
    joints_from_dh,
)
from armfusion.models.rotations import DEG, rotation_problem
from armfusion.models.sensor_description import DEVICE_TYPES, SensorDescription, describe, unmodelled_floor
from armfusion.sensors.csv_blocks import CsvLimits
from armfusion.sensors.samples import IMU_STREAMS, LINK_GYRO_SUFFIX, clipped_repr
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

MAX_LENGTH_MM = 100_000.0
"""A length of the arm or a sensor's position is below 100 m (any arm a chair carries is
under 2 m: a larger number is a unit slip, mm for µm, or a typo)."""
MAX_ANGLE_DEG = 3600.0
"""A DH angle, a joint limit or pose is within ten turns of zero."""
COUNTS_PER_REV_RANGE = (1.0, 2.0**32)
"""An encoder counts at least once and at most 2^32 times a turn (a 32-bit counter's
revolution; the finest rotary encoders count 2^29)."""
FEED_COUNTS = 2**31 - 1
"""Counts the encoder feed holds either way (``armfusion.sensors.encoders``: int32 per joint)."""
STREAM_NAMES_TAKEN = frozenset({"t", "enc", "true_q", "true_base", *IMU_STREAMS})
"""Names of a recording's own streams and columns (:mod:`armfusion.sensors.samples`): no sensor may
take one (its stream would be another's)."""


def _bounded(v: list[float], bound: float, unit: str) -> list[float]:
    """``v`` when every entry is within ``±bound``, else a ``ValueError`` naming the first."""
    for i, x in enumerate(v):
        if not abs(x) <= bound:
            raise ValueError(f"entry {i} is {x!r} {unit}; at most ±{bound:g} {unit}")
    return v


@dataclass(frozen=True)
class ConfigProblem:
    source: str
    key: str
    value: Any
    message: str

    def __str__(self) -> str:
        # a value is quoted short: a list of a million numbers, or what a YAML alias
        # expands to, must not become a message of megabytes
        got = "" if self.value is None else f" (got {clipped_repr(self.value, 60)})"
        return f"{self.source}: {self.key}: {self.message}{got}"


class ConfigError(ValueError):
    """Every problem found in one config, reported together."""

    def __init__(self, problems: list[ConfigProblem]):
        self.problems = problems
        n = len(problems)
        head = f"{n} problem{'s' if n != 1 else ''} in arm config"
        super().__init__(head + ":\n" + "\n".join(f"  - {p}" for p in problems))


class _Strict(BaseModel):
    # every number finite: d_mm: .inf is a typo, not an arm
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False,
                              use_attribute_docstrings=True)  # the reference's words


class DhSection(_Strict):
    convention: Literal["modified", "standard"]
    """modified (Craig): T = Rx(alpha) Tx(a) Rz(q + offset) Tz(d);
    standard: T = Rz(q + offset) Tz(d) Tx(a) Rx(alpha)."""
    alpha_deg: list[float]
    """Link twist, one entry per joint."""
    a_mm: list[float]
    """Link length, one entry per joint."""
    d_mm: list[float]
    """Link offset along the joint axis, one entry per joint."""
    offset_deg: list[float] | None = None
    """Joint angle offset, one entry per joint (zeros by default)."""

    @field_validator("a_mm", "d_mm")
    @classmethod
    def _length(cls, v: list[float]) -> list[float]:
        return _bounded(v, MAX_LENGTH_MM, "mm")

    @field_validator("alpha_deg", "offset_deg")
    @classmethod
    def _angle(cls, v: list[float] | None) -> list[float] | None:
        return v if v is None else _bounded(v, MAX_ANGLE_DEG, "deg")


class JointsSection(_Strict):
    names: list[str] | None = None
    """The joints' names (j1, j2, ... by default), one per joint, unique."""
    min_deg: list[float]
    """Lower joint limit, one per joint."""
    max_deg: list[float]
    """Upper joint limit, one per joint, above the lower."""
    counts_per_rev: list[float]
    """Encoder counts per joint revolution, one per joint."""
    encoder_on_joint: list[StrictBool] | None = None
    """Per joint, true where the encoder reads the joint itself (its counts exact); default
    false: through a gear or belt, whose ratio may be off."""

    @field_validator("counts_per_rev")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        lo, hi = COUNTS_PER_REV_RANGE
        bad = [(i, x) for i, x in enumerate(v) if not lo <= x <= hi]
        if bad:
            i, x = bad[0]
            raise ValueError(f"counts per revolution must be from 1 to 2^32; entry {i} is {x!r}")
        return v

    @field_validator("min_deg", "max_deg")
    @classmethod
    def _angle(cls, v: list[float]) -> list[float]:
        return _bounded(v, MAX_ANGLE_DEG, "deg")

    @field_validator("names")
    @classmethod
    def _unique(cls, v: list[str] | None) -> list[str] | None:
        twice = sorted({x for x in v or [] if v.count(x) > 1})
        if twice:
            raise ValueError(f"joint names must be unique; {', '.join(map(repr, twice))} is given twice")
        return v


class BusSection(_Strict):
    kind: Literal["i2c", "spi"]
    """The bus the device is on."""
    bus: StrictInt = Field(ge=0, le=255)
    """The bus number (/dev/i2c-N, /dev/spidevN.x)."""
    address: StrictInt | None = Field(default=None, ge=0, le=0x7F)
    """An I2C device's 7-bit address."""
    chip_select: StrictInt | None = Field(default=None, ge=0, le=255)
    """An SPI device's chip select."""


class SensorSection(_Strict):
    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=64)
    """The sensor's name: its streams' and CSV columns' prefix (acc1_x, ...)."""
    type: str
    """The device: adxl345, mpu9150, mpu6050, analog_triax or custom."""
    kind: str | None = None
    """accelerometer, gyroscope, magnetometer or imu (the device's by default; a custom sensor needs it)."""
    link: StrictInt
    """0: the base; k: rigid with link k (moved by joints 1..k)."""
    rotation: list[list[float]] = Field(default_factory=lambda: np.eye(3).tolist())
    """R_LS: the sensor's axes in the link frame (a proper rotation)."""
    position_mm: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    """The sensor's origin in the link frame."""
    bus: BusSection | None = None
    """Where the driver reads it: {kind: spi, bus: 0, chip_select: 0} or
    {kind: i2c, bus: 1, address: 0x53}."""
    settings: dict[str, Any] = Field(default_factory=dict)
    """Device settings (an analog_triax's volts per unit and ADC)."""
    outputs: dict[str, dict[str, Any]] | None = None
    """Per part (accelerometer, gyroscope, magnetometer, temperature), how its values arrive
    where they differ from the device's datasheet (:mod:`armfusion.models.sensor_description`)."""

    @field_validator("type")
    @classmethod
    def _known_type(cls, v: str) -> str:
        if v not in DEVICE_TYPES:
            raise ValueError(f"unknown sensor type; known types are {', '.join(DEVICE_TYPES)}")
        return v

    @model_validator(mode="after")
    def _described(self) -> SensorSection:
        self.description()
        return self

    def description(self) -> SensorDescription:
        """What the sensor is (its device's datasheet description with ``outputs`` laid over)."""
        return describe(self.type, self.kind, self.outputs, self.settings)

    @field_validator("rotation")
    @classmethod
    def _rotation(cls, v: list[list[float]]) -> list[list[float]]:
        why = rotation_problem(np.array(v, dtype=float) if _rect(v) else np.zeros((0,)))
        if why:
            raise ValueError(f"mounting rotation {why}")
        return v

    @field_validator("position_mm")
    @classmethod
    def _three(cls, v: list[float]) -> list[float]:
        if len(v) != 3:
            raise ValueError(f"a position has 3 entries, not {len(v)}")
        return _bounded(v, MAX_LENGTH_MM, "mm")

    @field_validator("name")
    @classmethod
    def _not_a_stream(cls, v: str) -> str:
        if v in STREAM_NAMES_TAKEN or v.startswith("true_") or v.endswith(LINK_GYRO_SUFFIX):
            raise ValueError(f"a recording's own stream is called {v!r} (t, enc, true_q, true_base, "
                             f"imu_acc…, a name ending in {LINK_GYRO_SUFFIX!r} or starting with 'true_'); "
                             "name the sensor otherwise")
        return v


COVARIANCE_ROUNDING = 1e-4
"""How negative, relative to its largest, a covariance's least eigenvalue may be: the file
holds 6 significant digits, so a fit's (semi-definite where an element is held) covariance
comes back with eigenvalues off by some 1e-6 of its largest per element."""


def _not_indefinite(m: np.ndarray) -> bool:
    """Is the (symmetric to 6 digits) ``m`` a covariance: no eigenvalue below zero by more
    than :data:`COVARIANCE_ROUNDING` of the largest."""
    eig = np.linalg.eigvalsh((m + m.T) / 2.0)
    return bool(eig[0] >= -COVARIANCE_ROUNDING * max(float(eig[-1]), 0.0))


def _rect(v) -> bool:
    return isinstance(v, list) and all(isinstance(r, list) and len(r) == len(v[0]) for r in v)


class EffectEntry(_Strict):
    effect: str
    """The effect's name in the effects library."""
    target: str | None = None
    """What it acts on: a sensor, a stream or a joint, as the effect takes."""
    params: dict[str, Any] = Field(default_factory=dict)
    """Its parameters' values, by name."""
    sigma: dict[str, Any] = Field(default_factory=dict)
    """Their 1-sigma uncertainties, by name, where calibrated."""
    note: str | None = None
    """Free text."""


UnmodelledG = Annotated[float, Field(ge=0.0, le=1.0)]
"""An accelerometer's unmodelled error, 1 sigma per axis, in g: 0 to 1 g (more than
gravity itself would make the sensor useless)."""


class CovarianceEntry(_Strict):
    """One stream's correction covariance, as ``calibrate sensors --write`` gives it."""

    elements: list[str]
    matrix: list[list[float]]

    @model_validator(mode="after")
    def _square(self) -> CovarianceEntry:
        n = len(self.elements)
        if len(self.matrix) != n or any(len(row) != n for row in self.matrix):
            raise ValueError(f"matrix must be {n} x {n}, one row and column per element")
        m = np.array(self.matrix, dtype=float) if n else np.zeros((0, 0))
        # the file holds 6 significant digits: symmetric to that
        scale = float(np.abs(np.diag(m)).max()) if n else 0.0
        if n and (np.any(np.diag(m) < 0) or not np.allclose(m, m.T, rtol=1e-4, atol=1e-9 * scale)):
            raise ValueError("matrix must be symmetric with a non-negative diagonal (a covariance)")
        if n and not _not_indefinite(m):
            raise ValueError("matrix must be positive semi-definite (a covariance: no combination of "
                             "the elements has a negative variance)")
        return self


class ReferenceRecord(_Strict):
    """A one-time joint reference the calibration rests on (``calibrate sensors --reference``):
    the joint's geometric angle the installer gave, where, and how the fit's check came out."""

    joint: str
    angle_deg: float
    sigma_deg: float = Field(gt=0.0)
    t_start_s: float
    t_end_s: float
    where: str
    fitted_deg: float | None = None
    fitted_sigma_deg: float | None = Field(default=None, ge=0.0)
    without_reference_deg: float | None = None
    without_reference_sigma_deg: float | None = Field(default=None, ge=0.0)
    z: float | None = None
    contradicted: bool = False
    message: str | None = None


class IdentifiedRecord(_Strict):
    """What the fit that calibrated this config did (written by ``calibrate sensors``)."""

    mode: str | None = None
    samples: int | None = Field(default=None, ge=0)
    chi2_red: float | None = Field(default=None, ge=0.0)
    held: list[str] = Field(default_factory=list)
    joint_zero_conventions: list[str] = Field(default_factory=list)
    references: list[ReferenceRecord] = Field(default_factory=list)


class CalibrationSection(_Strict):
    """The ``calibration:`` block: how far the sensors' model is to be trusted."""

    accel_unmodelled_g: UnmodelledG | None = None
    """Every accelerometer's unmodelled error, 1 sigma per axis."""
    accel_unmodelled_g_per_sensor: dict[str, UnmodelledG] | None = None
    """A link accelerometer's (or the IMU's), by sensor name, in place of the common one."""
    imu_accel_unmodelled_g: UnmodelledG | None = None
    """The base IMU accelerometer's unmodelled error (the common one by default)."""
    accel_fast_error_g_per_sensor: dict[str, UnmodelledG] | None = None
    """Per accelerometer (link or IMU, by sensor name), the fast error one sample carries
    beyond the sensor's datasheet noise (a motor's vibration, aliasing), 1 sigma per axis:
    it joins each reading's noise and averages away as noise does; the unmodelled error is
    what stays."""
    mag_unmodelled_ut: float | None = Field(default=None, ge=0.0, le=1000.0)
    """What the compass's horizontal reading may be off Earth's field, 1 sigma."""
    gyro_scale_unmodelled: float | None = Field(default=None, ge=0.0, le=0.5)
    """The gyro's scale-and-axes error left, a fraction, 1 sigma per axis."""
    correction_covariance: dict[str, CovarianceEntry] | None = None
    """Per stream, the fit's covariance of its correction (written by calibrate sensors)."""
    identified: IdentifiedRecord | None = None
    """What the fit that calibrated this config did (written by calibrate sensors)."""


class ArmSection(_Strict):
    name: str
    """The arm's name."""
    description: str | None = None
    """Free text."""
    source: str | None = None
    """Where the numbers come from (free text)."""
    dh: DhSection | None = None
    """The DH table (or `urdf`)."""
    urdf: str | None = None
    """A URDF file, relative to this config (or `dh`)."""
    joints: JointsSection
    """Limits and encoders, one entry per joint."""
    ready_pose_deg: list[float]
    """The park pose, inside the limits."""


class BaseMotionSection(_Strict):
    """The ``base_motion:`` block: how the base moves (its acceleration's spread and
    correlation time; optionally its speed's spread, where the speed is bounded, the spread
    of the point it turns about, and whether it turns about its vertical only or about every
    axis), where it is not a wheelchair."""

    accel_sigma_mps2: float = Field(gt=0.0, le=200.0)
    """The base acceleration's steady-state spread."""
    accel_tau_s: float = Field(gt=0.0, le=3600.0)
    """How long an acceleration lasts (correlation time)."""
    speed_sigma_mps: float | None = Field(default=None, gt=0.0, le=100.0)
    """The base speed's steady-state spread per axis, where it is bounded (a hand's)."""
    pivot_sigma_m: float | None = Field(default=None, gt=0.0, le=10.0)
    """The prior spread of the origin's offset from the point the base turns about."""
    turns_about: Literal["vertical", "any"] = "vertical"
    """vertical: a chair's turns; any: a hand's."""


class SiteSection(_Strict):
    """The ``site:`` block: where the chair is used. ``magnetic_declination_deg``: true
    north's angle from magnetic north, degrees, east positive (a chart or NOAA's calculator
    gives it); with it the heading is from true north."""

    magnetic_declination_deg: float = Field(ge=-180.0, le=180.0)
    """True north's angle from magnetic north, east positive."""


class ChairSection(_Strict):
    """The ``chair:`` block: the wheelchair the arm rides on. ``base_from_turning_centre_mm``:
    where the arm's base origin sits from the point the chair turns about (the mid-point
    of its drive wheels' axle, on the ground), in the chair's axes (parallel to the arm
    base's), millimetres. With it the tracker predicts the acceleration the chair's own
    rotation gives the arm's base (``ω̇ x ρ + ω x (ω x ρ)``, from the gyro), and its
    acceleration state holds only the turning centre's (a turn on the spot gives none)."""

    base_from_turning_centre_mm: list[float]
    """The arm base's origin from the chair's turning centre, chair axes (x forward, y left, z up)."""

    @field_validator("base_from_turning_centre_mm")
    @classmethod
    def _lever(cls, v: list[float]) -> list[float]:
        if len(v) != 3:
            raise ValueError(f"a position has 3 entries, not {len(v)}")
        if not all(np.isfinite(x) and abs(x) <= 5000.0 for x in v):
            raise ValueError("each entry must be a finite number of mm within ±5000 (a wheelchair's size)")
        return v


class FixedBaseSection(_Strict):
    """The ``base:`` block of an arm bolted down (``base: fixed`` is the short form): its
    base never moves, so the tracker holds no base acceleration and lets its tilt take no
    random walk. ``roll_deg``, ``pitch_deg``: the base's tilt where an installer's level
    gave it, to ``tilt_sigma_deg`` (1 sigma, default 0.1°); without them the base is level to
    ``tilt_sigma_deg`` (default 1°: a floor or table levelled as built), and the link
    accelerometers read the rest."""

    mount: Literal["fixed"]
    """fixed: the base is bolted down."""
    roll_deg: float | None = Field(default=None, ge=-90.0, le=90.0)
    """The base's roll, where an installer's level gave it."""
    pitch_deg: float | None = Field(default=None, ge=-90.0, le=90.0)
    """The base's pitch, where an installer's level gave it."""
    tilt_sigma_deg: float | None = Field(default=None, gt=0.0, le=10.0)
    """How well the tilt is known, 1 sigma (0.1° with a level, 1° without)."""

    @model_validator(mode="before")
    @classmethod
    def _short_form(cls, v: Any) -> Any:
        return {"mount": v} if isinstance(v, str) else v

    @model_validator(mode="after")
    def _both(self) -> FixedBaseSection:
        if (self.roll_deg is None) != (self.pitch_deg is None):
            raise ValueError("give both roll_deg and pitch_deg (the base's tilt), or neither")
        return self


class ArmConfigFile(_Strict):
    arm: ArmSection
    """The arm's kinematics, joints and encoders."""
    sensors: list[SensorSection]
    """Every sensor: what it is, where it sits, how its values arrive."""
    effects: list[EffectEntry] = Field(default_factory=list)
    """The calibrated physical effects."""
    calibration: CalibrationSection = Field(default_factory=CalibrationSection)
    """How far the sensors' model is trusted."""
    base_motion: BaseMotionSection | None = None
    """How the base moves, where it is not a wheelchair."""
    site: SiteSection | None = None
    """Where the chair is used."""
    chair: ChairSection | None = None
    """Where the wheelchair turns."""
    base: FixedBaseSection | None = None
    """A base bolted down (`base: fixed`), where it is not a chair."""

    @model_validator(mode="after")
    def _fixed_base_alone(self) -> ArmConfigFile:
        if self.base is not None and (self.base_motion is not None or self.chair is not None):
            raise ValueError("base: fixed: a bolted base has no base_motion or chair block")
        return self


def _loc(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _get(data: Any, loc: tuple) -> Any:
    for part in loc:
        try:
            data = data[part]
        except (KeyError, IndexError, TypeError):
            return None
    return data


MAX_SENSORS = (CsvLimits.max_columns - 1) // 3
"""Sensors a config may hold: a recording of them fits the recording CSV's columns (``t`` and at
least three a sensor)."""


def _friendly(msg: str) -> str:
    return msg.removeprefix("Value error, ")


def validate_config_dict(
    data: Any, source: str, urdf_joints: tuple[Joint, ...] | None = None
) -> tuple[ArmConfigFile | None, list[ConfigProblem]]:
    """Structural (pydantic) and cross-field checks; returns the parsed file and problems."""
    problems: list[ConfigProblem] = []
    parsed: ArmConfigFile | None = None
    if not isinstance(data, dict):
        return None, [ConfigProblem(source, "(top level)", type(data).__name__,
                                    "an arm config is a mapping with keys arm, sensors")]
    sensors = data.get("sensors")
    if isinstance(sensors, list) and len(sensors) > MAX_SENSORS:  # (checking each would take minutes)
        return None, [ConfigProblem(source, "sensors", None, (
            f"{len(sensors)} sensors, more than a recording holds: each has at least 3 columns, and a "
            f"recording CSV at most {CsvLimits.max_columns} (so at most {MAX_SENSORS} sensors)"))]
    try:
        parsed = ArmConfigFile.model_validate(data)
    except ValidationError as e:
        for err in e.errors():
            key = _loc(err["loc"]) or "(top level)"
            value = err.get("input") if err["type"] != "missing" else None
            if err["type"] == "missing":
                problems.append(ConfigProblem(source, key, None, "required key is missing"))
            elif err["type"] == "extra_forbidden":
                problems.append(ConfigProblem(source, key, value, "unknown key"))
            else:
                problems.append(ConfigProblem(source, key, value, _friendly(err["msg"])))
    problems.extend(_cross_checks(data, source, urdf_joints))
    return parsed, problems


def _cross_checks(data: dict, source: str, urdf_joints) -> list[ConfigProblem]:
    """Checks that need several keys at once; tolerant of a structurally broken file."""
    out: list[ConfigProblem] = []
    arm = data.get("arm") if isinstance(data.get("arm"), dict) else {}
    dh = arm.get("dh") if isinstance(arm.get("dh"), dict) else None
    joints = arm.get("joints") if isinstance(arm.get("joints"), dict) else {}
    if dh is None and not arm.get("urdf"):
        out.append(ConfigProblem(source, "arm", None, "give either arm.dh (a DH table) or arm.urdf"))
    if dh is not None and arm.get("urdf"):
        out.append(ConfigProblem(source, "arm", "dh and urdf", "give arm.dh or arm.urdf, not both"))
    n = None
    if dh is not None and isinstance(dh.get("alpha_deg"), list):
        n = len(dh["alpha_deg"])
        for key in ("a_mm", "d_mm", "offset_deg"):
            v = dh.get(key)
            if isinstance(v, list) and len(v) != n:
                out.append(ConfigProblem(source, f"arm.dh.{key}", v,
                                         f"has {len(v)} entries; alpha_deg has {n}"))
    elif urdf_joints is not None:
        n = len(urdf_joints)
    if n is not None:
        for key in ("min_deg", "max_deg", "counts_per_rev", "names", "encoder_on_joint"):
            v = joints.get(key)
            if isinstance(v, list) and len(v) != n:
                out.append(ConfigProblem(source, f"arm.joints.{key}", v,
                                         f"has {len(v)} entries; the arm has {n} joints"))
        ready = arm.get("ready_pose_deg")
        if isinstance(ready, list) and len(ready) != n:
            out.append(ConfigProblem(source, "arm.ready_pose_deg", ready,
                                     f"has {len(ready)} entries; the arm has {n} joints"))
    lo, hi = joints.get("min_deg"), joints.get("max_deg")
    if _numlist(lo) and _numlist(hi) and len(lo) == len(hi):
        for i, (a, b) in enumerate(zip(lo, hi, strict=True)):
            if a >= b:
                out.append(ConfigProblem(source, f"arm.joints.min_deg[{i}]", a,
                                         f"lower limit is not below the upper limit {b}"))
        cpr = joints.get("counts_per_rev")
        if _numlist(cpr) and len(cpr) == len(lo):
            for i, (a, b, c) in enumerate(zip(lo, hi, cpr, strict=True)):
                if c * (b - a) / 360.0 > FEED_COUNTS:  # relative counts: either way from power-up
                    out.append(ConfigProblem(source, f"arm.joints.counts_per_rev[{i}]", c,
                                             f"the joint's {b - a:g}° are {c * (b - a) / 360.0:.3g} counts, "
                                             f"more than the encoder feed's int32 holds either side of "
                                             f"where it powered up ({FEED_COUNTS})"))
        ready = arm.get("ready_pose_deg")
        if _numlist(ready) and len(ready) == len(lo):
            for i, r in enumerate(ready):
                if not lo[i] <= r <= hi[i]:
                    out.append(ConfigProblem(source, f"arm.ready_pose_deg[{i}]", r,
                                             f"outside joint limits [{lo[i]}, {hi[i]}] deg"))
    sensors = data.get("sensors")
    if isinstance(sensors, list):
        seen: dict[str, int] = {}
        wired: dict[tuple, int] = {}  # (kind, bus, chip select or address) -> the sensor on it
        for k, s in enumerate(sensors):
            if not isinstance(s, dict):
                continue
            bus = s.get("bus")
            if isinstance(bus, dict):
                spot = (bus.get("kind"), bus.get("bus"),
                        bus.get("chip_select") if bus.get("kind") == "spi" else bus.get("address"))
                if None not in spot and all(isinstance(x, str | int) for x in spot):
                    if spot in wired:
                        what = "chip select" if spot[0] == "spi" else "address"
                        out.append(ConfigProblem(source, f"sensors[{k}].bus", bus,
                                                 f"the {spot[0].upper()} bus {spot[1]} {what} {spot[2]} is "
                                                 f"sensors[{wired[spot]}]'s already: one device each"))
                    wired.setdefault(spot, k)
            name = s.get("name")
            if isinstance(name, str) and name.startswith("imu") and _role(s) in ("link", "other"):
                out.append(ConfigProblem(source, f"sensors[{k}].name", s["name"],
                                         "a name starting with 'imu' is the base IMU's streams' (imu_acc…) "
                                         "in a recording; name a sensor on a link otherwise"))
            name = s.get("name")
            if isinstance(name, str):
                if name in seen:
                    out.append(ConfigProblem(source, f"sensors[{k}].name", name,
                                             f"duplicate sensor name (also sensors[{seen[name]}])"))
                seen[name] = k
            link = s.get("link")
            if isinstance(link, int) and n is not None and not 0 <= link <= n:
                out.append(ConfigProblem(source, f"sensors[{k}].link", link,
                                         f"link index out of range: 0 (base) to {n}"))
            desc = _description_or_none(s)
            if desc is not None and isinstance(link, int):
                if desc.has("magnetometer") and link != 0:
                    out.append(ConfigProblem(source, f"sensors[{k}].link", link,
                                             f"a magnetometer ({s.get('type')}) is read only as part of the "
                                             "base IMU, on link 0 (the base)"))
                if link == 0 and desc.kind in ("gyroscope", "magnetometer"):
                    out.append(ConfigProblem(source, f"sensors[{k}].kind", desc.kind,
                                             "on the base, a gyroscope or magnetometer is read as part of "
                                             "an IMU (kind imu, with its accelerometer)"))
            bus = s.get("bus")
            if isinstance(bus, dict):
                if bus.get("kind") == "i2c" and bus.get("address") is None:
                    out.append(ConfigProblem(source, f"sensors[{k}].bus.address", None,
                                             "an I2C device needs an address"))
                if bus.get("kind") == "spi" and bus.get("chip_select") is None:
                    out.append(ConfigProblem(source, f"sensors[{k}].bus.chip_select", None,
                                             "an SPI device needs a chip_select"))
        roles = [(s.get("name"), _role(s)) for s in sensors if isinstance(s, dict)]
        accels = [nm for nm, role in roles if role == "link"]
        imus = [nm for nm, role in roles if role == "base_imu"]
        if not accels and all(role is not None for _, role in roles) and n != 0:
            # an arm with joints needs a link accelerometer to read them; a zero-joint arm
            # (an IMU alone, docs/tracking-hand.md) needs only its base IMU
            out.append(ConfigProblem(source, "sensors", len(sensors),
                                     "the arm has no link accelerometer"))
        if n == 0 and not imus and all(role is not None for _, role in roles):
            out.append(ConfigProblem(source, "sensors", len(sensors),
                                     "an arm with no joints needs a base IMU (an imu on link 0)"))
        if len(imus) > 1:
            out.append(ConfigProblem(source, "sensors", ", ".join(map(str, imus)),
                                     "more than one IMU on the base (link 0); the base has one"))
        cal = data.get("calibration")
        if isinstance(cal, dict):
            # per sensor: by the sensor's name (the IMU's too); covariances: by stream
            for key, allowed in (("accel_unmodelled_g_per_sensor", accels + imus),
                                 ("accel_fast_error_g_per_sensor", accels + imus),
                                 ("correction_covariance", accels + ["imu_acc"] * bool(imus))):
                given = cal.get(key)
                if isinstance(given, dict):
                    for name in given:
                        if name not in allowed:
                            out.append(ConfigProblem(
                                source, f"calibration.{key}.{name}", name,
                                "no such accelerometer in sensors (it has "
                                f"{', '.join(map(str, allowed)) or 'none'})"))
    return out


def _description_or_none(s: dict) -> SensorDescription | None:
    """A config sensor's description, or None where its own check will say what is wrong."""
    try:
        return describe(s.get("type"), s.get("kind"), s.get("outputs") if isinstance(s.get("outputs"), dict)
                        else None, s.get("settings") if isinstance(s.get("settings"), dict) else {})
    except (ValueError, TypeError, AttributeError):
        return None


def _role(s: dict) -> str | None:
    """``base_imu``, ``link`` (carries an accelerometer), ``other``; None when undescribable."""
    desc = _description_or_none(s)
    if desc is None:
        return None
    if desc.kind == "imu" and s.get("link") == 0:
        return "base_imu"
    return "link" if desc.has("accelerometer") else "other"


def _numlist(v) -> bool:
    """A list of finite numbers (a NaN or an infinity is said once, by the field's own check)."""
    return isinstance(v, list) and all(isinstance(x, int | float) and np.isfinite(x) for x in v)


def build_arm(
    data: Any, source: str, urdf_joints: tuple[Joint, ...] | None = None
) -> ArmModel:
    """Validate a parsed config mapping and build the arm model (raises :class:`ConfigError`)."""
    parsed, problems = validate_config_dict(data, source, urdf_joints)
    if problems or parsed is None:
        raise ConfigError(problems)
    arm = parsed.arm
    js = arm.joints
    dh_table = None
    if arm.dh is not None:
        n = len(arm.dh.alpha_deg)
        names = js.names or [f"j{i + 1}" for i in range(n)]
        offset = np.array(arm.dh.offset_deg or [0.0] * n) * DEG
        alpha = np.array(arm.dh.alpha_deg) * DEG
        a_m = np.array(arm.dh.a_mm) / 1000.0
        d_m = np.array(arm.dh.d_mm) / 1000.0
        dh_table = DhTable(arm.dh.convention, alpha, a_m, d_m, offset)
        joints = joints_from_dh(dh_table, names, np.array(js.min_deg) * DEG, np.array(js.max_deg) * DEG,
                                np.array(js.counts_per_rev))
    else:
        assert urdf_joints is not None
        names = js.names or [j.name for j in urdf_joints]
        joints = tuple(
            Joint(
                name=names[i], R_pre=j.R_pre, p_pre_m=j.p_pre_m, axis=j.axis, R_post=j.R_post,
                p_post_m=j.p_post_m, offset_rad=0.0, min_rad=js.min_deg[i] * DEG,
                max_rad=js.max_deg[i] * DEG, counts_per_rev=js.counts_per_rev[i],
            )
            for i, j in enumerate(urdf_joints)
        )
    if js.encoder_on_joint is not None:
        joints = tuple(replace(j, encoder_on_joint=bool(on))
                       for j, on in zip(joints, js.encoder_on_joint, strict=True))
    sensors = tuple(
        SensorMount(
            name=s.name, type=s.type, link=s.link,
            R_LS=_ro(np.array(s.rotation, dtype=float)),
            p_L_m=_ro(np.array(s.position_mm, dtype=float) / 1000.0),
            bus=s.bus.model_dump() if s.bus else {}, settings=dict(s.settings), description=s.description(),
        )
        for s in parsed.sensors
    )
    return ArmModel(
        name=arm.name, joints=joints, sensors=sensors,
        ready_pose_rad=_ro(np.array(arm.ready_pose_deg) * DEG), dh=dh_table, source=source,
        effects=tuple(parsed.effects),
        calibration=_calibration(parsed.calibration, sensors),
        base_motion=(None if parsed.base_motion is None else
                     BaseMotion(parsed.base_motion.accel_sigma_mps2, parsed.base_motion.accel_tau_s,
                                parsed.base_motion.speed_sigma_mps, parsed.base_motion.pivot_sigma_m,
                                parsed.base_motion.turns_about)),
        magnetic_declination_deg=(None if parsed.site is None else parsed.site.magnetic_declination_deg),
        base_from_turning_centre_m=(
            None if parsed.chair is None
            else _ro(np.array(parsed.chair.base_from_turning_centre_mm, dtype=float) / 1000.0)),
        fixed_base=_fixed_base(parsed.base),
    )


def _fixed_base(section: FixedBaseSection | None) -> FixedBase | None:
    if section is None:
        return None
    given = section.roll_deg is not None
    sigma_deg = section.tilt_sigma_deg or (LEVELLED_TILT_SIGMA_DEG if given else LEVEL_AS_BUILT_SIGMA_DEG)
    return FixedBase(roll_rad=section.roll_deg * DEG if given else None,
                     pitch_rad=section.pitch_deg * DEG if given else None,
                     tilt_sigma_rad=sigma_deg * DEG)


LEVELLED_TILT_SIGMA_DEG = 0.1
"""A bolted base's tilt read with an installer's level (a machinist's level: 0.1°), 1 sigma."""
LEVEL_AS_BUILT_SIGMA_DEG = 1.0
"""A bolted base's tilt from level where no level was read: a floor or a table as built
(within about a degree), 1 sigma."""


def _default_floors(section: CalibrationSection, sensors: tuple[SensorMount, ...]) -> tuple[dict, dict]:
    """The unmodelled-error floors the block does not give, each sensor's datasheet-typical
    one (:data:`armfusion.models.sensor_description.UNMODELLED_FLOOR`): ``({key: value}, {key: where
    from})``, keys a link accelerometer's name, ``imu_acc``, ``imu_mag``. A floor the block
    gives, even 0 (sensors as exact as modelled), is never replaced."""
    values: dict[str, float] = {}
    said: dict[str, str] = {}
    given = section.accel_unmodelled_g_per_sensor or {}
    for s in sensors:
        if s.is_link_accelerometer and section.accel_unmodelled_g is None and s.name not in given:
            values[s.name] = unmodelled_floor(s.description.device, "accelerometer")
            said[s.name] = f"{s.description.device} accelerometer, {values[s.name]:g} g"
        if s.is_base_imu:
            if section.accel_unmodelled_g is None and section.imu_accel_unmodelled_g is None \
                    and s.name not in given:
                values["imu_acc"] = unmodelled_floor(s.description.device, "accelerometer")
                said["imu_acc"] = f"{s.description.device} accelerometer, {values['imu_acc']:g} g"
            if s.description.has("magnetometer") and section.mag_unmodelled_ut is None:
                values["imu_mag"] = unmodelled_floor(s.description.device, "magnetometer")
                said["imu_mag"] = f"{s.description.device} magnetometer, {values['imu_mag']:g} uT"
    return values, said


def _calibration(section: CalibrationSection, sensors: tuple[SensorMount, ...] = ()) -> ArmCalibration:
    """The validated ``calibration:`` block as the typed object the estimators read, each
    floor it does not give the sensor's datasheet-typical one (:func:`_default_floors`)."""
    identified = section.identified
    defaults, said = _default_floors(section, sensors)
    per_sensor = dict(section.accel_unmodelled_g_per_sensor or {})
    per_sensor.update({k: v for k, v in defaults.items() if k not in ("imu_acc", "imu_mag")})
    return ArmCalibration(
        accel_unmodelled_g=float(section.accel_unmodelled_g or 0.0),
        accel_unmodelled_g_per_sensor=per_sensor,
        accel_fast_error_g_per_sensor=dict(section.accel_fast_error_g_per_sensor or {}),
        imu_accel_unmodelled_g=defaults.get("imu_acc", section.imu_accel_unmodelled_g),
        mag_unmodelled_ut=float(defaults.get("imu_mag", section.mag_unmodelled_ut or 0.0)),
        floors_by_default=said,
        gyro_scale_unmodelled=(None if section.gyro_scale_unmodelled is None
                               else float(section.gyro_scale_unmodelled)),
        correction_covariance={
            stream: CorrectionCovariance(tuple(c.elements), _ro(np.array(c.matrix, dtype=float)))
            for stream, c in (section.correction_covariance or {}).items()},
        references=tuple(JointReference(r.joint, r.angle_deg, r.sigma_deg, r.where)
                         for r in (identified.references if identified else ())),
        joint_zero_conventions=tuple(identified.joint_zero_conventions if identified else ()),
    )


def _ro(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a
