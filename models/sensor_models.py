"""What each sensor outputs, in counts: datasheet constants, count conversion, noise.

A measurement model here is the last, fixed step of a prediction: a physical value in a
sensor's own axes (specific force in g, angular rate in rad/s, magnetic field in µT,
temperature in °C, joint angle in rad) becomes register counts by a nominal gain and
zero, then (only when simulating) noise, rounding and saturation. Everything that makes
a real sensor differ from its datasheet (bias, scale, axis directions, drift…) is an
effect (:mod:`armfusion.models.effects`), applied to the physical value before this step, so that
it stays estimable. The physical values themselves are what ideal sensors read
(:func:`armfusion.models.motion.sensor_motion`): the accelerometer's specific force and the compass's
heading are written once, compiled, in :mod:`armfusion.models.sensor_kernels`.

Streams and their models (names as in :mod:`armfusion.sensors.samples`), each made from its
sensor's description (:mod:`armfusion.models.sensor_description`: the datasheet's, or the config's
``outputs``):

=================  ======================================================================
``<acc>``          a link sensor's accelerometer: an ADXL345 (10-bit at ±2 g, 256 LSB/g),
                   an ``analog_triax`` (volts through an ADC), an IMU's accelerometer…
``<acc>_gyro``     a link sensor's gyroscope (an IMU on a link)
``imu_acc``        the base IMU's accelerometer (MPU-9150 / MPU-6050 at ±2 g: 16384 LSB/g)
``imu_gyro``       its gyroscope (±250 °/s: 131 LSB per °/s)
``imu_mag``        its magnetometer, when it has one (the MPU-9150's AK8975: 0.3 µT/LSB,
                   13-bit), already in the accelerometer's axes (as the recording spec has it)
``imu_temp``       its temperature (MPU-9150: raw = (T - 35 °C)·340)
``enc``            relative encoders: counts = (q - q_power_up)·counts_per_rad, no noise.
=================  ======================================================================

A sensor may deliver values already in a physical unit (a logger that stored g rounded to
0.01): its stream's "counts" are then those values (``value_unit``), their step the
resolution.

Noise is white, Gaussian, with the rms of the datasheet at the simulated rate: for the
ADXL345 the datasheet's rms at 100 Hz (bandwidth = rate/2) scaled by √(rate/100 Hz); for
the MPU-9150 the noise density times √(rate/2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.models.arm import ArmModel, SensorMount
from armfusion.models.sensor_description import (  # noqa: F401  (the datasheet numbers, re-exported)
    ADXL345_LSB_PER_G,
    ADXL345_NOISE_LSB_RMS_AT_100HZ,
    AK8975_NOISE_UT_RMS,
    AK8975_UT_PER_LSB,
    CANONICAL_UNIT,
    MPU9150_ACCEL_LSB_PER_G,
    MPU9150_GYRO_LSB_PER_DPS,
    MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ,
    MPU9150_TEMP_LSB_PER_C,
    MPU9150_TEMP_OFFSET_C,
)
from armfusion.sensors.sample_checks import FEED_MAX, FEED_MIN
from armfusion.sensors.samples import (
    IMU_STREAMS,
    Recording,
    accel_columns,
    encoder_columns,
    link_gyro_columns,
    link_gyro_stream,
)

# --- Earth's magnetic field -----------------------------------------------------------
EARTH_FIELD_TAMPA_UT = np.array([24.0, 0.0, -39.0])
"""Earth's field in the world frame at Tampa, FL (USF), µT: world x = magnetic north,
z up, so 24 µT horizontal toward north and 39 µT down (inclination ≈ 58°; total
≈ 46 µT; WMM 2025, rounded). Declination does not enter: yaw is magnetic."""

ENCODER_STREAM = "enc"


@dataclass(frozen=True)
class StreamModel:
    """How one stream's physical value becomes what the recording holds:
    ``counts = gain·value + zero``.

    ``gain`` and ``zero`` are per channel; ``noise_counts_rms`` is per channel at the
    stream's rate; ``counts_min``/``counts_max`` the register limits (None: unbounded).
    ``value_unit`` is the unit of the recorded values (:mod:`armfusion.sensors.units`): ``counts``
    (register counts, whole numbers) or a physical unit, when the sensor delivers values
    already converted (then ``gain`` converts ``unit`` to it, and "counts" in the names
    here mean the recorded values); ``step`` is their resolution (1 for counts; 0.01 for
    values stored rounded to 0.01; 0 for none); ``delay_s`` the part's delay (a value
    recorded at ``t`` is the quantity at ``t - delay_s``: its description's).
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
    delay_s: float = 0.0

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

    @property
    def admissible_range(self) -> tuple[float, float]:
        """The values the stream may hold (:mod:`armfusion.models.sample_admission`): the register
        limits, or for a stream without them (the encoders) the feed's int32."""
        return (FEED_MIN if self.counts_min is None else self.counts_min,
                FEED_MAX if self.counts_max is None else self.counts_max)

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


