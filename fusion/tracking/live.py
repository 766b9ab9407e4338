"""The live front of the filter: one instant's raw samples (counts by stream, as the
devices gave them) checked (unknown streams refused; out-of-order, non-finite and
saturated samples counted and skipped), turned into SI readings with the config's
corrections at the IMU's latest temperature, and fed to the filter's one path
(:meth:`fusion.tracking.filter.Tracker._instant`). :mod:`fusion.tracking.run` is the same
for a whole recording."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from fusion.tracking.estimate import Estimate
from fusion.tracking.settings import ENC, GYRO, MAG
from models.sensor_models import mpu9150_temperature_c


def fuse_instant(tr, t_s: float, samples: Mapping[str, np.ndarray]) -> Estimate | None:
    """Fuse ``samples`` at ``t_s`` into the (initialised) tracker ``tr``: its estimate after
    them, or None when nothing was fused (out of order, or before the first encoder sample)."""
    idx = tr._sidx
    unknown = [s for s in samples if s not in idx and s != "imu_temp"]
    if unknown:
        raise KeyError(f"unknown stream {unknown[0]!r}; the tracker takes {list(tr.sensor_names)}")
    t = float(t_s)
    if t < tr.t_s - 1e-9:
        tr.health.out_of_order(idx, samples)
        return None
    temp = samples.get("imu_temp")
    if temp is not None:
        raw_t = float(np.ravel(temp)[0])
        if math.isfinite(raw_t):
            tr.readings.temperature_c = float(mpu9150_temperature_c(raw_t))
    phys = tr.health.admit(t, idx, samples, tr._limits, tr.readings.physical)
    enc = phys.get(ENC)
    present = [s for s in tr.accel_streams if s in phys]
    acc = None
    if present:
        sel = np.array([idx[s] for s in present], dtype=np.int64)
        acc = (sel, np.stack([phys[s][0] for s in present]), np.stack([phys[s][1] for s in present]),
               tr.measurements.selection(sel))
    mag = phys.get(MAG)
    R_0I = tr.R_0I
    if not tr._instant(t, None if enc is None else enc[0] / tr.counts_per_rad,
                       R_0I @ phys[GYRO][1] if GYRO in phys else None, acc,
                       None if mag is None else (mag[0], R_0I @ mag[1])):
        return None
    return tr.estimate
