"""What each sensor outputs, in counts: datasheet constants, count conversion, noise.

A measurement model here is the last, fixed step of a prediction: a physical value in a
sensor's own axes (specific force in g, angular rate in rad/s, magnetic field in µT,
temperature in °C, joint angle in rad) becomes register counts by a nominal gain and
zero, then (only when simulating) noise, rounding and saturation. Everything that makes
a real sensor differ from its datasheet (bias, scale, axis directions, drift…) is an
effect (:mod:`models.effects`), applied to the physical value before this step, so that
it stays estimable. The physical values themselves are what ideal sensors read
(:func:`models.motion.sensor_motion`): the accelerometer's specific force and the compass's
heading are written once, compiled, in :mod:`models.sensor_kernels`.

Streams and their models (names as in :mod:`sensors.samples`):

=============  ==========================================================================
``<acc>``      ADXL345, 10-bit at ±2 g: 256 LSB/g nominal (datasheet 230-282), noise
               0.75 LSB rms on x/y and 1.1 LSB on z at 100 Hz, counts -512…511. Or an
               ``analog_triax`` (the sensor-calibration article's 3DM): volts through an
               ADC, its constants from the sensor's ``settings``.
``imu_acc``    MPU-9150 accelerometer at ±2 g: 16384 LSB/g, 400 µg/√Hz, int16.
``imu_gyro``   MPU-9150 gyroscope at ±250 °/s: 131 LSB per °/s, 0.005 °/s/√Hz, int16.
``imu_mag``    AK8975 (inside the MPU-9150): 0.3 µT/LSB, 13-bit (-4096…4095), already
               in the accelerometer's axes (as the recording spec has it).
``imu_temp``   MPU-9150 temperature: raw = (T - 35 °C)·340.
``enc``        relative encoders: counts = (q - q_power_up)·counts_per_rad, no noise.
=============  ==========================================================================

Noise is white, Gaussian, with the rms of the datasheet at the simulated rate: for the
ADXL345 the datasheet's rms at 100 Hz (bandwidth = rate/2) scaled by √(rate/100 Hz); for
the MPU-9150 the noise density times √(rate/2).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from models.arm import ArmModel, SensorMount
from sensors.samples import IMU_STREAMS, Recording, accel_columns, encoder_columns

# --- ADXL345 (link accelerometers), 10-bit, ±2 g ---------------------------------------
ADXL345_LSB_PER_G = 256.0
"""Nominal sensitivity at ±2 g, 10-bit (datasheet: 230 min, 282 max)."""
ADXL345_NOISE_LSB_RMS_AT_100HZ = np.array([0.75, 0.75, 1.1])
"""Datasheet noise at 100 Hz output rate, x/y/z (290 / 430 µg/√Hz)."""
ADXL345_COUNTS_MIN, ADXL345_COUNTS_MAX = -512, 511
ADXL345_REFERENCE_RATE_HZ = 100.0

# --- MPU-9150 accelerometer, ±2 g -----------------------------------------------------
MPU9150_ACCEL_LSB_PER_G = 16384.0
MPU9150_ACCEL_NOISE_G_PER_SQRT_HZ = 400e-6
INT16_MIN, INT16_MAX = -32768, 32767

# --- MPU-9150 gyroscope, ±250 °/s -----------------------------------------------------
MPU9150_GYRO_LSB_PER_DPS = 131.0
MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ = 0.005
MPU9150_GYRO_ZERO_RATE_OFFSET_DPS_MAX = 20.0
"""Initial zero-rate offset tolerance (datasheet ±20 °/s): see the gyro_bias effect."""

# --- MPU-9150 temperature sensor ------------------------------------------------------
MPU9150_TEMP_LSB_PER_C = 340.0
MPU9150_TEMP_OFFSET_C = 35.0
MPU9150_TEMP_NOISE_C_RMS = 0.02
"""Not in the datasheet: a few LSB of register jitter (our assumption)."""

# --- AK8975 magnetometer --------------------------------------------------------------
AK8975_UT_PER_LSB = 0.3
AK8975_COUNTS_MIN, AK8975_COUNTS_MAX = -4096, 4095
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
ADC14_COUNTS_MIN, ADC14_COUNTS_MAX = -8192, 8191

# --- Earth's magnetic field -----------------------------------------------------------
EARTH_FIELD_TAMPA_UT = np.array([24.0, 0.0, -39.0])
"""Earth's field in the world frame at Tampa, FL (USF), µT: world x = magnetic north,
z up, so 24 µT horizontal toward north and 39 µT down (inclination ≈ 58°; total
≈ 46 µT; WMM 2025, rounded). Declination does not enter: yaw is magnetic."""

IMU_STREAM_NAMES = ("imu_acc", "imu_gyro", "imu_mag", "imu_temp")
ENCODER_STREAM = "enc"


@dataclass(frozen=True)
class StreamModel:
    """How one stream's physical value becomes what the recording holds:
    ``counts = gain·value + zero``.

    ``gain`` and ``zero`` are per channel; ``noise_counts_rms`` is per channel at the
    stream's rate; ``counts_min``/``counts_max`` the register limits (None: unbounded).
    ``value_unit`` is the unit of the recorded values (:mod:`sensors.units`): ``counts``
    (register counts, whole numbers) or a physical unit, when the sensor delivers values
    already converted (then ``gain`` converts ``unit`` to it, and "counts" in the names
    here mean the recorded values); ``step`` is their resolution (1 for counts; 0.01 for
    values stored rounded to 0.01; 0 for none).
    """

    stream: str
    kind: str
    sensor: str  # the config sensor it belongs to ("imu" streams: the IMU's name; enc: "")
    channels: tuple[str, ...]
    unit: str
    gain: np.ndarray
    zero: np.ndarray
    noise_counts_rms: np.ndarray
    counts_min: float | None
    counts_max: float | None
    value_unit: str = "counts"
    step: float = 1.0

    @property
    def size(self) -> int:
        return len(self.channels)

    def to_counts(self, value: np.ndarray) -> np.ndarray:
        """Physical value ``(N, k)`` to ideal (float, unrounded) counts."""
        return value * self.gain + self.zero

    def from_counts(self, counts: np.ndarray) -> np.ndarray:
        """Counts ``(N, k)`` back to the physical value with the nominal gain and zero."""
        return (np.asarray(counts, dtype=float) - self.zero) / self.gain

    @property
    def sigma_counts(self) -> np.ndarray:
        """Standard deviation of one reading in counts: noise and rounding (step/√12)."""
        return np.sqrt(self.noise_counts_rms**2 + self.step**2 / 12.0)

    def noise_physical_rms(self) -> np.ndarray:
        return self.noise_counts_rms / np.abs(self.gain)

    def saturated(self, counts: np.ndarray) -> np.ndarray:
        """``(N, k)``: where a channel reads its register limit (or past it): the true value
        may be anywhere beyond, so such a sample says nothing reliable. All False for an
        unbounded stream (the encoders)."""
        c = np.asarray(counts, dtype=float)
        if self.counts_min is None:
            return np.zeros(c.shape, bool)
        return (c <= self.counts_min) | (c >= self.counts_max)

    def beyond_range(self, counts: np.ndarray) -> np.ndarray:
        """``(N, k)``: where a channel reads past its register limits (or ±inf): no such
        device can have said it, so the recording is wrong, not the sensor saturated."""
        c = np.asarray(counts, dtype=float)
        if self.counts_min is None:
            return np.isinf(c)
        return (c < self.counts_min) | (c > self.counts_max)

    def digitise(self, counts: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """Add noise (if ``rng``), round to the resolution (integers for counts), saturate
        at the range's limits."""
        c = np.asarray(counts, dtype=float)
        if rng is not None and np.any(self.noise_counts_rms > 0):
            c = c + rng.standard_normal(c.shape) * self.noise_counts_rms
        if self.step > 0:
            c = np.rint(c / self.step) * self.step
        if self.counts_min is not None:
            c = np.clip(c, self.counts_min, self.counts_max)
        return c.astype(np.int64) if self.value_unit == "counts" else c


