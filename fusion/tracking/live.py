"""The live front of the filter: one instant's raw samples (counts by stream, as the
devices gave them) admitted (:func:`admit_instant`: unknown streams refused; out-of-order,
non-finite and saturated samples counted and skipped), turned into SI readings with the
config's corrections at the IMU's latest temperature, as the
:class:`armfusion.fusion.tracking.update.InstantReadings` the filter's one path
(:meth:`armfusion.fusion.tracking.filter.Tracker.step`) takes. :mod:`armfusion.fusion.tracking.run` admits a
whole recording's samples at once into the same records."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from armfusion.fusion.tracking.settings import ENC, GYRO, MAG
from armfusion.fusion.tracking.update import InstantReadings, MagReading
from armfusion.models.sensor_models import mpu9150_temperature_c


def admit_instant(tr, t: float, samples: Mapping[str, np.ndarray]) -> InstantReadings | None:
    """``samples`` at ``t`` for the (initialised) :class:`armfusion.fusion.tracking.filter.Tracker`
    ``tr``, admitted: None when the instant is out of order (counted)."""
    idx = tr.sensor_index
    unknown = [s for s in samples if s not in idx and s != "imu_temp"]
    if unknown:
        raise KeyError(f"unknown stream {unknown[0]!r}; the tracker takes {list(tr.sensor_names)}")
    if t < tr.t_s - 1e-9:
        tr.health.out_of_order(idx, samples)
        return None
    temp = samples.get("imu_temp")
    if temp is not None:
        raw_t = float(np.ravel(temp)[0])
        if math.isfinite(raw_t):
            tr.readings.temperature_c = float(mpu9150_temperature_c(raw_t))
    phys = tr.health.admit(t, idx, samples, tr.count_limits, tr.readings.physical)
    enc = phys.get(ENC)
    present = [s for s in tr.accel_streams if s in phys]
    acc = None
    if present:
        acc = tr.measurements.readings(np.array([idx[s] for s in present], dtype=np.int64),
                                       np.stack([phys[s][0] for s in present]),
                                       np.stack([phys[s][1] for s in present]))
    mag = phys.get(MAG)
    R_0I = tr.R_0I
    return InstantReadings(None if enc is None else enc[0] / tr.counts_per_rad,
                           R_0I @ phys[GYRO][1] if GYRO in phys else None, acc,
                           None if mag is None else MagReading(mag[0], R_0I @ mag[1]))
