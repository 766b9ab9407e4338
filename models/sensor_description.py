"""A sensor described by what it is, not assumed: its kind, and for each of its sensing
parts the quantity it measures, the units its values arrive in, their scale, range,
resolution and noise.

A config sensor names a device (``type``): a datasheet description below (ADXL345,
MPU-9150, MPU-6050, an analog triaxial accelerometer through an ADC), which its
``outputs`` may override part by part (a logger that stored the MPU-6050's values in g
rounded to 0.01, a gyro set to ±1000 °/s), or ``custom``, described wholly by ``kind`` and
``outputs``. Everything downstream works from these descriptions: the count models of
:mod:`armfusion.models.sensor_models` (gain, zero, noise, range, resolution), hence the simulator,
the startup, the identification, the tracker and the workbench.

Kinds: ``accelerometer`` (one part, ``accelerometer``), ``gyroscope``, ``magnetometer``,
and ``imu`` (an accelerometer and a gyroscope, with or without a magnetometer and a
temperature sensor). On link 0 an ``imu`` is the base IMU (streams ``imu_acc``,
``imu_gyro``, ``imu_mag``, ``imu_temp``); on a link, a sensor's accelerometer is a link
accelerometer (stream ``<name>``) and its gyroscope a link gyroscope (``<name>_gyro``).

A part's numbers, with the units they are in:

- ``units``: of the delivered values: ``counts`` (register counts) or a unit of the part's
  quantity (:mod:`armfusion.sensors.units`: ``g``, ``m/s^2``, ``deg/s``, ``rad/s``, ``uT``…);
- ``scale`` (counts per ``scale_unit``, for counts only) and ``zero`` (the delivered value
  at zero, in the delivered units);
- ``range``: ± full scale in the datasheet unit (``g``, ``deg/s``, ``uT``, ``degC``); or
  ``limits``: the delivered values' own (min, max), e.g. a register's -512…511;
- ``resolution``: the step of the delivered values (1 count; 0.01 for values stored rounded
  to 0.01; 0 for none);
- noise: ``noise_density`` in the datasheet unit per √Hz (rms at a rate = density ·
  √(bandwidth), the bandwidth ``bandwidth_hz`` or else half the rate), or ``noise_rms`` in
  the datasheet unit at ``noise_rate_hz`` (scaled by √(rate / noise_rate_hz); without a
  rate, the same at every rate); one number or one per axis. ``noise_unit``: the
  delivered units instead of the datasheet unit (an ADXL345's noise is given in LSB);
- ``delay_s``: the part's delay: a value delivered at ``t`` is the quantity at ``t -
  delay_s`` (a digital low-pass filter's group delay, from its datasheet table; a part that
  decimates by averaging delivers its output period's mean, half a period late). 0 (the
  default): the value at its own instant. The simulator draws it; the tracker turns the
  attitude by the gyroscope's rate over each interval accordingly (docs/tracking.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from armfusion.sensors.units import COUNTS, UnitError, canonical_unit_name, factor, quantity_of

KINDS: dict[str, tuple[str, ...]] = {
    # kind: (parts it must have, ...) ; optional parts are listed in OPTIONAL_PARTS
    "accelerometer": ("accelerometer",),
    "gyroscope": ("gyroscope",),
    "magnetometer": ("magnetometer",),
    "imu": ("accelerometer", "gyroscope"),
}
OPTIONAL_PARTS: dict[str, tuple[str, ...]] = {"imu": ("magnetometer", "temperature")}
PART_QUANTITY: dict[str, str] = {"accelerometer": "acceleration", "gyroscope": "angular_rate",
                                 "magnetometer": "magnetic_field", "temperature": "temperature"}
DATASHEET_UNIT: dict[str, str] = {"accelerometer": "g", "gyroscope": "deg/s", "magnetometer": "uT",
                                  "temperature": "degC"}
"""The unit a datasheet gives each part's range, scale and noise in."""
CANONICAL_UNIT: dict[str, str] = {"accelerometer": "g", "gyroscope": "rad/s", "magnetometer": "uT",
                                  "temperature": "degC"}
