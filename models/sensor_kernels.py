"""What an ideal accelerometer and compass read, compiled (numba): each equation written once.

- The accelerometer (:func:`specific_force_one`): a sensor whose point accelerates with
  ``a`` (base axes, m/s², gravity not included) in a base whose world-up is ``up`` (base
  axes, unit) reads the specific force ``f = R_0S^T (a + g up)`` in its own axes: gravity
  plus motion (:func:`gravity_plus`), turned into the sensor's axes (:func:`to_sensor_axes`).
  The batch model (:func:`armfusion.models.motion.sensor_motion`, through
  :func:`armfusion.models.chain_kernels.sensor_one`) and the tracker's measurement model
  (:func:`armfusion.fusion.tracking.tracker_kernels.measurement_points`, which turns the sum by each
  sigma point's joint angles between the two steps) both call these.
- World-up in the axes of a base at roll and pitch (:func:`tilt_up`, from their sines and
  cosines): ``[-sin p, sin r cos
  p, cos r cos p]`` (the compiled form of :func:`armfusion.models.rotations.up_from_tilt`).
- The compass (:func:`magnetic_heading_one`): the heading of a base at roll and pitch whose
  magnetometer reads ``m`` (base axes) is ``atan2(-h_y, h_x)`` of the de-tilted field ``h =
  Ry(p) Rx(r) m`` (the compiled form of :func:`armfusion.fusion.tracking.heading.tilt_compensated_heading`,
  before the declination and the wrap).
- Still accelerometers (:func:`still_readings_batch`, for :func:`armfusion.models.kinematics.gravity_in_sensors`
  and :func:`armfusion.models.kinematics.gravity_jacobian`): the accelerometer's equation with no
  motion, in g.

Everything is plain float arithmetic on three components, inlined into the kernels that
call it. Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import numpy as np
from armfusion.models.rotations import up_from_sines
from numba import njit

# World-up in base axes from the sines and cosines of roll and pitch: the equation of
# armfusion.models.rotations.up_from_tilt, compiled.
tilt_up = njit(cache=True, nogil=True, inline="always")(up_from_sines)


@njit(cache=True, nogil=True, inline="always")
def gravity_plus(a0, a1, a2, u0, u1, u2, g_mps2):  # pragma: no cover - compiled
    """Specific force in base axes, m/s²: the point's acceleration ``a`` plus ``g up``."""
    return a0 + g_mps2 * u0, a1 + g_mps2 * u1, a2 + g_mps2 * u2


@njit(cache=True, nogil=True, inline="always")
def to_sensor_axes(R_0S, v0, v1, v2):  # pragma: no cover - compiled
    """``R_0S^T v``: a base-axis vector in the sensor's own axes, three floats."""
    return (R_0S[0, 0] * v0 + R_0S[1, 0] * v1 + R_0S[2, 0] * v2,
            R_0S[0, 1] * v0 + R_0S[1, 1] * v1 + R_0S[2, 1] * v2,
            R_0S[0, 2] * v0 + R_0S[1, 2] * v1 + R_0S[2, 2] * v2)


@njit(cache=True, nogil=True, inline="always")
def specific_force_one(R_0S, a0, a1, a2, u0, u1, u2, g_mps2):  # pragma: no cover - compiled
    """What an ideal accelerometer reads, m/s², its own axes: ``R_0S^T (a + g up)``."""
    s0, s1, s2 = gravity_plus(a0, a1, a2, u0, u1, u2, g_mps2)
    return to_sensor_axes(R_0S, s0, s1, s2)


def magnetic_heading(m0, m1, m2, sr, cr, sp, cp):
    """Magnetic heading (rad, in [-pi, pi]) of a base at roll r and pitch p (``sin r, cos r,
    sin p, cos p``) whose magnetometer reads ``m`` (base axes): ``atan2(-h_y, h_x)``, ``h =
    Ry(p) Rx(r) m``. Plain arithmetic: floats or arrays alike (``armfusion.fusion.tracking.heading``
    calls it batched), and compiled below as :func:`magnetic_heading_one`."""
    y1 = cr * m1 - sr * m2
    hx = cp * m0 + sp * (sr * m1 + cr * m2)
    return np.arctan2(-y1, hx)


magnetic_heading_one = njit(cache=True, nogil=True, inline="always")(magnetic_heading)


@njit(cache=True, nogil=True)
def still_readings_batch(R_0S, up):  # pragma: no cover - compiled
    """What still accelerometers read, in g: :func:`specific_force_one` with no motion and
    ``g = 1`` for every instant and sensor, ``R_0S (N, S, 3, 3)``, world-up ``up (N, 3)`` ->
    ``(N, S, 3)`` (``R_0S^T up``)."""
    N, S = R_0S.shape[0], R_0S.shape[1]
    out = np.empty((N, S, 3))
    for t in range(N):
        for s in range(S):
            out[t, s, 0], out[t, s, 1], out[t, s, 2] = specific_force_one(
                R_0S[t, s], 0.0, 0.0, 0.0, up[t, 0], up[t, 1], up[t, 2], 1.0)
    return out
