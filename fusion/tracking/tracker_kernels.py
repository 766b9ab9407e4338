"""The tracker's process and measurement models, compiled (numba), for every sigma point.

A tracker step evaluates its models at 2n + 1 = 39 sigma points of a 19-state filter: a
few thousand floating-point operations, which as NumPy array calls cost far more in
interpreter overhead than in arithmetic. These kernels do the same arithmetic in one
compiled loop per call. :mod:`fusion.tracking.tracker` calls them. The accelerometer's and the
compass's equations are :mod:`models.sensor_kernels`' (written once there, for the batch
models too). The tests hold the kernels to the motion model computed from scratch
(:func:`models.motion.specific_force`, tests/fusion/test_tracker.py) and to the same
equations written in NumPy (``tools/bench_track_numpy.py``, the filterpy baseline of
``tools/bench_track.py``, tests/fusion/test_tracker_kernels.py).

The state layout (see :class:`fusion.tracking.tracker.StateLayout`): joint offsets ``0 … n-1``,
roll, pitch, the base's linear acceleration (3), yaw, the gyro bias (3), the IMU
accelerometer's bias (3). Kernels take the first index of each block.

Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from models.chain_kernels import cross3
from models.rotations import TWO_PI
from models.sensor_kernels import gravity_plus, magnetic_heading_one, tilt_up, to_sensor_axes


@njit(cache=True, nogil=True)
def process_points(X, dt, w, have_w, roll, yaw, bias, accel, accel_decay):  # pragma: no cover - compiled
    """The process model at every sigma point ``X (N, n)`` -> ``(N, n)``.

    With a gyro reading ``w`` (rad/s, body axes; ``have_w``), each point's rates minus its
    own gyro bias turn its attitude over ``dt`` (midpoint rule on the rates of
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``: roll rate ``w_x + (sin r w_y + cos r w_z) tan p``,
    pitch rate ``cos r w_y - sin r w_z``, yaw rate ``(sin r w_y + cos r w_z) / cos p``);
    the base's acceleration decays by ``accel_decay``; everything else stays. Yaw is not
    wrapped here (the unscented mean wraps it)."""
    N, n = X.shape
    Y = X.copy()
    for i in range(N):
        if have_w:
            w0 = w[0] - X[i, bias]
            w1 = w[1] - X[i, bias + 1]
            w2 = w[2] - X[i, bias + 2]
            r, p = X[i, roll], X[i, roll + 1]
            sr, cr = math.sin(r), math.cos(r)
            # the rates at the start, half a step, then the rates at the midpoint
            b = sr * w1 + cr * w2
            r_mid = r + 0.5 * dt * (w0 + b * math.tan(p))
            p_mid = p + 0.5 * dt * (cr * w1 - sr * w2)
            sr, cr = math.sin(r_mid), math.cos(r_mid)
            b = sr * w1 + cr * w2
            Y[i, roll] = r + dt * (w0 + b * math.tan(p_mid))
            Y[i, roll + 1] = p + dt * (cr * w1 - sr * w2)
            Y[i, yaw] = X[i, yaw] + dt * (b / math.cos(p_mid))
        for c in range(3):
            Y[i, accel + c] = X[i, accel + c] * accel_decay
    return Y


@njit(cache=True, nogil=True)
def measurement_points(X, sel, links, axes, offset_ref, motion_mps2, R_0S, imu_index, roll, accel, yaw,
                       imu_bias, g_mps2, still, m_B, heading_shift):  # pragma: no cover - compiled
    """Every measurement of one update at every sigma point ``X (N, n)`` -> ``(N, m)``.

    Columns: the accelerometers ``sel`` (indices into the tracker's accelerometers; three
    columns each, specific force in g, in ``sel``'s order), then with ``still`` the base's
    acceleration (three columns: a parked chair's is zero), then, when ``m_B`` (the
    magnetometer's mean field, base axes, µT) is finite, the heading residual
    ``yaw - tilt-compensated heading`` wrapped to [-pi, pi) (``heading_shift``:
    declination - pi).

    The accelerometers (the model of :mod:`models.sensor_kernels`, ``f = R_0S^T (a + g up)``):
    each point's base-axis specific force is the frame's motion acceleration (at the mean
    pose) plus the point's base acceleration plus gravity turned by its roll and pitch (``g
    up``, :func:`models.sensor_kernels.tilt_up`), carried to the sensor by the joints
    between the base and its link. The point's joint angles
    differ from the frame's by ``d_j = offset_j - offset_ref_j``, so its rotation is the
    frame's times ``exp([a_j]x d_j)`` for each joint ``j`` below the link (product of
    exponentials about the base-axis joint axes ``axes`` of the frame): in row form
    ``f^T = v^T E_0 … E_(link-1) R_0S / g``, each ``v^T E_j`` being
    ``v - sin d (a x v) + (1 - cos d) a x (a x v)``. The IMU (``imu_index``) adds its bias.
    The heading is :func:`models.sensor_kernels.magnetic_heading_one` at the point's roll and
    pitch: the residual ``yaw - heading - heading_shift``, wrapped.
    """
    N = X.shape[0]
    k = sel.shape[0]
    n_joints = axes.shape[0]
    have_mag = math.isfinite(m_B[0]) and math.isfinite(m_B[1]) and math.isfinite(m_B[2])
    m = 3 * k + (3 if still else 0) + (1 if have_mag else 0)
    Z = np.empty((N, m))
    sd = np.empty(n_joints)
    omc = np.empty(n_joints)
    for i in range(N):
        sr, cr = math.sin(X[i, roll]), math.cos(X[i, roll])
        sp, cp = math.sin(X[i, roll + 1]), math.cos(X[i, roll + 1])
        u0, u1, u2 = tilt_up(sr, cr, sp, cp)
        # the base's specific force: its acceleration plus g up
        b0, b1, b2 = gravity_plus(X[i, accel], X[i, accel + 1], X[i, accel + 2], u0, u1, u2, g_mps2)
        for j in range(n_joints):
            d = X[i, j] - offset_ref[j]
            sd[j] = math.sin(d)
            omc[j] = 1.0 - math.cos(d)
        for c in range(k):
            s = sel[c]
            v0 = motion_mps2[s, 0] + b0
            v1 = motion_mps2[s, 1] + b1
            v2 = motion_mps2[s, 2] + b2
            for j in range(links[s]):
                a0, a1, a2 = axes[j, 0], axes[j, 1], axes[j, 2]
                c0, c1, c2 = cross3(a0, a1, a2, v0, v1, v2)  # a x v
                e0, e1, e2 = cross3(a0, a1, a2, c0, c1, c2)  # a x (a x v)
                v0 = v0 - sd[j] * c0 + omc[j] * e0
                v1 = v1 - sd[j] * c1 + omc[j] * e1
                v2 = v2 - sd[j] * c2 + omc[j] * e2
            f0, f1, f2 = to_sensor_axes(R_0S[s], v0, v1, v2)
            Z[i, 3 * c], Z[i, 3 * c + 1], Z[i, 3 * c + 2] = f0 / g_mps2, f1 / g_mps2, f2 / g_mps2
            if s == imu_index:
                for r in range(3):
                    Z[i, 3 * c + r] += X[i, imu_bias + r]
        col = 3 * k
        if still:
            for r in range(3):
                Z[i, col + r] = X[i, accel + r]
            col += 3
        if have_mag:
            d = X[i, yaw] - magnetic_heading_one(m_B[0], m_B[1], m_B[2], sr, cr, sp, cp) - heading_shift
            Z[i, col] = (d % TWO_PI) - math.pi
    return Z
