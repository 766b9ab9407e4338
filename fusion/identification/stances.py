"""The chair's parked stances in a recording (:func:`parked_stances`): where it stands still,
each stance with its own base attitude in the fit, and the windows while it moves between
them left out (:func:`~armfusion.fusion.identification.data.data_from_recording` with
``stances=True``).
"""

from __future__ import annotations

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG
from armfusion.models.sensor_models import stream_models


def parked_stances(arm: ArmModel, rec, t_windows_s: np.ndarray, window: int,
                   rate_threshold_rad_s: float = 0.3 * DEG, accel_threshold_g: float = 0.005,
                   margin_s: float = 1.0, min_stance_s: float = 10.0):
    """Where the chair stands parked: per window (``t_windows_s``, means of ``window``
    encoder samples), the stance it belongs to and whether it is parked.

    The chair moves where the IMU's gyro departs from its median (the gyro bias: a
    calibration stands parked most of the time) by more than ``rate_threshold_rad_s`` on
    some axis, or where its accelerometer's window mean changes from one window to the next
    by more than ``accel_threshold_g`` (rolling onto a slope, driving); the arm's own motion
    moves neither. Those windows, ``margin_s`` either side and parked stretches shorter than
    ``min_stance_s`` are left out. Every window gets the nearest stance (so a time
    derivative across the edge of a stance sees one attitude). Returns ``(stance, used)``,
    or ``(None, None)`` when the chair never moves (one stance, every window).
    """
    if arm.imu is None:
        raise ValueError("finding the parked stances needs the base IMU's gyro and accelerometer")
    models = stream_models(arm)
    n = len(t_windows_s)
    moving = np.zeros(n, bool)
    for name, thr, diff in (("imu_gyro", rate_threshold_rad_s, False), ("imu_acc", accel_threshold_g, True)):
        st = rec.get(name)
        if st is None or len(st) == 0:
            raise ValueError(f"finding the parked stances needs the IMU's {name!r} stream")
        v = models[name].from_counts(np.asarray(st.values, float))
        ts = np.asarray(st.t_s, float)
        # the stream's mean over each window, on the windows' own instants
        half = 0.5 * window * np.median(np.diff(ts)) if len(ts) > 1 else 0.0
        cs = np.vstack([np.zeros((1, v.shape[1])), np.cumsum(v, 0)])
        a = np.searchsorted(ts, t_windows_s - half)
        b = np.maximum(np.searchsorted(ts, t_windows_s + half), a + 1)
        b = np.minimum(b, len(ts))
        m = (cs[b] - cs[a]) / np.maximum(b - a, 1)[:, None]
        if diff:
            d = np.zeros(n)
            d[1:] = np.max(np.abs(np.diff(m, axis=0)), 1)
            moving |= d > thr
            moving[:-1] |= d[1:] > thr
        else:
            moving |= np.max(np.abs(m - np.median(m, 0)), 1) > thr
    if not moving.any():
        return None, None
    dt = float(np.median(np.diff(t_windows_s))) if n > 1 else 1.0
    pad = int(np.ceil(margin_s / dt))
    grown = moving.copy()
    for k in range(1, pad + 1):
        grown[k:] |= moving[:-k]
        grown[:-k] |= moving[k:]
    parked = ~grown
    # runs of parked windows
    edges = np.flatnonzero(np.diff(np.concatenate([[0], parked.astype(int), [0]])))
    runs = [(a, b) for a, b in zip(edges[::2], edges[1::2], strict=True) if (b - a) * dt >= min_stance_s]
    if not runs:
        raise ValueError("the chair never stands parked for "
                         f"{min_stance_s:g} s: no stance to calibrate on")
    used = np.zeros(n, bool)
    for a, b in runs:
        used[a:b] = True
    # every window to its nearest run (by index distance to the run's ends)
    idx = np.arange(n)
    dist = np.stack([np.where(idx < a, a - idx, np.where(idx >= b, idx - b + 1, 0)) for a, b in runs])
    return np.argmin(dist, 0), used
