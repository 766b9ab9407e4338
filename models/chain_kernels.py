"""The kinematic chain and its motion, compiled (numba): the one written form of each equation.

Three equations, each written once here for ONE instant and called by every path:

- :func:`pose_one`, forward kinematics: with ``theta = q + offset_rad``, per joint ``p <- p +
  R p_pre``, ``R <- R R_pre``; the joint's axis ``R a`` and origin ``p``; ``R <- R
  exp([a]x theta)`` (``R Rz(theta)`` when every axis is z); ``p <- p + R p_post``, ``R <- R
  R_post``.
- :func:`motion_one`, the outward recursion (recursive Newton-Euler's outward pass): at
  joint i with axis z and origin o, ``ω_i = ω_(i-1) + z q̇``, ``ω̇_i = ω̇_(i-1) + z q̈ + ω_(i-1)
  x z q̇``; a point P fixed in a link at lever arm r from a point O of the same link has
  ``v_P = v_O + ω x r``, ``a_P = a_O + ω̇ x r + ω x (ω x r)``.
- :func:`sensor_one`, a sensor on link k at ``p_LS`` turned by ``R_LS``: ``r = R_0k p_LS``,
  ``R_0S = R_0k R_LS``, ``p_0S = p_k + r``, its point's velocity and acceleration by the
  lever-arm rule above, and the angular velocity in its own axes ``R_0S^T ω_k``; what an
  ideal accelerometer there reads is :func:`armfusion.models.sensor_kernels.specific_force_one`.

The batch functions (:func:`chain_poses_batch`, :func:`link_motion_batch`,
:func:`sensor_motion_batch`, :func:`sensor_poses_batch`) loop over N instants calling the
one-instant forms; :mod:`armfusion.models.kinematics` and :mod:`armfusion.models.motion` wrap them in their
NumPy-facing records, and the tracker's live frame (:func:`armfusion.fusion.tracking.frame_kernels.frame_one`)
calls the one-instant forms inside its own compiled loop. A new joint or mount effect on
the geometry is written here, once.

The arm's constants travel as two contiguous tables (:func:`chain_table`, :func:`mount_table`).
The arithmetic is the former NumPy forms' term for term (same products, same order of
sums), so the batch results are unchanged to the bit (tests/models/test_chain_kernels.py).
Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import exp_so3_into
from armfusion.models.sensor_kernels import specific_force_one, to_sensor_axes
from numba import njit

_exp_so3_into = njit(cache=True, nogil=True, inline="always")(exp_so3_into)

# the columns of a chain table: one row per joint
R_PRE, P_PRE, AXIS, R_POST, P_POST, OFFSET = 0, 9, 12, 15, 24, 27
CHAIN_COLUMNS = 28
# the columns of a mount table: one row per sensor
R_LS, P_LS = 0, 9
MOUNT_COLUMNS = 12


def chain_table(arm: ArmModel) -> np.ndarray:
    """The arm's chain as one contiguous ``(n, 28)`` float64 table, made once per arm: each
    joint's row ``R_pre`` (9, row-major), ``p_pre_m`` (3), ``axis`` (3), ``R_post`` (9),
    ``p_post_m`` (3), ``offset_rad``."""
    hit = arm.__dict__.get("_chain_table")
    if hit is None:
        ch = arm.chain
        n = arm.n_joints
        hit = np.empty((n, CHAIN_COLUMNS))
        hit[:, R_PRE:R_PRE + 9] = np.asarray(ch.R_pre, float).reshape(n, 9)
        hit[:, P_PRE:P_PRE + 3] = ch.p_pre_m
        hit[:, AXIS:AXIS + 3] = ch.axis
        hit[:, R_POST:R_POST + 9] = np.asarray(ch.R_post, float).reshape(n, 9)
        hit[:, P_POST:P_POST + 3] = ch.p_post_m
        hit[:, OFFSET] = ch.offset_rad
        hit.setflags(write=False)
        arm.__dict__["_chain_table"] = hit
    return hit


def mount_table(R_LS_: np.ndarray, p_LS_m: np.ndarray) -> np.ndarray:
    """Sensor mounts ``R_LS (S, 3, 3)``, ``p_L_m (S, 3)`` as one contiguous ``(S, 12)`` table:
    each sensor's ``R_LS`` (9, row-major) and ``p_L_m`` (3)."""
    R = np.asarray(R_LS_, float)
    S = R.shape[0]
    out = np.empty((S, MOUNT_COLUMNS))
    out[:, R_LS:R_LS + 9] = R.reshape(S, 9)
    out[:, P_LS:P_LS + 3] = p_LS_m
    return kernel_input(out)


