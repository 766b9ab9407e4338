"""The arm config's schema: the pydantic models a parsed YAML mapping is validated against,
each key with its type, bounds and the reference's words (``docs/reference/config.md`` is
written from them). Checks that need several sections at once are
:mod:`armfusion.models.arm_config_checks`; :mod:`armfusion.models.arm_config` runs both and
builds the arm.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from armfusion.models.rotations import rotation_problem
from armfusion.models.sensor_description import DEVICE_TYPES, SensorDescription, describe
from armfusion.sensors.samples import IMU_STREAMS, LINK_GYRO_SUFFIX
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
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