def _accel_stream(sensor: SensorMount, rate_hz: float) -> StreamModel:
    cols = accel_columns(sensor.name)
    if sensor.type == "adxl345":
        gain = float(sensor.settings.get("lsb_per_g", ADXL345_LSB_PER_G))
        noise = ADXL345_NOISE_LSB_RMS_AT_100HZ * np.sqrt(rate_hz / ADXL345_REFERENCE_RATE_HZ)
        return StreamModel(sensor.name, "accel", sensor.name, cols, "g", np.full(3, gain),
                           np.zeros(3), noise, ADXL345_COUNTS_MIN, ADXL345_COUNTS_MAX)
    # analog_triax: volts through an ADC
    st = sensor.settings
    cpv = float(st.get("adc_counts_per_volt", ANALOG_TRIAX_ADC_COUNTS_PER_VOLT))
    vpg = float(st.get("volts_per_g", ANALOG_TRIAX_VOLTS_PER_G))
    zero_v = float(st.get("zero_g_volts", ANALOG_TRIAX_ZERO_G_VOLTS))
    noise_v = np.broadcast_to(np.asarray(st.get("accel_noise_v", ANALOG_TRIAX_NOISE_V_RMS), float), (3,))
    return StreamModel(sensor.name, "accel", sensor.name, cols, "g", np.full(3, vpg * cpv),
                       np.full(3, zero_v * cpv), noise_v * cpv, ADC14_COUNTS_MIN, ADC14_COUNTS_MAX)