"""The unit armfusion computes each part's physical value in."""
AXES: dict[str, int] = {"accelerometer": 3, "gyroscope": 3, "magnetometer": 3, "temperature": 1}


@dataclass(frozen=True)
class PartDescription:
    """How one sensing part's values arrive (see the module's docstring for each field)."""

    part: str
    units: str
    scale: float | None = None
    scale_unit: str | None = None
    zero: float = 0.0
    range: float | None = None
    limits: tuple[float, float] | None = None
    resolution: float = 0.0
    noise_density: tuple[float, ...] | None = None
    noise_rms: tuple[float, ...] | None = None
    noise_rate_hz: float | None = None
    noise_unit: str | None = None
    bandwidth_hz: float | None = None
    rate_hz: float | None = None
    delay_s: float = 0.0

    @property
    def quantity(self) -> str:
        return PART_QUANTITY[self.part]

    @property
    def counts(self) -> bool:
        return self.units == COUNTS

    def gain(self) -> float:
        """Delivered values per canonical unit (counts per g, deg/s per rad/s…)."""
        canonical = CANONICAL_UNIT[self.part]
        if self.counts:
            return self.scale / factor(self.scale_unit, canonical)
        return factor(canonical, self.units)

    def value_limits(self) -> tuple[float, float] | None:
        """The (min, max) a delivered value can take: past them no such device reads."""
        if self.limits is not None:
            return self.limits
        if self.range is None:
            return None
        top = self.range * (self.scale * factor(DATASHEET_UNIT[self.part], self.scale_unit) if self.counts
                            else factor(DATASHEET_UNIT[self.part], self.units))
        return (self.zero - top, self.zero + top)

    def noise(self, rate_hz: float) -> np.ndarray:
        """Per axis, the rms noise of one delivered value at ``rate_hz``, in delivered units."""
        n = AXES[self.part]
        if self.noise_unit is not None and self.noise_unit == self.units:
            per_noise_unit = 1.0
        else:
            per_noise_unit = (self.scale * factor(DATASHEET_UNIT[self.part], self.scale_unit) if self.counts
                              else factor(DATASHEET_UNIT[self.part], self.units))
        if self.noise_density is not None:
            band = self.bandwidth_hz if self.bandwidth_hz is not None else rate_hz / 2
            rms = np.asarray(self.noise_density, float) * np.sqrt(band)
        elif self.noise_rms is not None:
            rms = np.asarray(self.noise_rms, float)
            if self.noise_rate_hz is not None:
                rms = rms * np.sqrt(rate_hz / self.noise_rate_hz)
        else:
            rms = np.zeros(1)
        return np.broadcast_to(rms * per_noise_unit, (n,)).copy()


@dataclass(frozen=True)
class SensorDescription:
    """A device: its kind and its parts, by part name."""

    device: str
    kind: str
    parts: Mapping[str, PartDescription] = field(default_factory=dict)

    def has(self, part: str) -> bool:
        return part in self.parts

    def part(self, part: str) -> PartDescription:
        try:
            return self.parts[part]
        except KeyError:
            raise KeyError(f"the {self.device} ({self.kind}) has no {part}; it has "
                           f"{', '.join(self.parts)}") from None


def _counts(part: str, scale: float, limits: tuple[float, float], **kw) -> PartDescription:
    return PartDescription(part, COUNTS, scale=scale, scale_unit=DATASHEET_UNIT[part], limits=limits,
                           resolution=1.0, **kw)


# --- ADXL345 (link accelerometers), 10-bit, ±2 g ---------------------------------------
ADXL345_LSB_PER_G = 256.0
"""Nominal sensitivity at ±2 g, 10-bit (datasheet: 230 min, 282 max)."""
ADXL345_NOISE_LSB_RMS_AT_100HZ = np.array([0.75, 0.75, 1.1])
"""Datasheet noise at 100 Hz output rate, x/y/z (290 / 430 µg/√Hz)."""
ADXL345_COUNTS = (-512, 511)

