"""A bolted base's tilt and what the link accelerometers' unmodelled error leaves in it.

A fixed base's tilt takes no random walk: every reading of gravity adds to what the filter
knows of it, and the filter counts each sample's unmodelled-error floor
(``calibration.accel_unmodelled_g``, or the sensor class's) as fresh noise, so its own tilt
sigma shrinks with the number of samples (on the UR5 twin to 0.06° while the roll was 0.5°
off). The floor is not fresh noise: a mount a degree off, a scale 4 % low, an offset, stay.
An accelerometer whose reading of 1 g errs by ``f`` g on each axis turns the direction of
gravity it reads by up to ``f`` rad about each horizontal axis, however long it is read;
independent sensors' errors combine as information does (``1 / f² = Σ 1 / f_i²``). So the
readings cannot place the tilt better than ``f``: the reported tilt's variance is at least
the smaller of ``f²`` and the variance the filter started from (the startup's, which holds
the floor as a floor, or the installer's level, which the readings need not better). That
floor joins the reported roll and pitch and the joint-and-tilt block the combinations come
from, never the filter's own covariance (a sigma floor, not a change in what the filter
weighs). A base that moves takes the same floor (its attitude walk did not keep a chair's
reported tilt from 0.03° while it was 2° off), with its IMU's floor where the base only
yaws (the IMU's bias, a state of the filter, is revealed only by turning about a horizontal
axis), and not bounded by the start's variance (a still average, which the floor bounds).
"""

from __future__ import annotations

import numpy as np


def floor_var_rad2(floors_g: np.ndarray) -> float:
    """The variance (rad²) the link accelerometers' floors ``floors_g`` (g, one per sensor)
    leave in the tilt they read together, however long: ``1 / Σ 1 / f_i²``; 0 where a sensor
    is stated exact (a floor of 0: the config's word) or there is none."""
    f = np.asarray(floors_g, float)
    if f.size == 0 or np.any(f <= 0.0):
        return 0.0
    return float(1.0 / np.sum(1.0 / f**2))


def tilt_shortfall_var(floor_var: float, P_tilt: np.ndarray, P0_tilt: np.ndarray) -> np.ndarray:
    """What the reported tilt variances (rad², roll and pitch) add to the filter's ``P_tilt``
    so that neither is below ``min(P0, floor_var)``: per axis its shortfall (0 where none, or
    where ``floor_var`` is 0)."""
    P, P0 = np.asarray(P_tilt, float), np.asarray(P0_tilt, float)
    if floor_var <= 0.0:
        return np.zeros_like(P)
    return np.maximum(np.minimum(P0, floor_var) - P, 0.0)