def part_stream(stream: str, kind: str, sensor: SensorMount, channels: tuple[str, ...], part: str,
                rate_hz: float) -> StreamModel:
    """The count model of one sensing ``part`` of ``sensor`` (its description's units, scale,
    zero, limits, resolution and noise at ``rate_hz``) as the recording's stream ``stream``."""
    p = sensor.description.part(part)
    k = len(channels)
    limits = p.value_limits()
    lo, hi = (None, None) if limits is None else limits
    if p.counts and limits is not None and float(lo).is_integer() and float(hi).is_integer():
        lo, hi = int(lo), int(hi)  # a register's limits are whole counts
    return StreamModel(stream, kind, sensor.name, channels, CANONICAL_UNIT[part], np.full(k, p.gain()),
                       np.full(k, p.zero), p.noise(rate_hz), lo, hi, p.units, p.resolution, p.delay_s)


def stream_models(arm: ArmModel, rate_hz: float | dict[str, float] = 100.0) -> dict[str, StreamModel]:
    """The count model of every raw stream the arm's sensors produce, config order: each
    link accelerometer (and a link's gyroscope, ``<name>_gyro``), the base IMU's parts,
    the encoders. Made from the sensors' descriptions (:mod:`armfusion.models.sensor_description`).

    ``rate_hz`` sets the noise (a number for all streams, or per stream name).
    """
    def rate(name: str) -> float:
        return float(rate_hz.get(name, 100.0)) if isinstance(rate_hz, dict) else float(rate_hz)

    out: dict[str, StreamModel] = {}
    for s in arm.link_accelerometers:
        out[s.name] = part_stream(s.name, "accel", s, accel_columns(s.name), "accelerometer", rate(s.name))
    for s in arm.sensors:
        if s.has_link_gyro:
            name = link_gyro_stream(s.name)
            out[name] = part_stream(name, "link_gyro", s, link_gyro_columns(s.name), "gyroscope", rate(name))
    imu = arm.imu
    if imu is not None:
        for stream, part in IMU_STREAM_PARTS.items():
            if imu.description.has(part):
                kind, channels = IMU_STREAMS[stream]
                out[stream] = part_stream(stream, kind, imu, channels, part, rate(stream))
    out[ENCODER_STREAM] = StreamModel(
        ENCODER_STREAM, "encoder", "", encoder_columns(arm.n_joints), "rad", arm.counts_per_rad.copy(),
        np.zeros(arm.n_joints), np.zeros(arm.n_joints), None, None)
    return out


IMU_STREAM_PARTS = {"imu_acc": "accelerometer", "imu_gyro": "gyroscope", "imu_mag": "magnetometer",
                    "imu_temp": "temperature"}
"""The base IMU's streams and the part of its description each comes from."""


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


def encoder_angles_at(arm: ArmModel, enc, t_s: float) -> tuple[int, np.ndarray]:
    """The encoder stream's last sample at or before ``t_s`` (the first, if none is): its
    index and the joints' relative angles there (counts / counts per rad)."""
    k = min(max(int(np.searchsorted(enc.t_s, t_s + 1e-9)) - 1, 0), len(enc) - 1)
    return k, np.asarray(enc.values[k], float) / arm.counts_per_rad