# --- InvenSense MPU-9150 and MPU-6050 (the same accelerometer and gyroscope die) --------
MPU9150_ACCEL_LSB_PER_G = 16384.0
"""At ±2 g."""
MPU9150_ACCEL_NOISE_G_PER_SQRT_HZ = 400e-6
MPU9150_GYRO_LSB_PER_DPS = 131.0
"""At ±250 °/s."""
MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ = 0.005
INT16 = (-32768, 32767)
MPU9150_TEMP_LSB_PER_C = 340.0
MPU9150_TEMP_OFFSET_C = 35.0
MPU6050_TEMP_OFFSET_C = 36.53
"""The MPU-6050's register map: °C = raw / 340 + 36.53."""
MPU9150_TEMP_NOISE_C_RMS = 0.02
"""Not in the datasheet: a few LSB of register jitter (our assumption)."""

# --- AK8975 magnetometer (inside the MPU-9150) ------------------------------------------
AK8975_UT_PER_LSB = 0.3
AK8975_COUNTS = (-4096, 4095)
AK8975_NOISE_UT_RMS = 0.6
"""Not in the datasheet (it gives none): about two LSB, typical of measured AK89xx parts."""

# --- analog triaxial sensor (the sensor-calibration article's Microstrain 3DM taps) ------
ANALOG_TRIAX_VOLTS_PER_G = 1.25
"""0-5 V output for ±2 g: 1.25 V/g (the article's S ≈ 0.127 V·s²/m)."""
ANALOG_TRIAX_ZERO_G_VOLTS = 2.5
ANALOG_TRIAX_ADC_COUNTS_PER_VOLT = 8192 / 10.0
"""The article's Quanser Q8 board: 14-bit, ±10 V."""
ANALOG_TRIAX_NOISE_V_RMS = np.array([0.0134, 0.0136, 0.0146])
"""The article's measured rms noise of its three accelerometers (at 1 kHz)."""
ADC14_COUNTS = (-8192, 8191)


def _invensense(temp_offset_c: float, magnetometer: bool) -> SensorDescription:
    parts = {
        "accelerometer": _counts("accelerometer", MPU9150_ACCEL_LSB_PER_G, INT16,
                                 noise_density=(MPU9150_ACCEL_NOISE_G_PER_SQRT_HZ,)),
        "gyroscope": _counts("gyroscope", MPU9150_GYRO_LSB_PER_DPS, INT16,
                             noise_density=(MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ,)),
    }
    if magnetometer:
        parts["magnetometer"] = _counts("magnetometer", 1.0 / AK8975_UT_PER_LSB, AK8975_COUNTS,
                                        noise_rms=(AK8975_NOISE_UT_RMS,))
    parts["temperature"] = PartDescription(
        "temperature", COUNTS, scale=MPU9150_TEMP_LSB_PER_C, scale_unit="degC",
        zero=-temp_offset_c * MPU9150_TEMP_LSB_PER_C, limits=INT16, resolution=1.0,
        noise_rms=(MPU9150_TEMP_NOISE_C_RMS,))
    return SensorDescription("mpu9150" if magnetometer else "mpu6050", "imu", parts)


DEVICES: dict[str, SensorDescription] = {
    "adxl345": SensorDescription("adxl345", "accelerometer", {
        "accelerometer": _counts("accelerometer", ADXL345_LSB_PER_G, ADXL345_COUNTS,
                                 noise_rms=tuple(ADXL345_NOISE_LSB_RMS_AT_100HZ.tolist()),
                                 noise_rate_hz=100.0, noise_unit=COUNTS)}),
    # accelerometer ±2 g, gyroscope ±250 °/s, AK8975 magnetometer, temperature
    "mpu9150": _invensense(MPU9150_TEMP_OFFSET_C, magnetometer=True),
    # the MPU-9150 without the magnetometer
    "mpu6050": _invensense(MPU6050_TEMP_OFFSET_C, magnetometer=False),
}
"""The datasheet descriptions a config's ``type`` names (``analog_triax`` is made from the
sensor's ``settings``: :func:`analog_triax`; ``custom`` from ``kind`` and ``outputs``)."""