def kernel_input(a, dtype=np.float64) -> np.ndarray:
    """``a`` as a contiguous, read-only array (a view: no copy when it already is
    contiguous), so that each batch kernel is compiled for one signature whatever its
    caller passes (numba types writable and read-only arrays apart)."""
    v = np.ascontiguousarray(a, dtype=dtype).view()
    v.flags.writeable = False
    return v


# --------------------------------------------------------------------------------------
# small 3-vector helpers (inlined by the compiler)
@njit(cache=True, nogil=True, inline="always")
def cross3(a0, a1, a2, b0, b1, b2):  # pragma: no cover - compiled
    """``a x b`` as three floats."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, nogil=True, inline="always")
def _mv(R, r, v0, v1, v2):  # pragma: no cover - compiled
    """Row ``r`` of ``R @ v`` for a ``(3, 3)`` matrix ``R``."""
    return R[r, 0] * v0 + R[r, 1] * v1 + R[r, 2] * v2


@njit(cache=True, nogil=True, inline="always")
def _mm_rows(R, C, c0, out):  # pragma: no cover - compiled
    """``out = R @ C`` with ``C`` the nine row-major entries ``C[c0 : c0 + 9]``."""
    for a in range(3):
        for b in range(3):
            out[a, b] = R[a, 0] * C[c0 + b] + R[a, 1] * C[c0 + 3 + b] + R[a, 2] * C[c0 + 6 + b]


@njit(cache=True, nogil=True, inline="always")
def _lever(w0, w1, w2, d0, d1, d2, r0, r1, r2):  # pragma: no cover - compiled
    """The lever-arm terms of a point at ``r`` in a link turning at ``ω``, ``ω̇``: ``ω x r``
    (velocity) and ``ω̇ x r``, ``ω x (ω x r)`` (acceleration), as nine floats."""
    x0, x1, x2 = cross3(w0, w1, w2, r0, r1, r2)
    t0, t1, t2 = cross3(d0, d1, d2, r0, r1, r2)
    u0, u1, u2 = cross3(w0, w1, w2, x0, x1, x2)
    return x0, x1, x2, t0, t1, t2, u0, u1, u2


# --------------------------------------------------------------------------------------
# one instant
@njit(cache=True, nogil=True, inline="always")
def pose_one(q, chain, axis_is_z, R_0L, p_0L, axes, origin):  # pragma: no cover - compiled
    """Forward kinematics of one pose (the module's first equation): geometric joint angles
    ``q (n,)`` rad into every link frame ``R_0L (n + 1, 3, 3)``, ``p_0L (n + 1, 3)`` (index 0
    the base) and every joint's axis ``axes (n, 3)`` and origin ``origin (n, 3)``, base axes."""
    n = chain.shape[0]
    R = np.eye(3)
    T = np.empty((3, 3))
    p0, p1, p2 = 0.0, 0.0, 0.0
    for a in range(3):
        p_0L[0, a] = 0.0
        for b in range(3):
            R_0L[0, a, b] = R[a, b]
    for i in range(n):
        c = chain[i]
        v0, v1, v2 = c[P_PRE], c[P_PRE + 1], c[P_PRE + 2]
        p0, p1, p2 = p0 + _mv(R, 0, v0, v1, v2), p1 + _mv(R, 1, v0, v1, v2), p2 + _mv(R, 2, v0, v1, v2)
        _mm_rows(R, c, R_PRE, T)
        a0, a1, a2 = c[AXIS], c[AXIS + 1], c[AXIS + 2]
        axes[i, 0] = _mv(T, 0, a0, a1, a2)
        axes[i, 1] = _mv(T, 1, a0, a1, a2)
        axes[i, 2] = _mv(T, 2, a0, a1, a2)
        origin[i, 0], origin[i, 1], origin[i, 2] = p0, p1, p2
        th = q[i] + c[OFFSET]
        if axis_is_z:  # T Rz(theta): only the first two columns change
            ct, st = math.cos(th), math.sin(th)
            for r in range(3):
                R[r, 0] = ct * T[r, 0] + st * T[r, 1]
                R[r, 1] = ct * T[r, 1] - st * T[r, 0]
                R[r, 2] = T[r, 2]
        else:  # T exp([v]x), v = axis theta (armfusion.models.rotations.exp_so3)
            E = np.empty((3, 3))
            _exp_so3_into(a0 * th, a1 * th, a2 * th, E)
            for r in range(3):
                for s in range(3):
                    R[r, s] = T[r, 0] * E[0, s] + T[r, 1] * E[1, s] + T[r, 2] * E[2, s]
        v0, v1, v2 = c[P_POST], c[P_POST + 1], c[P_POST + 2]
        p0, p1, p2 = p0 + _mv(R, 0, v0, v1, v2), p1 + _mv(R, 1, v0, v1, v2), p2 + _mv(R, 2, v0, v1, v2)
        _mm_rows(R, c, R_POST, T)
        for a in range(3):
            for b in range(3):
                R[a, b] = T[a, b]
                R_0L[i + 1, a, b] = T[a, b]
        p_0L[i + 1, 0], p_0L[i + 1, 1], p_0L[i + 1, 2] = p0, p1, p2


@njit(cache=True, nogil=True, inline="always")
def motion_one(p_0L, axes, origin, qd, qdd, w_B, wd_B, a_B, om, al, ve, ac, v_o, a_o):  # pragma: no cover
    """The outward recursion at one instant (the module's second equation), from the pose
    (:func:`pose_one`'s ``p_0L``, ``axes``, ``origin``), the joint rates ``qd`` and
    accelerations ``qdd (n,)``, and the base's angular velocity ``w_B``, acceleration
    ``wd_B`` and origin's linear acceleration ``a_B (3,)`` (base axes). Writes every link's
    ``om``, ``al`` (angular velocity, acceleration), ``ve``, ``ac`` (its origin's velocity
    relative to the base origin's translation, and inertial acceleration) ``(n + 1, 3)``,
    and every joint origin's ``v_o``, ``a_o (n, 3)``."""
    n = axes.shape[0]
    w0, w1, w2 = w_B[0], w_B[1], w_B[2]
    d0, d1, d2 = wd_B[0], wd_B[1], wd_B[2]
    v0, v1, v2 = 0.0, 0.0, 0.0
    c0, c1, c2 = a_B[0], a_B[1], a_B[2]
    om[0, 0], om[0, 1], om[0, 2] = w0, w1, w2
    al[0, 0], al[0, 1], al[0, 2] = d0, d1, d2
    ve[0, 0], ve[0, 1], ve[0, 2] = v0, v1, v2
    ac[0, 0], ac[0, 1], ac[0, 2] = c0, c1, c2
    for i in range(n):
        # to the joint's origin, fixed in the link before it
        r0, r1, r2 = origin[i, 0] - p_0L[i, 0], origin[i, 1] - p_0L[i, 1], origin[i, 2] - p_0L[i, 2]
        x0, x1, x2, t0, t1, t2, u0, u1, u2 = _lever(w0, w1, w2, d0, d1, d2, r0, r1, r2)
        v0, v1, v2 = v0 + x0, v1 + x1, v2 + x2
        c0, c1, c2 = (c0 + t0) + u0, (c1 + t1) + u1, (c2 + t2) + u2
        v_o[i, 0], v_o[i, 1], v_o[i, 2] = v0, v1, v2
        a_o[i, 0], a_o[i, 1], a_o[i, 2] = c0, c1, c2
        # through the joint
        z0, z1, z2 = axes[i, 0], axes[i, 1], axes[i, 2]
        y0, y1, y2 = z0 * qd[i], z1 * qd[i], z2 * qd[i]
        x0, x1, x2 = cross3(w0, w1, w2, y0, y1, y2)
        d0, d1, d2 = (d0 + z0 * qdd[i]) + x0, (d1 + z1 * qdd[i]) + x1, (d2 + z2 * qdd[i]) + x2
        w0, w1, w2 = w0 + y0, w1 + y1, w2 + y2
        # on to the next link's origin, fixed in the link after the joint
        r0 = p_0L[i + 1, 0] - origin[i, 0]
        r1 = p_0L[i + 1, 1] - origin[i, 1]
        r2 = p_0L[i + 1, 2] - origin[i, 2]
        x0, x1, x2, t0, t1, t2, u0, u1, u2 = _lever(w0, w1, w2, d0, d1, d2, r0, r1, r2)
        v0, v1, v2 = v0 + x0, v1 + x1, v2 + x2
        c0, c1, c2 = (c0 + t0) + u0, (c1 + t1) + u1, (c2 + t2) + u2
        om[i + 1, 0], om[i + 1, 1], om[i + 1, 2] = w0, w1, w2
        al[i + 1, 0], al[i + 1, 1], al[i + 1, 2] = d0, d1, d2
        ve[i + 1, 0], ve[i + 1, 1], ve[i + 1, 2] = v0, v1, v2
        ac[i + 1, 0], ac[i + 1, 1], ac[i + 1, 2] = c0, c1, c2


@njit(cache=True, nogil=True, inline="always")
def sensor_pose_one(R_0L, p_0L, k, mount, R_0S, p_0S):  # pragma: no cover - compiled
    """A sensor's pose: on link ``k`` with ``mount (12,)`` (:func:`mount_table`'s row) ->
    ``R_0S (3, 3) = R_0k R_LS``, ``p_0S (3,) = p_k + r``; returns the lever arm ``r = R_0k
    p_LS`` (base axes) as three floats."""
    RL = R_0L[k]
    v0, v1, v2 = mount[P_LS], mount[P_LS + 1], mount[P_LS + 2]
    # summed first + third, then second: the order NumPy's einsum (two-lane SIMD) summed the
    # batch form's lever arms in, so that seeded results did not move when this replaced it
    r0 = (RL[0, 0] * v0 + RL[0, 2] * v2) + RL[0, 1] * v1
    r1 = (RL[1, 0] * v0 + RL[1, 2] * v2) + RL[1, 1] * v1
    r2 = (RL[2, 0] * v0 + RL[2, 2] * v2) + RL[2, 1] * v1
    _mm_rows(RL, mount, R_LS, R_0S)
    p_0S[0], p_0S[1], p_0S[2] = p_0L[k, 0] + r0, p_0L[k, 1] + r1, p_0L[k, 2] + r2
    return r0, r1, r2


@njit(cache=True, nogil=True, inline="always")
def sensor_one(R_0L, p_0L, om, al, ve, ac, k, mount, R_0S, p_0S, vel, acc, omega_S):  # pragma: no cover
    """A sensor's pose and motion at one instant (the module's third equation), from
    :func:`pose_one` and :func:`motion_one`'s link arrays: writes ``R_0S (3, 3)``, ``p_0S``,
    its point's velocity ``vel`` and acceleration ``acc`` (without gravity), and its angular
    velocity in its own axes ``omega_S`` (rad/s: what an ideal gyro reads). What an ideal
    accelerometer there reads is :func:`armfusion.models.sensor_kernels.specific_force_one` of ``acc``."""
    r0, r1, r2 = sensor_pose_one(R_0L, p_0L, k, mount, R_0S, p_0S)
    w0, w1, w2 = om[k, 0], om[k, 1], om[k, 2]
    x0, x1, x2, t0, t1, t2, u0, u1, u2 = _lever(w0, w1, w2, al[k, 0], al[k, 1], al[k, 2], r0, r1, r2)
    vel[0], vel[1], vel[2] = ve[k, 0] + x0, ve[k, 1] + x1, ve[k, 2] + x2
    acc[0] = (ac[k, 0] + t0) + u0
    acc[1] = (ac[k, 1] + t1) + u1
    acc[2] = (ac[k, 2] + t2) + u2
    omega_S[0], omega_S[1], omega_S[2] = to_sensor_axes(R_0S, w0, w1, w2)


# --------------------------------------------------------------------------------------
# N instants: a loop over the one-instant forms
@njit(cache=True, nogil=True)
def chain_poses_batch(q, chain, axis_is_z):  # pragma: no cover - compiled
    """:func:`pose_one` for every pose of ``q (N, n)``: ``R_0L (N, n + 1, 3, 3)``, ``p_0L (N, n
    + 1, 3)``, ``axes (N, n, 3)``, ``origin (N, n, 3)``."""
    N, n = q.shape
    R_0L = np.empty((N, n + 1, 3, 3))
    p_0L = np.empty((N, n + 1, 3))
    axes = np.empty((N, n, 3))
    origin = np.empty((N, n, 3))
    for t in range(N):
        pose_one(q[t], chain, axis_is_z, R_0L[t], p_0L[t], axes[t], origin[t])
    return R_0L, p_0L, axes, origin


@njit(cache=True, nogil=True)
def link_motion_batch(q, qd, qdd, w_B, wd_B, a_B, chain, axis_is_z):  # pragma: no cover - compiled
    """:func:`pose_one` then :func:`motion_one` at every instant (inputs ``(N, n)`` and ``(N,
    3)``): ``R_0L, p_0L, om, al, ve, ac, axes, origin, v_o, a_o`` (link arrays ``(N, n + 1,
    ...)``, joint arrays ``(N, n, 3)``)."""
    N, n = q.shape
    R_0L, p_0L, axes, origin = chain_poses_batch(q, chain, axis_is_z)
    om = np.empty((N, n + 1, 3))
    al = np.empty((N, n + 1, 3))
    ve = np.empty((N, n + 1, 3))
    ac = np.empty((N, n + 1, 3))
    v_o = np.empty((N, n, 3))
    a_o = np.empty((N, n, 3))
    for t in range(N):
        motion_one(p_0L[t], axes[t], origin[t], qd[t], qdd[t], w_B[t], wd_B[t], a_B[t], om[t], al[t],
                   ve[t], ac[t], v_o[t], a_o[t])
    return R_0L, p_0L, om, al, ve, ac, axes, origin, v_o, a_o


@njit(cache=True, nogil=True)
def sensor_poses_batch(R_0L, p_0L, links, mounts):  # pragma: no cover - compiled
    """:func:`sensor_pose_one` for every instant and sensor: ``R_0S (N, S, 3, 3)``, ``p_0S (N,
    S, 3)``."""
    N = R_0L.shape[0]
    S = links.shape[0]
    R_0S = np.empty((N, S, 3, 3))
    p_0S = np.empty((N, S, 3))
    for t in range(N):
        for s in range(S):
            sensor_pose_one(R_0L[t], p_0L[t], links[s], mounts[s], R_0S[t, s], p_0S[t, s])
    return R_0S, p_0S


@njit(cache=True, nogil=True)
def sensor_motion_batch(R_0L, p_0L, om, al, ve, ac, links, mounts, up, g_mps2):  # pragma: no cover
    """:func:`sensor_one` for every instant and sensor, and what an ideal accelerometer there
    reads (:func:`armfusion.models.sensor_kernels.specific_force_one`, world-up ``up (N, 3)`` in base
    axes, m/s²): ``R_0S (N, S, 3, 3)`` and ``p_0S, vel, acc, f, omega_S`` ``(N, S, 3)``."""
    N = R_0L.shape[0]
    S = links.shape[0]
    R_0S = np.empty((N, S, 3, 3))
    p_0S = np.empty((N, S, 3))
    vel = np.empty((N, S, 3))
    acc = np.empty((N, S, 3))
    f = np.empty((N, S, 3))
    omega_S = np.empty((N, S, 3))
    for t in range(N):
        for s in range(S):
            a = acc[t, s]
            sensor_one(R_0L[t], p_0L[t], om[t], al[t], ve[t], ac[t], links[s], mounts[s], R_0S[t, s],
                       p_0S[t, s], vel[t, s], a, omega_S[t, s])
            f[t, s, 0], f[t, s, 1], f[t, s, 2] = specific_force_one(R_0S[t, s], a[0], a[1], a[2], up[t, 0],
                                                                    up[t, 1], up[t, 2], g_mps2)
    return R_0S, p_0S, vel, acc, f, omega_S
