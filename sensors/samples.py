"""Raw sample types: what the sensors said, exactly as they said it, in time-stamped batches.

A recording is a set of named streams. Each stream is one sensor (or one group of
columns of the recording CSV) sampled at its own instants: ``t_s`` of shape ``(N,)``
and ``values`` of shape ``(N, k)``. A raw stream holds int64 when every value is a whole
number within 64-bit integers (register counts, as every armfusion device gives them) and float64 otherwise
(values a sensor delivered already in a physical unit, e.g. g rounded to 0.01: the unit
is the config's sensor description's, ``StreamModel.value_unit``); raw values must be
finite (a sensor not sampled is a missing sample, not a NaN). The optional ground-truth
streams hold floats (rad). Conversion to SI units is a model step.

Stream names and their CSV columns (shared/spec/recording-csv.md):

=============  ===============  =========================================
stream         kind             CSV columns
=============  ===============  =========================================
``<acc>``      ``accel``        ``<acc>_x``, ``<acc>_y``, ``<acc>_z``
``imu_acc``    ``imu_accel``    ``imu_ax``, ``imu_ay``, ``imu_az``
``imu_gyro``   ``gyro``         ``imu_gx``, ``imu_gy``, ``imu_gz``
``<s>_gyro``   ``link_gyro``    ``<s>_gx``, ``<s>_gy``, ``<s>_gz`` (a gyroscope on a link)
``imu_mag``    ``mag``          ``imu_mx``, ``imu_my``, ``imu_mz``
``imu_temp``   ``temperature``  ``imu_temp``
``enc``        ``encoder``      ``enc1`` … ``encN``
``true_q``     ``truth_joints`` ``true_q1`` … ``true_qN`` (rad)
``true_base``  ``truth_base``   ``true_roll``, ``true_pitch``, ``true_yaw`` (rad)
=============  ===============  =========================================

:func:`stream_gaps` says where a stream misses samples (``inspect`` and the bag import report it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

StreamKind = Literal[
    "accel", "imu_accel", "gyro", "link_gyro", "mag", "temperature", "encoder", "truth_joints",
    "truth_base",
]

RAW_KINDS: frozenset[str] = frozenset(
    {"accel", "imu_accel", "gyro", "link_gyro", "mag", "temperature", "encoder"}
)
TRUTH_KINDS: frozenset[str] = frozenset({"truth_joints", "truth_base"})

IMU_STREAMS: dict[str, tuple[StreamKind, tuple[str, ...]]] = {
    "imu_acc": ("imu_accel", ("imu_ax", "imu_ay", "imu_az")),
    "imu_gyro": ("gyro", ("imu_gx", "imu_gy", "imu_gz")),
    "imu_mag": ("mag", ("imu_mx", "imu_my", "imu_mz")),
    "imu_temp": ("temperature", ("imu_temp",)),
}
TRUTH_BASE_COLUMNS: tuple[str, ...] = ("true_roll", "true_pitch", "true_yaw")

ECHO_CHARS = 32
"""At most this many characters of an offending value are quoted in an error message."""


class RecordingError(ValueError):
    """A file is not a readable recording; the message names the file and the place."""


def clipped_repr(value: object, limit: int = ECHO_CHARS) -> str:
    """``repr(value)`` for a message, cut to about ``limit`` characters (a hostile file
    may hold a cell of millions of digits: the message says how long it was instead)."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, str) and len(value) > limit:
        return f"{value[:limit]!r}… ({len(value)} characters)"
    text = repr(value)
    return text if len(text) <= limit + 2 else f"{text[:limit]}… ({len(text)} characters)"


def accel_columns(name: str) -> tuple[str, str, str]:
    """CSV columns of the link accelerometer called ``name``."""
    return (f"{name}_x", f"{name}_y", f"{name}_z")


LINK_GYRO_SUFFIX = "_gyro"
"""A link gyroscope's stream is its sensor's name with this suffix (``shaft`` -> ``shaft_gyro``)."""


def link_gyro_stream(sensor: str) -> str:
    """The stream name of the gyroscope of the link sensor called ``sensor``."""
    return sensor + LINK_GYRO_SUFFIX


def link_gyro_columns(sensor: str) -> tuple[str, str, str]:
    """CSV columns of the gyroscope of the link sensor called ``sensor``."""
    return (f"{sensor}_gx", f"{sensor}_gy", f"{sensor}_gz")


def encoder_columns(n_joints: int) -> tuple[str, ...]:
    return tuple(f"enc{i + 1}" for i in range(n_joints))


def truth_joint_columns(n_joints: int) -> tuple[str, ...]:
    return tuple(f"true_q{i + 1}" for i in range(n_joints))