DEVICE_TYPES: tuple[str, ...] = (*DEVICES, "analog_triax", "custom")


def analog_triax(settings: Mapping[str, Any]) -> SensorDescription:
    """The sensor-calibration article's Microstrain 3DM taps: 0-5 V for ±2 g (1.25 V/g, 2.5 V
    at 0 g) through a 14-bit ±10 V ADC (819.2 counts per volt), its measured noise per axis;
    each constant overridable by ``settings`` (``volts_per_g``, ``zero_g_volts``,
    ``adc_counts_per_volt``, ``accel_noise_v``)."""
    cpv = float(settings.get("adc_counts_per_volt", ANALOG_TRIAX_ADC_COUNTS_PER_VOLT))
    vpg = float(settings.get("volts_per_g", ANALOG_TRIAX_VOLTS_PER_G))
    zero_v = float(settings.get("zero_g_volts", ANALOG_TRIAX_ZERO_G_VOLTS))
    noise_v = np.broadcast_to(np.asarray(settings.get("accel_noise_v", ANALOG_TRIAX_NOISE_V_RMS), float),
                              (3,))
    part = PartDescription("accelerometer", COUNTS, scale=vpg * cpv, scale_unit="g", zero=zero_v * cpv,
                           limits=ADC14_COUNTS, resolution=1.0,
                           noise_rms=tuple((noise_v * cpv).tolist()), noise_unit=COUNTS)
    return SensorDescription("analog_triax", "accelerometer", {"accelerometer": part})


UNMODELLED_FLOOR: dict[str, dict[str, float]] = {
    # an uncalibrated ADXL345: 0 g offset ±35 mg (x, y) / ±40 mg (z), sensitivity ±1 %,
    # cross-axis ±1 %, a board glued 1-3° off (about 35 mg at 1 g): about 45 mg together
    "adxl345": {"accelerometer": 0.045},
    # an uncalibrated MPU-9150 / MPU-6050: initial tolerance ±80 mg x/y, ±150 mg z (σ taken
    # as half), sensitivity ±3 %, cross-axis ±2 %, a board 1-3° off: about 60 mg together;
    # its AK8975 compass near a chair's motors and steel: hard iron of the order of 15 µT
    "mpu9150": {"accelerometer": 0.06, "magnetometer": 15.0},
    "mpu6050": {"accelerometer": 0.06},
    # the article's taps, uncalibrated: their zero and gain through the ADC are the analog
    # part's few percent
    "analog_triax": {"accelerometer": 0.05},
    # a MEMS part of no known datasheet, as the class comes: zero-g offset ±40-60 mg,
    # sensitivity ±2-4 %, a mount 1-2° off; a compass as the MPU-9150's
    "custom": {"accelerometer": 0.05, "magnetometer": 15.0},
}
"""Per device and part, the error its model leaves when nothing of it is calibrated, 1 sigma
per axis, in the part's datasheet unit (g, µT): the unmodelled-error floor the startup and
the tracker take where the config's ``calibration:`` block gives none
(:func:`armfusion.models.arm_config` fills it in; ``docs/config.md``, *Unmodelled-error floors*)."""


def unmodelled_floor(device: str, part: str) -> float:
    """The datasheet-typical unmodelled error of ``device``'s ``part`` (see
    :data:`UNMODELLED_FLOOR`; a device or part it does not name: the ``custom`` one's)."""
    return float(UNMODELLED_FLOOR.get(device, {}).get(part, UNMODELLED_FLOOR["custom"][part]))


PART_KEYS = ("units", "scale", "scale_unit", "zero", "range", "limits", "resolution", "noise_density",
             "noise_rms", "noise_rate_hz", "noise_unit", "bandwidth_hz", "rate_hz", "delay_s")
MAX_DELAY_S = 1.0
"""A part's ``delay_s`` is below this (a filter's delay is milliseconds; a second is a typo)."""