def stream_models(arm: ArmModel, rate_hz: float | dict[str, float] = 100.0) -> dict[str, StreamModel]:
    """The count model of every raw stream the arm's sensors produce, config order.

    ``rate_hz`` sets the noise (a number for all streams, or per stream name).
    """
    def rate(name: str) -> float:
        return float(rate_hz.get(name, 100.0)) if isinstance(rate_hz, dict) else float(rate_hz)

    out: dict[str, StreamModel] = {}
    for s in arm.link_accelerometers:
        out[s.name] = _accel_stream(s, rate(s.name))
    imu = arm.imu
    if imu is not None:
        r = rate("imu_acc")
        out["imu_acc"] = StreamModel(
            "imu_acc", "imu_accel", imu.name, IMU_STREAMS["imu_acc"][1], "g",
            np.full(3, MPU9150_ACCEL_LSB_PER_G), np.zeros(3),
            np.full(3, MPU9150_ACCEL_NOISE_G_PER_SQRT_HZ * np.sqrt(r / 2) * MPU9150_ACCEL_LSB_PER_G),
            INT16_MIN, INT16_MAX)
        r = rate("imu_gyro")
        lsb_per_rad_s = MPU9150_GYRO_LSB_PER_DPS * 180.0 / np.pi
        out["imu_gyro"] = StreamModel(
            "imu_gyro", "gyro", imu.name, IMU_STREAMS["imu_gyro"][1], "rad/s",
            np.full(3, lsb_per_rad_s), np.zeros(3),
            np.full(3, MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ * np.sqrt(r / 2) * MPU9150_GYRO_LSB_PER_DPS),
            INT16_MIN, INT16_MAX)
        out["imu_mag"] = StreamModel(
            "imu_mag", "mag", imu.name, IMU_STREAMS["imu_mag"][1], "uT",
            np.full(3, 1.0 / AK8975_UT_PER_LSB), np.zeros(3),
            np.full(3, AK8975_NOISE_UT_RMS / AK8975_UT_PER_LSB), AK8975_COUNTS_MIN, AK8975_COUNTS_MAX)
        out["imu_temp"] = StreamModel(
            "imu_temp", "temperature", imu.name, IMU_STREAMS["imu_temp"][1], "degC",
            np.array([MPU9150_TEMP_LSB_PER_C]), np.array([-MPU9150_TEMP_OFFSET_C * MPU9150_TEMP_LSB_PER_C]),
            np.array([MPU9150_TEMP_NOISE_C_RMS * MPU9150_TEMP_LSB_PER_C]), INT16_MIN, INT16_MAX)
    out[ENCODER_STREAM] = StreamModel(
        ENCODER_STREAM, "encoder", "", encoder_columns(arm.n_joints), "rad", arm.counts_per_rad.copy(),
        np.zeros(arm.n_joints), np.zeros(arm.n_joints), None, None)
    return out


def stream_group(stream: str) -> str:
    """The device a stream comes from (its samples share one instant): ``imu_*`` -> ``imu``."""
    return "imu" if stream in IMU_STREAM_NAMES else stream


def accel_counts_to_g(counts: np.ndarray, model: StreamModel) -> np.ndarray:
    """Raw accelerometer counts to g with the nominal sensitivity (for plots and checks)."""
    return model.from_counts(counts)


def mpu9150_temperature_c(raw) -> np.ndarray | float:
    """The MPU-9150's temperature register (counts, any shape) in °C: raw / 340 + 35."""
    return np.asarray(raw, dtype=float) / MPU9150_TEMP_LSB_PER_C + MPU9150_TEMP_OFFSET_C