def _raw_values(name: str, v: np.ndarray) -> np.ndarray:
    """A raw stream's values: int64 when every one is a whole number within 64-bit integers
    (counts: what every recording before physical-unit sensors held, unchanged), else
    float64; refused when one is not finite, or integers (not floats) beyond 64 bits."""
    if v.dtype == object:
        try:
            return np.asarray(v, dtype=np.int64)
        except (OverflowError, TypeError, ValueError):
            try:
                v = np.asarray(v, dtype=np.float64)
            except (OverflowError, TypeError, ValueError):
                raise ValueError(f"stream {name!r}: raw values must be numbers "
                                 "(whole counts within 64-bit integers, or finite decimals)") from None
            if not np.all(np.isfinite(v)) or not np.any(v != np.round(v)):
                raise ValueError(f"stream {name!r}: raw counts must be 64-bit integers") from None
    if v.dtype.kind in "iub":
        return v.astype(np.int64, copy=False)
    v = v.astype(np.float64, copy=False)
    if not np.all(np.isfinite(v)):
        i, j = (int(x[0]) for x in np.nonzero(~np.isfinite(v)))
        raise ValueError(f"stream {name!r}: raw value {float(v[i, j])!r} at sample {i}, channel {j} "
                         "is not finite (a sensor not sampled is a missing sample, not a NaN)")
    if np.all(v == np.round(v)) and not (v.size and float(np.abs(v).max()) >= 2.0**63):
        return v.astype(np.int64)
    return v  # a decimal somewhere, or a whole float beyond any count: physical values


@dataclass(frozen=True)
class Stream:
    """One sensor's samples: ``t_s (N,)`` seconds and ``values (N, k)`` (raw: int64 counts
    when all are whole numbers within 64 bits, else float64; truth: float64)."""

    name: str
    kind: StreamKind
    t_s: np.ndarray
    values: np.ndarray
    channels: tuple[str, ...]

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=np.float64).reshape(-1)
        v = np.asarray(self.values)
        if v.ndim == 1:
            v = v.reshape(-1, 1)
        if v.shape != (t.shape[0], len(self.channels)):
            raise ValueError(
                f"stream {self.name!r}: values have shape {v.shape}, expected "
                f"({t.shape[0]}, {len(self.channels)}) for channels {list(self.channels)}"
            )
        v = v.astype(np.float64, copy=False) if self.kind in TRUTH_KINDS else _raw_values(self.name, v)
        if not np.isfinite(t).all():  # (the method: NumPy's function costs more on a driver's few samples)
            i = int(np.argmax(~np.isfinite(t)))
            raise ValueError(f"stream {self.name!r}: t = {float(t[i])!r} at sample {i} is not a finite time")
        if t.size > 1:
            bad = np.flatnonzero(np.diff(t) <= 0)
            if bad.size:
                i = int(bad[0]) + 1
                raise ValueError(
                    f"stream {self.name!r}: time is not increasing at sample {i} "
                    f"(t = {t[i]!r} after {t[i - 1]!r})"
                )
        t.setflags(write=False)
        v.setflags(write=False)
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "values", v)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def rate_hz(self) -> float:
        """Median sample rate; 0 for fewer than two samples."""
        if len(self) < 2:
            return 0.0
        return float(1.0 / np.median(np.diff(self.t_s)))

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0]) if len(self) else 0.0

    def between(self, t_start_s: float, t_end_s: float) -> Stream:
        """The samples with ``t_start_s <= t < t_end_s``."""
        m = (self.t_s >= t_start_s) & (self.t_s < t_end_s)
        return Stream(self.name, self.kind, self.t_s[m], self.values[m], self.channels)


@dataclass(frozen=True)
class Recording:
    """What the sensors said over time: named streams, plus optional ground truth."""

    streams: dict[str, Stream]
    meta: dict = field(default_factory=dict)

    def raw(self) -> dict[str, Stream]:
        return {k: s for k, s in self.streams.items() if s.kind in RAW_KINDS}

    def truth(self) -> dict[str, Stream]:
        return {k: s for k, s in self.streams.items() if s.kind in TRUTH_KINDS}

    def accelerometers(self) -> dict[str, Stream]:
        return {k: s for k, s in self.streams.items() if s.kind == "accel"}

    def get(self, name: str) -> Stream | None:
        return self.streams.get(name)

    def between(self, t_start_s: float, t_end_s: float) -> Recording:
        """Every stream's samples in ``[t_start_s, t_end_s)`` (see :meth:`Stream.between`)."""
        return Recording({k: s.between(t_start_s, t_end_s) for k, s in self.streams.items()},
                         dict(self.meta))

    @property
    def t_start_s(self) -> float:
        ts = [s.t_s[0] for s in self.streams.values() if len(s)]
        return float(min(ts)) if ts else 0.0

    @property
    def t_end_s(self) -> float:
        ts = [s.t_s[-1] for s in self.streams.values() if len(s)]
        return float(max(ts)) if ts else 0.0

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s


GAP_FACTOR = 1.5
"""A gap is an interval longer than this many sample periods: at least one sample is
missing there (one missing sample makes an interval of two periods). It was 3, which
let a stream missing one sample in five pass as "0 gaps"."""

PERIOD_PERCENTILE = 10.0
"""The stream's sample period is this percentile of its intervals: the median is no
period when half of them span a missing sample."""


def stream_gaps(s: Stream) -> tuple[int, float, int]:
    """Number of gaps, the longest interval between samples [s], and how many samples
    the gaps miss (each gap's interval in sample periods, less one)."""
    if len(s) < 3:
        return 0, float(np.diff(s.t_s).max()) if len(s) == 2 else 0.0, 0
    dt = np.diff(s.t_s)
    period = float(np.percentile(dt, PERIOD_PERCENTILE))
    gap = dt > GAP_FACTOR * period
    missing = int(np.sum(np.maximum(np.rint(dt[gap] / period) - 1, 1)))
    return int(np.sum(gap)), float(dt.max()), missing