def describe(device: str, kind: str | None, outputs: Mapping[str, Mapping[str, Any]] | None,
             settings: Mapping[str, Any] | None = None) -> SensorDescription:
    """The description of a config sensor: the device's datasheet one (or ``custom``'s
    nothing) with ``outputs`` laid over it part by part. Raises ValueError naming the
    part and key of the first thing wrong."""
    outputs = dict(outputs or {})
    if device == "analog_triax":
        base = analog_triax(settings or {})
    elif device == "custom":
        if kind is None:
            raise ValueError("a custom sensor needs its kind (accelerometer, gyroscope, magnetometer, imu)")
        base = SensorDescription("custom", kind, {})
    elif device in DEVICES:
        base = DEVICES[device]
    else:
        raise ValueError(f"unknown device {device!r}; known: {', '.join(DEVICE_TYPES)}")
    if kind is not None and kind != base.kind:
        if kind not in KINDS:
            raise ValueError(f"unknown kind {kind!r}; known: {', '.join(KINDS)}")
        raise ValueError(f"kind {kind!r} does not match the {device}, which is an {base.kind}")
    kind = base.kind
    allowed = KINDS[kind] + OPTIONAL_PARTS.get(kind, ())
    parts = dict(base.parts)
    for name, given in outputs.items():
        if name not in allowed:
            raise ValueError(f"outputs.{name}: an {kind} has no {name} (its parts: {', '.join(allowed)})")
        parts[name] = _part(name, parts.get(name), given)
    missing = [p for p in KINDS[kind] if p not in parts]
    if missing:
        raise ValueError(f"outputs: an {kind} needs {' and '.join(missing)} described (units at least)")
    return SensorDescription(device, kind, {p: parts[p] for p in allowed if p in parts})


def _part(name: str, base: PartDescription | None, given: Mapping[str, Any]) -> PartDescription:
    """Part ``name`` of a sensor: ``given``'s keys checked and laid over ``base`` (the device's
    part, None for one described from scratch). Raises ValueError naming the first key wrong."""
    unknown = [k for k in given if k not in PART_KEYS]
    if unknown:
        raise ValueError(f"outputs.{name}.{unknown[0]}: not a part's key (known: {', '.join(PART_KEYS)})")
    kw: dict[str, Any] = {key: given[key] for key in PART_KEYS if key in given}
    where = f"outputs.{name}"
    for check in _KEY_CHECKS:
        check(kw, name, base, where)
    return _checked_part(_laid_over(name, base, kw), name, where)


def _check_units(kw: dict[str, Any], name: str, base: PartDescription | None, where: str) -> None:
    """``units``: a known unit of the part's quantity (or counts); needed for a new part."""
    if "units" in kw:
        try:
            kw["units"] = canonical_unit_name(kw["units"])
            q = quantity_of(kw["units"])
        except UnitError as e:
            raise ValueError(f"{where}.units: {e}") from None
        if q is not None and q != PART_QUANTITY[name]:
            raise ValueError(f"{where}.units: {kw['units']} is a unit of {q}, not of "
                             f"{PART_QUANTITY[name]} (the {name}'s)")
    elif base is None:
        raise ValueError(f"{where}.units: needed (counts, or a unit of {PART_QUANTITY[name]})")


def _check_noise(kw: dict[str, Any], name: str, base: PartDescription | None, where: str) -> None:
    """``noise_density``, ``noise_rms``: one number or one per axis, finite and >= 0."""
    for key in ("noise_density", "noise_rms"):
        if key in kw:
            v = kw[key]
            vals = (v,) if isinstance(v, int | float) else tuple(v)
            if len(vals) not in (1, AXES[name]) or not all(isinstance(x, int | float) and math.isfinite(x)
                                                           and x >= 0 for x in vals):
                raise ValueError(f"{where}.{key}: one number or one per axis, each finite and >= 0")
            kw[key] = tuple(float(x) for x in vals)


def _check_limits(kw: dict[str, Any], name: str, base: PartDescription | None, where: str) -> None:
    """``limits``: [min, max] of the delivered values."""
    if "limits" in kw:
        lim = kw["limits"]
        if not (isinstance(lim, list | tuple) and len(lim) == 2 and lim[0] < lim[1]):
            raise ValueError(f"{where}.limits: [min, max] of the delivered values, min below max")
        kw["limits"] = (float(lim[0]), float(lim[1]))


