"""REP 103 and REP 145 for armfusion's attitude: one place for the conversion.

armfusion's world frame has x to (magnetic or true) north, y to the west and z up; its
heading is the base's yaw counter-clockwise from north (0 facing north, +pi/2 facing west),
and the base's attitude is ``R_WB = Rz(heading) Ry(pitch) Rx(roll)`` (docs/tracking.md).
REP 103's world is ENU (x east, y north, z up), yaw counter-clockwise from east: the same
up axis, turned by +pi/2 about it, so ``R_ENU_B = Rz(pi/2) R_WB = Rz(heading + pi/2)
Ry(pitch) Rx(roll)``: roll and pitch are unchanged, the ENU yaw is the heading plus pi/2
(:func:`armfusion.fusion.tracking.estimate.yaw_enu_rad`, which the heading feed's ``yaw_enu_rad`` uses).

REP 145 (and ``sensor_msgs/Imu``): each covariance is 3 x 3, row-major, about the x, y and z
axes; a quantity not estimated has ``-1`` in its covariance's first element. armfusion
estimates the orientation (its roll, pitch and heading sigmas on the diagonal; the
cross-covariances are not kept per instant and are written as 0), not the angular velocity
or the linear acceleration, whose covariances are ``-1`` in element 0.
"""

from __future__ import annotations

import numpy as np

ENU_FROM_ARMFUSION_YAW_RAD = np.pi / 2
"""The ENU yaw of a heading of 0 (facing north): +pi/2 (north is ENU's +y)."""
NOT_ESTIMATED = -1.0
"""REP 145: the first element of a covariance whose quantity is not estimated."""


def enu_quaternion_xyzw(rpy_rad: np.ndarray) -> np.ndarray:
    """The base's orientation in ENU, ``(..., 4)`` as ROS orders a quaternion (x, y, z, w; w >= 0),
    from armfusion's roll, pitch and heading ``(..., 3)``: ``Rz(yaw_enu) Ry(pitch) Rx(roll)``."""
    rpy = np.asarray(rpy_rad, float)
    r, p, y = rpy[..., 0] / 2, rpy[..., 1] / 2, (rpy[..., 2] + ENU_FROM_ARMFUSION_YAW_RAD) / 2
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    q = np.stack([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                  cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy], axis=-1)
    return np.where(q[..., 3:] < 0, -q, q)


def orientation_covariance(rpy_sigma_rad: np.ndarray) -> np.ndarray:
    """``(..., 9)``: the 3 x 3 row-major covariance about x, y, z (roll, pitch, yaw) with the
    sigmas' squares on its diagonal."""
    s = np.asarray(rpy_sigma_rad, float)
    cov = np.zeros((*s.shape[:-1], 9))
    cov[..., 0], cov[..., 4], cov[..., 8] = s[..., 0] ** 2, s[..., 1] ** 2, s[..., 2] ** 2
    return cov


def not_estimated() -> np.ndarray:
    """The covariance of a quantity not estimated: ``-1`` then zeros (REP 145)."""
    cov = np.zeros(9)
    cov[0] = NOT_ESTIMATED
    return cov
