"""The tracker's process model, compiled (numba), for every sigma point: the attitude turned
by the gyro exactly (in Euler angles, :func:`process_points`, or in the filter's tangent space,
:func:`process_points_tangent`), the base's acceleration, jerk and velocity stepped, and the
tangent space's charts (:func:`points_from_tangent`, :func:`tangent_from_points`,
:func:`fold_attitude`). :mod:`armfusion.fusion.tracking.process` calls them; the measurement
models are :mod:`armfusion.fusion.tracking.tracker_kernels`'.

The rotations' equations are :mod:`armfusion.models.rotations`' (``R_from_rpy_into``,
``exp_so3_into``, ``wrap_angle``), compiled here from their one definition. The tests hold
the kernels to the same equations written in NumPy (``tools/bench_track_numpy.py``,
tests/fusion/test_tracker_kernels.py).

The state layout (see :class:`armfusion.fusion.tracking.settings.StateLayout`): joint offsets
``0 … n-1``, roll, pitch, the base's linear acceleration (3), yaw, the gyro bias (3), the IMU
accelerometer's bias (3), and where the base's speed is bounded its velocity (3). Kernels
take the first index of each block.

Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.models.rotations import R_from_rpy_into, exp_so3_into, wrap_angle
from numba import njit

_exp_so3_into = njit(cache=True, nogil=True, inline="always")(exp_so3_into)
_wrap = njit(cache=True, nogil=True, inline="always")(wrap_angle)
_R_into = njit(cache=True, nogil=True, inline="always")(R_from_rpy_into)


@njit(cache=True, nogil=True, inline="always")
def euler_nearest(A, r, p, y):  # pragma: no cover - compiled
    """The roll, pitch and yaw of the rotation ``A (3, 3)`` in the Euler chart nearest
    ``(r, p, y)``: of the two triples that give it, ``(r1, p1, y1)`` with ``|p1| <= pi/2``
    and ``(r1 + pi, ±pi - p1, y1 + pi)``, the one closer to ``(r, p, y)``, its roll and yaw
    unwrapped onto those (so no point jumps a whole turn, and one that had gone past the
    vertical stays in its chart)."""
    p1 = math.atan2(-A[2, 0], math.sqrt(A[2, 1] * A[2, 1] + A[2, 2] * A[2, 2]))
    dr1 = _wrap(math.atan2(A[2, 1], A[2, 2]) - r)
    dy1 = _wrap(math.atan2(A[1, 0], A[0, 0]) - y)
    p2 = math.copysign(math.pi, p1) - p1
    dr2 = _wrap(dr1 + math.pi)
    dy2 = _wrap(dy1 + math.pi)
    if dr1 * dr1 + (p1 - p) * (p1 - p) + dy1 * dy1 <= dr2 * dr2 + (p2 - p) * (p2 - p) + dy2 * dy2:
        return r + dr1, p1, y + dy1
    return r + dr2, p2, y + dy2


@njit(cache=True, nogil=True, inline="always")
def _matmul3_into(A, B, C):  # pragma: no cover - compiled
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True, nogil=True)
def points_from_tangent(X, roll, yaw):  # pragma: no cover - compiled
    """Sigma points ``X (N, n)`` whose attitude columns (roll, pitch, then ``yaw``) hold the
    central point's roll, pitch, yaw plus a world-axis rotation vector (the filter's tangent
    space: the attitude's covariance is that of ``δ`` in ``R = exp([δ]x) R_0``, its x and y
    parts the tilt, its z part the heading), as points whose attitude columns are the Euler
    angles of ``exp([δ]x) R_0``, in the central point's chart (:func:`euler_nearest`). The
    central point ``X[0]`` is the same in both."""
    N = X.shape[0]
    Z = X.copy()
    E = np.empty((3, 3))
    R0 = np.empty((3, 3))
    A = np.empty((3, 3))
    r0, p0, y0 = X[0, roll], X[0, roll + 1], X[0, yaw]
    _R_into(r0, p0, y0, R0)
    for i in range(1, N):
        _exp_so3_into(X[i, roll] - r0, X[i, roll + 1] - p0, _wrap(X[i, yaw] - y0), E)
        _matmul3_into(E, R0, A)
        Z[i, roll], Z[i, roll + 1], Z[i, yaw] = euler_nearest(A, r0, p0, y0)
    return Z


@njit(cache=True, nogil=True)
def tangent_from_points(Y, roll, yaw):  # pragma: no cover - compiled
    """The inverse of :func:`points_from_tangent` about the central point ``Y[0]``: each
    point's attitude as ``Y[0]``'s Euler angles plus ``δ = log(R_i R_0^T)`` (world axes)."""
    N = Y.shape[0]
    Z = Y.copy()
    R0 = np.empty((3, 3))
    Ri = np.empty((3, 3))
    m = np.empty((3, 3))
    r0, p0, y0 = Y[0, roll], Y[0, roll + 1], Y[0, yaw]
    _R_into(r0, p0, y0, R0)
    for i in range(1, N):
        _R_into(Y[i, roll], Y[i, roll + 1], Y[i, yaw], Ri)
        for a in range(3):  # m = R_i R_0^T
            for b in range(3):
                m[a, b] = Ri[a, 0] * R0[b, 0] + Ri[a, 1] * R0[b, 1] + Ri[a, 2] * R0[b, 2]
        vx, vy, vz = 0.5 * (m[2, 1] - m[1, 2]), 0.5 * (m[0, 2] - m[2, 0]), 0.5 * (m[1, 0] - m[0, 1])
        c = min(1.0, max(-1.0, 0.5 * (m[0, 0] + m[1, 1] + m[2, 2] - 1.0)))
        s = math.sqrt(vx * vx + vy * vy + vz * vz)
        k = 1.0 if s < 1e-12 else math.atan2(s, c) / s
        Z[i, roll], Z[i, roll + 1], Z[i, yaw] = r0 + k * vx, p0 + k * vy, y0 + k * vz
    return Z


@njit(cache=True, nogil=True, inline="always")
def _canonical_euler(A):  # pragma: no cover - compiled
    """Roll, pitch (within ±pi/2) and yaw of the rotation ``A (3, 3)``
    (:func:`armfusion.models.rotations.rpy_from_R`, pitch by ``atan2`` to stay exact near ±pi/2)."""
    pitch = math.atan2(-A[2, 0], math.sqrt(A[2, 1] * A[2, 1] + A[2, 2] * A[2, 2]))
    return math.atan2(A[2, 1], A[2, 2]), pitch, math.atan2(A[1, 0], A[0, 0])


@njit(cache=True, nogil=True)
def process_points_tangent(X, dt, w, have_w, roll, yaw, bias, accel, scale, accel_decay, vel=-1,
                           vel_gain=0.0, jerk=-1, jerk_decay=1.0):  # pragma: no cover
    """:func:`process_points` for points whose attitude is in the filter's tangent space
    (:func:`points_from_tangent`), in one pass: each point's rotation ``exp([δ]x) R_0``,
    turned by its gyro rates, ``R' = R exp([w dt]x)``, taken back into the tangent space
    about the propagated central point ``R_0'``. Returns ``(T, Y)``: the propagated points
    in the tangent space (about ``R_0'``'s canonical Euler angles) and each as canonical
    Euler angles (the same rotations, for the measurement models: they use the angles'
    sines and cosines, and wrap the heading). ``scale``: as :func:`process_points`.

    With a velocity block (``vel >= 0``: :attr:`armfusion.fusion.tracking.settings.StateLayout.vel`)
    the base's acceleration is the derivative of a bounded velocity
    (:func:`_velocity_step`); without, it only decays, and with a jerk block (``jerk >= 0``:
    :attr:`armfusion.fusion.tracking.settings.StateLayout.jerk`) it changes by the jerk over ``dt``
    (``a' = a e^(-dt/τ_a) + j dt``), the jerk decaying by ``jerk_decay``."""
    N = X.shape[0]
    T = X.copy()
    Y = X.copy()
    E = np.empty((3, 3))
    R0 = np.empty((3, 3))
    Ri = np.empty((3, 3))
    A = np.empty((3, 3))
    C0 = np.empty((3, 3))
    r0, p0, y0 = X[0, roll], X[0, roll + 1], X[0, yaw]
    _R_into(r0, p0, y0, R0)
    e0r = e0p = e0y = 0.0
    for i in range(N):
        if i == 0:  # the point's rotation
            Ri[:, :] = R0
        else:
            _exp_so3_into(X[i, roll] - r0, X[i, roll + 1] - p0, X[i, yaw] - y0, E)
            _matmul3_into(E, R0, Ri)
        if have_w:  # turned by the gyro, less the point's own bias (and scale about z)
            wz = w[2] - X[i, bias + 2]
            if scale >= 0:
                wz /= 1.0 + X[i, scale]
            _exp_so3_into(dt * (w[0] - X[i, bias]), dt * (w[1] - X[i, bias + 1]), dt * wz, E)
            _matmul3_into(Ri, E, A)
        else:
            A[:, :] = Ri
        er, ep, ey = _canonical_euler(A)
        Y[i, roll], Y[i, roll + 1], Y[i, yaw] = er, ep, ey
        if i == 0:
            e0r, e0p, e0y = er, ep, ey
            C0[:, :] = A
            T[0, roll], T[0, roll + 1], T[0, yaw] = er, ep, ey
        else:
            vx, vy, vz = _turn_from(A, C0)
            T[i, roll], T[i, roll + 1], T[i, yaw] = e0r + vx, e0p + vy, e0y + vz
        _linear_step(X, T, Y, i, dt, E, have_w, accel, accel_decay, vel, vel_gain, jerk, jerk_decay)
    return T, Y


@njit(cache=True, nogil=True, inline="always")
def _turn_from(A, C0):  # pragma: no cover - compiled
    """The rotation vector (world axes) of ``log(A C0^T)``: a point's turn ``A`` from the
    central point's ``C0`` (only the skew part and the trace of the product are needed)."""
    b10 = A[1, 0] * C0[0, 0] + A[1, 1] * C0[0, 1] + A[1, 2] * C0[0, 2]
    b01 = A[0, 0] * C0[1, 0] + A[0, 1] * C0[1, 1] + A[0, 2] * C0[1, 2]
    b20 = A[2, 0] * C0[0, 0] + A[2, 1] * C0[0, 1] + A[2, 2] * C0[0, 2]
    b02 = A[0, 0] * C0[2, 0] + A[0, 1] * C0[2, 1] + A[0, 2] * C0[2, 2]
    b21 = A[2, 0] * C0[1, 0] + A[2, 1] * C0[1, 1] + A[2, 2] * C0[1, 2]
    b12 = A[1, 0] * C0[2, 0] + A[1, 1] * C0[2, 1] + A[1, 2] * C0[2, 2]
    tr = (A[0, 0] * C0[0, 0] + A[0, 1] * C0[0, 1] + A[0, 2] * C0[0, 2]
          + A[1, 0] * C0[1, 0] + A[1, 1] * C0[1, 1] + A[1, 2] * C0[1, 2]
          + A[2, 0] * C0[2, 0] + A[2, 1] * C0[2, 1] + A[2, 2] * C0[2, 2])
    vx, vy, vz = 0.5 * (b21 - b12), 0.5 * (b02 - b20), 0.5 * (b10 - b01)
    c = min(1.0, max(-1.0, 0.5 * (tr - 1.0)))
    sn = math.sqrt(vx * vx + vy * vy + vz * vz)
    k = 1.0 if sn < 1e-12 else math.atan2(sn, c) / sn
    return k * vx, k * vy, k * vz


@njit(cache=True, nogil=True, inline="always")
def _linear_step(X, T, Y, i, dt, E, have_w, accel, accel_decay, vel, vel_gain, jerk,
                 jerk_decay):  # pragma: no cover - compiled
    """Point ``i``'s base acceleration (and velocity, or jerk) over ``dt`` into ``T`` and
    ``Y``: :func:`_velocity_step` with a velocity block (``vel >= 0``), else the
    acceleration decays by ``accel_decay`` and, with a jerk block (``jerk >= 0``), changes
    by the jerk over ``dt``, the jerk decaying by ``jerk_decay``."""
    if vel >= 0:
        _velocity_step(X, T, i, dt, E, have_w, accel, accel_decay, vel, vel_gain)
        for c3 in range(3):
            Y[i, accel + c3] = T[i, accel + c3]
            Y[i, vel + c3] = T[i, vel + c3]
        return
    for c3 in range(3):
        v = X[i, accel + c3] * accel_decay
        if jerk >= 0:
            v += dt * X[i, jerk + c3]
            jv = X[i, jerk + c3] * jerk_decay
            Y[i, jerk + c3] = jv
            T[i, jerk + c3] = jv
        Y[i, accel + c3] = v
        T[i, accel + c3] = v


@njit(cache=True, nogil=True, inline="always")
def _velocity_step(X, T, i, dt, E, have_w, accel, accel_decay, vel, vel_gain):  # pragma: no cover
    """Point ``i``'s base acceleration ``a`` and velocity ``v`` (both base axes) over ``dt``,
    written into ``T``: in world axes ``v' = a`` and ``a' = -a / τ_a - v / (τ_a τ_v)``
    (``accel_decay = exp(-dt / τ_a)``, ``vel_gain = dt / (τ_a τ_v)``): a damped oscillator
    for the velocity in the world, whose acceleration averages to zero over time however
    large it is (a hand, or anything whose speed is bounded, cannot accelerate one way for
    long), where a first-order acceleration alone can hold a sustained acceleration (and so
    a tilt) for as long as it likes. The step is taken in the world (in the base's axes at
    the interval's start) and the result turned into the base's axes at its end by the
    point's own turn over it, ``E = exp([ω dt]x)`` (``ω`` its gyro rates less its bias):
    ``v' = E^T (v + a dt)``, exactly, at any turn rate (a first-order ``- ω × v dt`` lengthens
    each vector by ``(|ω| dt)² / 2`` a step: at 1000 °/s and 285 Hz, by 70 % in a second)."""
    vx, vy, vz = X[i, vel], X[i, vel + 1], X[i, vel + 2]
    ax, ay, az = X[i, accel], X[i, accel + 1], X[i, accel + 2]
    ux, uy, uz = vx + dt * ax, vy + dt * ay, vz + dt * az
    bx = ax * accel_decay - vel_gain * vx
    by = ay * accel_decay - vel_gain * vy
    bz = az * accel_decay - vel_gain * vz
    if have_w:  # into the base's axes at the interval's end: E^T
        T[i, vel] = E[0, 0] * ux + E[1, 0] * uy + E[2, 0] * uz
        T[i, vel + 1] = E[0, 1] * ux + E[1, 1] * uy + E[2, 1] * uz
        T[i, vel + 2] = E[0, 2] * ux + E[1, 2] * uy + E[2, 2] * uz
        T[i, accel] = E[0, 0] * bx + E[1, 0] * by + E[2, 0] * bz
        T[i, accel + 1] = E[0, 1] * bx + E[1, 1] * by + E[2, 1] * bz
        T[i, accel + 2] = E[0, 2] * bx + E[1, 2] * by + E[2, 2] * bz
    else:
        T[i, vel], T[i, vel + 1], T[i, vel + 2] = ux, uy, uz
        T[i, accel], T[i, accel + 1], T[i, accel + 2] = bx, by, bz


@njit(cache=True, nogil=True)
def fold_attitude(x, anchor, roll, yaw):  # pragma: no cover - compiled
    """``x (n,)`` whose attitude columns hold ``anchor (3,)`` (roll, pitch, yaw) plus a
    world-axis rotation vector ``δ`` -> a copy whose attitude columns are the canonical
    Euler angles of ``exp([δ]x) R(anchor)`` (pitch within ±pi/2, roll and yaw within
    ±pi): the reset of the filter's tangent space (:func:`points_from_tangent`)."""
    out = x.copy()
    E = np.empty((3, 3))
    R0 = np.empty((3, 3))
    A = np.empty((3, 3))
    _exp_so3_into(x[roll] - anchor[0], x[roll + 1] - anchor[1], _wrap(x[yaw] - anchor[2]), E)
    _R_into(anchor[0], anchor[1], anchor[2], R0)
    _matmul3_into(E, R0, A)
    out[roll], out[roll + 1], out[yaw] = _canonical_euler(A)
    return out


@njit(cache=True, nogil=True)
def process_points(X, dt, w, have_w, roll, yaw, bias, accel, scale, accel_decay, jerk=-1,
                   jerk_decay=1.0):  # pragma: no cover
    """The process model at every sigma point ``X (N, n)`` -> ``(N, n)``.

    With a gyro reading ``w`` (rad/s, body axes; ``have_w``), each point's rates minus its
    own gyro bias (its z rate divided by ``1 + s``, the point's scale error in column ``scale``
    where that is not -1) turn its attitude over ``dt`` exactly: ``R' = R exp([w dt]x)`` with
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``, read back as Euler angles in the chart nearest the
    point's (:func:`euler_nearest`; exact at any rate, where a rule on the Euler-angle rates
    loses accuracy at a hand's 1000 deg/s and breaks down near pitch ±90 deg);
    the base's acceleration decays by ``accel_decay`` (and changes by its jerk over ``dt``
    where ``jerk`` is not -1, the jerk decaying by ``jerk_decay``); everything else stays. Roll and yaw
    are not wrapped here (the filter holds the attitude's spread as a tangent vector and
    folds the mean back into canonical Euler angles:
    :meth:`armfusion.fusion.tracking.process.ProcessModel.fold_attitude`)."""
    N, n = X.shape
    Y = X.copy()
    E = np.empty((3, 3))
    R = np.empty((3, 3))
    A = np.empty((3, 3))
    for i in range(N):
        if have_w:
            wz = w[2] - X[i, bias + 2]
            if scale >= 0:
                wz /= 1.0 + X[i, scale]
            _exp_so3_into(dt * (w[0] - X[i, bias]), dt * (w[1] - X[i, bias + 1]), dt * wz, E)
            _R_into(X[i, roll], X[i, roll + 1], X[i, yaw], R)
            _matmul3_into(R, E, A)
            Y[i, roll], Y[i, roll + 1], Y[i, yaw] = euler_nearest(A, X[i, roll], X[i, roll + 1], X[i, yaw])
        for c in range(3):
            Y[i, accel + c] = X[i, accel + c] * accel_decay
            if jerk >= 0:
                Y[i, accel + c] += dt * X[i, jerk + c]
                Y[i, jerk + c] = X[i, jerk + c] * jerk_decay
    return Y