def _check_numbers(kw: dict[str, Any], name: str, base: PartDescription | None, where: str) -> None:
    """The positive numbers (scale, range, the rates, the bandwidth), the delay, the resolution."""
    for key in ("scale", "range", "bandwidth_hz", "rate_hz", "noise_rate_hz"):
        if key in kw and not (isinstance(kw[key], int | float) and math.isfinite(kw[key]) and kw[key] > 0):
            raise ValueError(f"{where}.{key}: a positive number")
    if "delay_s" in kw and not (isinstance(kw["delay_s"], int | float) and not isinstance(kw["delay_s"], bool)
                                and 0.0 <= kw["delay_s"] < MAX_DELAY_S):
        raise ValueError(f"{where}.delay_s: seconds, >= 0 and below {MAX_DELAY_S:g} (a filter's delay)")
    if "resolution" in kw and not (isinstance(kw["resolution"], int | float) and kw["resolution"] >= 0):
        raise ValueError(f"{where}.resolution: a number >= 0 (0: not rounded)")


def _check_unit_names(kw: dict[str, Any], name: str, base: PartDescription | None, where: str) -> None:
    """``noise_unit``, ``scale_unit``: known units, by their canonical names."""
    for key in ("noise_unit", "scale_unit"):
        if key in kw:
            try:
                kw[key] = canonical_unit_name(kw[key])
            except UnitError as e:
                raise ValueError(f"{where}.{key}: {e}") from None


_KEY_CHECKS = (_check_units, _check_noise, _check_limits, _check_numbers, _check_unit_names)
"""A part's key checks in the order they are made (each canonicalises the keys it checks)."""


def _laid_over(name: str, base: PartDescription | None, kw: dict[str, Any]) -> PartDescription:
    """The checked keys ``kw`` laid over ``base``: delivered in other units than the device's
    registers, the registers' scale, limits, zero and resolution no longer apply; a noise
    given one way replaces the other."""
    part = PartDescription(name, kw.pop("units")) if base is None else base
    if "units" in kw and kw["units"] != part.units:
        # delivered in other units than the device's registers: the register's scale, limits,
        # zero and resolution no longer apply (range, noise in datasheet units still do)
        rms, unit = part.noise_rms, part.noise_unit
        if rms is not None and unit is not None and unit == part.units and part.counts:
            # the register noise given in counts: in the datasheet's unit now
            per = part.scale * factor(DATASHEET_UNIT[name], part.scale_unit)
            rms, unit = tuple(v / per for v in rms), None
        part = replace(part, units=kw.pop("units"), scale=None, scale_unit=None, zero=0.0, limits=None,
                       resolution=0.0, noise_rms=rms, noise_unit=unit)
    if "noise_density" in kw:
        part = replace(part, noise_rms=None, noise_rate_hz=None, noise_unit=None)
    elif "noise_rms" in kw:
        part = replace(part, noise_density=None, noise_rate_hz=None, noise_unit=None)
    return replace(part, **kw)


def _checked_part(part: PartDescription, name: str, where: str) -> PartDescription:
    """The part as a whole: one delivering counts has its scale (in the datasheet's unit
    where none is given); its noise is in the datasheet's unit or the delivered one."""
    if part.counts:
        if part.scale is None:
            raise ValueError(f"{where}.scale: a part delivering counts needs its scale (counts per "
                             f"{DATASHEET_UNIT[name]})")
        if part.scale_unit is None:
            part = replace(part, scale_unit=DATASHEET_UNIT[name])
        if quantity_of(part.scale_unit) != PART_QUANTITY[name]:
            raise ValueError(f"{where}.scale_unit: {part.scale_unit} is not a unit of {PART_QUANTITY[name]}")
    if part.noise_unit is not None and part.noise_unit not in (part.units, DATASHEET_UNIT[name]):
        raise ValueError(f"{where}.noise_unit: {part.noise_unit}; the noise is given in the datasheet's "
                         f"{DATASHEET_UNIT[name]} or in the delivered {part.units}")
    return part
