"""Finding the still stretches of a recording.

A stretch is still when, over a sliding window, every accelerometer's and the gyro's
sample standard deviation stays near its noise floor and no encoder moves. The
statistics are binned on a common grid (default 0.1 s) and windowed with cumulative
sums, so an hour of 100 Hz data takes milliseconds. The limits are physical (g, °/s);
each stream's are turned into the units its recording holds by its count model, the
config's description of the sensor (without a config: the recording spec's devices,
ADXL345 and MPU-9150 counts).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from armfusion.models.sensor_description import (
    ADXL345_LSB_PER_G,
    MPU9150_ACCEL_LSB_PER_G,
    MPU9150_GYRO_LSB_PER_DPS,
)
from armfusion.models.sensor_models import StreamModel
from armfusion.sensors.samples import Recording, Stream


@dataclass(frozen=True)
class StaticDetectionSettings:
    window_s: float = 1.0
    """Sliding window over which the spread is measured."""
    grid_s: float = 0.1
    """Resolution of the segment boundaries."""
    min_duration_s: float = 1.0
    """Shorter still stretches are not reported."""
    accel_std_g: float = 3.5 / ADXL345_LSB_PER_G
    """Link accelerometer: 13.7 mg (an ADXL345's noise is 3-4 mg rms: 0.75-1.1 LSB at 256 LSB/g)."""
    imu_accel_std_g: float = 150.0 / MPU9150_ACCEL_LSB_PER_G
    """The IMU's accelerometer: 9.2 mg (an MPU-9150's noise is about 2.8 mg rms at 100 Hz)."""
    gyro_std_dps: float = 20.0 / MPU9150_GYRO_LSB_PER_DPS
    """The IMU's gyro: 0.15 °/s (an MPU-9150's noise is about 0.035 °/s rms at 100 Hz)."""
    encoder_range_counts: float = 50.0
    """Largest encoder change inside a window that still counts as not moving."""


@dataclass(frozen=True)
class Segment:
    t_start_s: float
    t_end_s: float

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s


def _binned_window_std(stream: Stream, edges0: float, n_bins: int, grid_s: float, k: int):
    """Windowed std per channel on the grid: ``(n_bins, channels)``; NaN where no samples."""
    idx = np.floor((stream.t_s - edges0) / grid_s).astype(np.int64)
    ok = (idx >= 0) & (idx < n_bins)
    idx = idx[ok]
    x = stream.values[ok].astype(np.float64)
    x = x - x.mean(axis=0) if len(x) else x  # numerically kinder for raw counts
    cnt = np.bincount(idx, minlength=n_bins).astype(np.float64)
    s1 = np.stack([np.bincount(idx, x[:, c], minlength=n_bins) for c in range(x.shape[1])], 1)
    s2 = np.stack([np.bincount(idx, x[:, c] ** 2, minlength=n_bins) for c in range(x.shape[1])], 1)

    def window(a):
        c = np.cumsum(np.concatenate([np.zeros((1,) + a.shape[1:]), a]), axis=0)
        lo = np.clip(np.arange(n_bins) - k // 2, 0, n_bins)
        hi = np.clip(np.arange(n_bins) - k // 2 + k, 0, n_bins)
        return c[hi] - c[lo]

    n = window(cnt[:, None])
    m1 = window(s1) / np.maximum(n, 1)
    m2 = window(s2) / np.maximum(n, 1)
    std = np.sqrt(np.maximum(m2 - m1**2, 0.0))
    std[n[:, 0] < 3] = np.nan
    return std


def _binned_window_range(stream: Stream, edges0: float, n_bins: int, grid_s: float, k: int):
    """Windowed max-min per channel (for encoders): ``(n_bins, channels)``; NaN where empty."""
    idx = np.floor((stream.t_s - edges0) / grid_s).astype(np.int64)
    ok = (idx >= 0) & (idx < n_bins)
    idx, x = idx[ok], stream.values[ok].astype(np.float64)
    hi = np.full((n_bins, x.shape[1]), -np.inf)
    lo = np.full((n_bins, x.shape[1]), np.inf)
    np.maximum.at(hi, idx, x)
    np.minimum.at(lo, idx, x)
    from numpy.lib.stride_tricks import sliding_window_view

    pad = k // 2
    hp = np.pad(hi, ((pad, k - 1 - pad), (0, 0)), constant_values=-np.inf)
    lp = np.pad(lo, ((pad, k - 1 - pad), (0, 0)), constant_values=np.inf)
    wh = sliding_window_view(hp, k, axis=0).max(axis=-1)
    wl = sliding_window_view(lp, k, axis=0).min(axis=-1)
    r = wh - wl
    r[~np.isfinite(r)] = np.nan
    return r


SPEC_GAIN = {"accel": ADXL345_LSB_PER_G, "imu_accel": MPU9150_ACCEL_LSB_PER_G,
             "gyro": MPU9150_GYRO_LSB_PER_DPS * 180.0 / np.pi}
"""Without a config, what the recording spec's count columns are: an ADXL345's counts per g,
an MPU-9150's per g and per rad/s."""


def still_mask(rec: Recording, settings: StaticDetectionSettings | None = None,
               models: Mapping[str, StreamModel] | None = None):
    """Grid times ``(M,)`` and a boolean ``(M,)``: is the arm (and chair) still there.
    ``models``: the streams' count models (the config's; default: :data:`SPEC_GAIN`)."""
    st = settings or StaticDetectionSettings()
    t0, t1 = rec.t_start_s, rec.t_end_s
    n_bins = max(int(np.ceil((t1 - t0) / st.grid_s)) + 1, 1)
    k = max(int(round(st.window_s / st.grid_s)), 1)
    grid_t = t0 + (np.arange(n_bins) + 0.5) * st.grid_s
    still = np.ones(n_bins, dtype=bool)
    seen = np.zeros(n_bins, dtype=bool)
    limits = {"accel": st.accel_std_g, "imu_accel": st.imu_accel_std_g,
              "gyro": st.gyro_std_dps * np.pi / 180.0}
    for s in rec.raw().values():
        if len(s) == 0:
            continue
        if s.kind in limits:
            m = None if models is None else models.get(s.name)
            gain = np.abs(m.gain) if m is not None else SPEC_GAIN[s.kind]
            std = _binned_window_std(s, t0, n_bins, st.grid_s, k)
            has = ~np.isnan(std).any(axis=1)
            still &= ~has | (np.nan_to_num(std, nan=0.0) <= limits[s.kind] * gain).all(axis=1)
            if s.kind in ("accel", "imu_accel"):
                seen |= has
        elif s.kind == "encoder":
            r = _binned_window_range(s, t0, n_bins, st.grid_s, k)
            has = ~np.isnan(r).any(axis=1)
            still &= ~has | (np.nan_to_num(r, nan=0.0) <= st.encoder_range_counts).all(axis=1)
    return grid_t, still & seen


def find_static_segments(
    rec: Recording, settings: StaticDetectionSettings | None = None,
    models: Mapping[str, StreamModel] | None = None,
) -> list[Segment]:
    """Still stretches at least ``min_duration_s`` long, in time order (``models``: see
    :func:`still_mask`)."""
    st = settings or StaticDetectionSettings()
    grid_t, still = still_mask(rec, st, models)
    if not still.any():
        return []
    d = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    out = []
    half = st.grid_s / 2
    for a, b in zip(starts, ends, strict=True):
        seg = Segment(float(max(grid_t[a] - half, rec.t_start_s)),
                      float(min(grid_t[b - 1] + half, rec.t_end_s)))
        if seg.duration_s >= st.min_duration_s - 1e-9:
            out.append(seg)
    return out