def recording_problems(arm: ArmModel, rec: Recording) -> list[str]:
    """Where a recording does not fit ``arm``'s config, one line each: a stream of the
    config's sensors with another number of channels than the config gives it (the
    encoders: one per joint), and ground-truth joint angles for another number of
    joints. Empty when it fits. A sensor the recording lacks is not a misfit here (the
    commands say what they can do without it)."""
    out = []
    n = arm.n_joints
    for name, model in stream_models(arm).items():
        s = rec.get(name)
        if s is None or len(s.channels) == model.size:
            continue
        if name == ENCODER_STREAM:
            out.append(f"encoder stream {name!r} has {len(s.channels)} channels "
                       f"({s.channels[0]}..{s.channels[-1]}) but the arm has {n} joints")
        else:
            out.append(f"stream {name!r} has {len(s.channels)} channels; the config's sensor "
                       f"gives {model.size} ({', '.join(model.channels)})")
    for s in rec.truth().values():
        if s.kind == "truth_joints" and len(s.channels) != n:
            out.append(f"ground truth {s.name!r} has {len(s.channels)} joint angles but the arm "
                       f"has {n} joints")
    return out


# --------------------------------------------------------------------------------------
# what every command that reads samples does with range and saturation
class OutOfRangeError(ValueError):
    """A recording holds a value its device cannot output (past its register range)."""


class MissingSensorError(ValueError):
    """A recording lacks a stream that the config and the command require."""


@dataclass(frozen=True)
class SampleScreen:
    """What :func:`screen_samples` found: per stream with a count model, its samples and
    those saturated (a channel at its register limit); the commands leave those out."""

    samples: dict[str, int]
    saturated: dict[str, int]

    @property
    def any_saturated(self) -> bool:
        return any(self.saturated.values())

    def words(self) -> str:
        """One line for a person: which streams had saturated samples, how many of how many."""
        parts = [f"{s} {n:,} of {self.samples[s]:,} ({100.0 * n / self.samples[s]:.2g} %)"
                 for s, n in self.saturated.items() if n]
        return ("saturated samples (a channel at its register limit), left out: " + ", ".join(parts)
                if parts else "no saturated sample")

    def as_dict(self) -> dict:
        return {"samples": dict(self.samples), "saturated": {s: n for s, n in self.saturated.items() if n}}


def screen_samples(arm: ArmModel, rec, required: Iterable[str] = (), needed_by: str = "") -> SampleScreen:
    """Every command's check of a recording's samples against the config's sensors.

    Raises :class:`MissingSensorError` when a stream of ``required`` has no sample (naming
    them and ``needed_by``), :class:`OutOfRangeError` at the first value past its device's
    register range (naming the stream, channel, time and sample), and otherwise counts the
    saturated samples per stream (:meth:`StreamModel.saturated`), which the commands leave out.
    Streams the config does not describe (truth, unknown sensors) are not looked at.
    """
    missing = [s for s in required if rec.get(s) is None or len(rec.get(s)) == 0]
    if missing:
        raise MissingSensorError(
            f"the recording has no samples of {', '.join(missing)}"
            + (f", which {needed_by}" if needed_by else "")
            + f" (it has: {', '.join(s for s in rec.raw() if len(rec.get(s))) or 'no sensor stream'})")
    samples, saturated = {}, {}
    for name, model in stream_models(arm).items():
        st = rec.get(name)
        if st is None or len(st) == 0 or st.values.shape[1] != model.size:
            continue
        bad = model.beyond_range(st.values)
        if bad.any():
            i, k = (int(v[0]) for v in np.nonzero(bad))
            v = float(st.values[i, k])
            where = (f"{model.channels[k]} = {v:.6g} counts at t = {float(st.t_s[i]):.3f} s "
                     f"(sample {i + 1:,} of {name})")
            rng = ("" if model.counts_min is None else
                   f" {model.counts_min:.0f}…{model.counts_max:.0f} counts")
            sensor = next((m for m in arm.sensors if m.name == model.sensor), None)
            device = f"the {sensor.type}'s" if sensor is not None else "its"
            raise OutOfRangeError(f"{where}: beyond {device} register range{rng}; no such sensor "
                                  f"can read that, so the recording is refused")
        samples[name] = len(st)
        saturated[name] = int(model.saturated(st.values).any(axis=1).sum())
    return SampleScreen(samples, saturated)


def encoder_angles_at(arm: ArmModel, enc, t_s: float) -> tuple[int, np.ndarray]:
    """The encoder stream's last sample at or before ``t_s`` (the first, if none is): its
    index and the joints' relative angles there (counts / counts per rad)."""
    k = min(max(int(np.searchsorted(enc.t_s, t_s + 1e-9)) - 1, 0), len(enc) - 1)
    return k, np.asarray(enc.values[k], float) / arm.counts_per_rad
