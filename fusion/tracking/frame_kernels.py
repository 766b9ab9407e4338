"""The kinematic frame of one instant, and the causal fits that feed it, compiled (numba).

The live path (:meth:`armfusion.fusion.tracking.tracker.Tracker.update_instant`) makes one frame per fused
instant: the mean pose's sensor rotations, joint axes and motion accelerations
(:func:`armfusion.fusion.tracking.tracker.make_frames` with K = 1). In NumPy that is a few hundred
floating-point operations spread over some two hundred small array calls (the chain's
forward kinematics, the outward recursion's cross products, the sensors' lever arms), so
nearly all of its cost is call overhead. :func:`frame_one` calls the same compiled
equations the batch models call (:mod:`armfusion.models.chain_kernels`: written once there) in one
compiled loop; :class:`FrameConstants` holds the arm's chain and the sensors' mounts
as a few contiguous arrays, made once per tracker, and turns one instant's inputs into
the fields of a :class:`armfusion.fusion.tracking.tracker.Frames` record. A run over a recording
makes a block of instants' frames in one call (:func:`frame_block`, a loop of
:func:`frame_one`; :meth:`FrameConstants.fields_block`).

The encoder and gyro differentiators (:class:`armfusion.fusion.tracking.tracker.CausalDifferentiator`) fit
a polynomial to the last few samples at every sample; :func:`push_fit` shifts the window
and solves that one small least-squares problem in one call (:func:`causal_poly_fit` in
:mod:`armfusion.fusion.tracking.tracker` is the batched NumPy form, for whole recordings);
:func:`push_fits` is a block of instants through it in one call (a loop of :func:`push_fit`
and :func:`extrapolate_fit`).

The tests (tests/fusion/test_frame_kernels.py) hold the frame to :func:`make_frames` (the
batch path), a block's frames and fits to the one-instant ones (to the bit), and the fit
to :func:`causal_poly_fit`.
Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.chain_kernels import _lever, chain_table, motion_one, mount_table, pose_one, sensor_one
from armfusion.models.kinematics import sensor_indices
from armfusion.models.rotations import GRAVITY_MPS2, skew_into
from numba import njit

_skew_into = njit(cache=True, nogil=True, inline="always")(skew_into)


# --------------------------------------------------------------------------------------
# the frame
@njit(cache=True, nogil=True)
def frame_one(enc_fit, offset, effect_joint, effect_delta, omega_B, omega_dot_B, motion, chain,
              axis_is_z, mounts, links, g_mps2, lever_m):  # pragma: no cover - compiled
    """The kinematic frame of one instant: every field of :func:`armfusion.fusion.tracking.tracker.make_frames`
    for K = 1, from the arm's constants (:class:`FrameConstants`).

    Inputs: ``enc_fit (3, n)`` the encoder angles (rad), rates (rad/s) and accelerations
    (rad/s²) at the instant; ``offset (n,)`` the offsets (rad), so that the reference
    angles are ``q_ref = enc_fit[0] + offset``; ``effect_joint (E,)``, ``effect_delta (E,)``
    the joint effects' changes of the geometric angles (rad), added in order:
    ``q_geom[effect_joint[e]] += effect_delta[e]``; ``omega_B``, ``omega_dot_B (3,)`` the
    base's angular velocity (rad/s) and acceleration (rad/s²), base axes. ``motion`` False:
    the rates and accelerations are taken as zero (no motion compensation). ``lever_m (3,)``:
    the base origin from the chair's turning centre (m, base axes; zero where the config
    states none): the base origin's own acceleration from the chair's rotation,
    ``ω̇ x ρ + ω x (ω x ρ)``, is in every sensor's motion, and ``dist2_m2`` is measured
    from the turning centre (the differentiated gyro's error reaches a sensor that far off).

    The equations are :mod:`armfusion.models.chain_kernels`' (the same functions the batch models
    call): forward kinematics (:func:`armfusion.models.chain_kernels.pose_one`), the outward recursion
    from the base origin's acceleration the chair's rotation gives it about its turning
    centre (:func:`armfusion.models.chain_kernels.motion_one`),
    and each sensor's pose and motion (:func:`armfusion.models.chain_kernels.sensor_one`).

    Returns ``(q_ref (n,), offset_ref (n,), R_0S (S, 3, 3), motion_mps2 (S, 3), axes (n, 3),
    p_0S_m (S, 3), omega_dot_B (3,), K (n, 3, 3), motion_g (S,), dist2_m2 (S,),
    omega_dot_norm, omega_S_rad_s (S, 3))``: ``K`` the axes' skew matrices, ``motion_g``
    ``|a_S| / g``, ``dist2_m2`` ``|p_0S + ρ|²``, ``omega_dot_norm`` ``|ω̇_B|``.
    """
    n = chain.shape[0]
    S = mounts.shape[0]
    q_ref = np.empty(n)
    offset_ref = np.empty(n)
    q_geom = np.empty(n)
    for j in range(n):
        offset_ref[j] = offset[j]
        q_ref[j] = enc_fit[0, j] + offset[j]
        q_geom[j] = q_ref[j]
    for e in range(effect_joint.shape[0]):
        q_geom[effect_joint[e]] += effect_delta[e]

    R_0L = np.empty((n + 1, 3, 3))
    p_0L = np.empty((n + 1, 3))
    axes = np.empty((n, 3))
    origin = np.empty((n, 3))
    pose_one(q_geom, chain, axis_is_z, R_0L, p_0L, axes, origin)

    zeros_n = np.zeros(n)
    w_B = np.zeros(3)
    wd_B = np.zeros(3)
    qd, qdd = zeros_n, zeros_n
    if motion:
        qd, qdd = enc_fit[1], enc_fit[2]
        for a in range(3):
            w_B[a] = omega_B[a]
            wd_B[a] = omega_dot_B[a]
    om = np.empty((n + 1, 3))
    al = np.empty((n + 1, 3))
    ve = np.empty((n + 1, 3))
    ac = np.empty((n + 1, 3))
    v_o = np.empty((n, 3))
    a_o = np.empty((n, 3))
    # the base origin turning about the chair's turning centre, ``lever_m`` away
    _, _, _, t0, t1, t2, u0, u1, u2 = _lever(w_B[0], w_B[1], w_B[2], wd_B[0], wd_B[1], wd_B[2],
                                             lever_m[0], lever_m[1], lever_m[2])
    a_B = np.empty(3)
    a_B[0], a_B[1], a_B[2] = t0 + u0, t1 + u1, t2 + u2
    motion_one(p_0L, axes, origin, qd, qdd, w_B, wd_B, a_B, om, al, ve, ac, v_o, a_o)

    R_0S = np.empty((S, 3, 3))
    acc = np.empty((S, 3))
    p_0S = np.empty((S, 3))
    vel = np.empty((S, 3))
    omega_S = np.empty((S, 3))
    motion_g = np.empty(S)
    dist2 = np.empty(S)
    for s in range(S):
        sensor_one(R_0L, p_0L, om, al, ve, ac, links[s], mounts[s], R_0S[s], p_0S[s], vel[s], acc[s],
                   omega_S[s])
        motion_g[s] = math.sqrt(acc[s, 0] ** 2 + acc[s, 1] ** 2 + acc[s, 2] ** 2) / g_mps2
        dist2[s] = ((p_0S[s, 0] + lever_m[0]) ** 2 + (p_0S[s, 1] + lever_m[1]) ** 2
                    + (p_0S[s, 2] + lever_m[2]) ** 2)

    # the axes' skew matrices
    K = np.zeros((n, 3, 3))
    for j in range(n):
        _skew_into(axes[j, 0], axes[j, 1], axes[j, 2], K[j])
    wd_norm = math.sqrt(wd_B[0] ** 2 + wd_B[1] ** 2 + wd_B[2] ** 2)
    return q_ref, offset_ref, R_0S, acc, axes, p_0S, wd_B, K, motion_g, dist2, wd_norm, omega_S


@njit(cache=True, nogil=True)
def frame_block(enc_fit, have, offset, effect_joint, effect_delta, omega_B, omega_dot_B, motion, chain,
                axis_is_z, mounts, links, g_mps2, lever_m):  # pragma: no cover - compiled
    """:func:`frame_one` at each of B instants, in one call (a run over a recording makes a
    block's frames at once): ``enc_fit (B, 3, n)``, ``omega_B``, ``omega_dot_B (B, 3)``,
    ``effect_delta (B, E)``, ``offset (n,)`` shared; ``have (B,)`` False: no frame at that
    instant (its rows are left zero). Returns :func:`frame_one`'s fields stacked on a first
    axis of B (``omega_dot_norm (B,)``)."""
    B = enc_fit.shape[0]
    n = chain.shape[0]
    S = mounts.shape[0]
    q_ref = np.zeros((B, n))
    offset_ref = np.zeros((B, n))
    R_0S = np.zeros((B, S, 3, 3))
    acc = np.zeros((B, S, 3))
    axes = np.zeros((B, n, 3))
    p_0S = np.zeros((B, S, 3))
    wd_B = np.zeros((B, 3))
    K = np.zeros((B, n, 3, 3))
    motion_g = np.zeros((B, S))
    dist2 = np.zeros((B, S))
    wd_norm = np.zeros(B)
    omega_S = np.zeros((B, S, 3))
    for b in range(B):
        if not have[b]:
            continue
        f = frame_one(enc_fit[b], offset, effect_joint, effect_delta[b], omega_B[b], omega_dot_B[b], motion,
                      chain, axis_is_z, mounts, links, g_mps2, lever_m)
        q_ref[b] = f[0]
        offset_ref[b] = f[1]
        R_0S[b] = f[2]
        acc[b] = f[3]
        axes[b] = f[4]
        p_0S[b] = f[5]
        wd_B[b] = f[6]
        K[b] = f[7]
        motion_g[b] = f[8]
        dist2[b] = f[9]
        wd_norm[b] = f[10]
        omega_S[b] = f[11]
    return q_ref, offset_ref, R_0S, acc, axes, p_0S, wd_B, K, motion_g, dist2, wd_norm, omega_S


# --------------------------------------------------------------------------------------
class FrameConstants:
    """The arm's chain and the sensors' mounts as contiguous arrays for :func:`frame_one`,
    made once (per tracker): ``chain`` (:func:`armfusion.models.chain_kernels.chain_table`),
    ``mounts`` (:func:`armfusion.models.chain_kernels.mount_table`) and ``links (S,)`` int64.

    ``joint_effects``: the (effect, parameters) pairs of
    :func:`armfusion.fusion.tracking.tracker.make_frames`. Those that add a constant (``joint_offset``) are
    added in the kernel; any other (sag, play: functions of the gravity torque) is
    evaluated here in NumPy exactly as :func:`make_frames` evaluates it, and its change
    passed on.
    """

    def __init__(self, arm: ArmModel, names, joint_effects=(), g_mps2: float = GRAVITY_MPS2):
        from armfusion.models.effects.library import JointOffset

        idx = sensor_indices(arm, list(names))
        mounts = mount_table(np.stack([arm.sensors[i].R_LS for i in idx]),
                             np.stack([arm.sensors[i].p_L_m for i in idx]))
        self.arm = arm
        self.names = tuple(names)
        self.chain = chain_table(arm)
        self.axis_is_z = bool(arm.chain.axis_is_z)
        self.mounts = np.ascontiguousarray(mounts)
        self.links = np.array([arm.sensors[i].link for i in idx], dtype=np.int64)
        self.g_mps2 = float(g_mps2)
        self.joint_effects = list(joint_effects)
        self.effect_joint = np.array([e.j for e, _ in self.joint_effects], dtype=np.int64)
        self.effect_delta = np.zeros(len(self.joint_effects))
        self._varying = []  # (position in the effect list, effect, parameters)
        for k, (e, th) in enumerate(self.joint_effects):
            if type(e) is JointOffset:  # delta = theta[0] at every instant
                self.effect_delta[k] = float(np.asarray(th, float)[0])
            else:
                self._varying.append((k, e, th))
        self._zeros3 = np.zeros(3)
        rho = arm.base_from_turning_centre_m
        self.lever_m = np.zeros(3) if rho is None else np.array(rho, dtype=float)
        """The base origin from the chair's turning centre (m; zero: not stated)."""

    def fields(self, enc_fit: np.ndarray, offset: np.ndarray, omega_B: np.ndarray | None,
               omega_dot_B: np.ndarray | None, motion: bool = True) -> tuple:
        """The fields of the one-instant :class:`armfusion.fusion.tracking.tracker.Frames` record (the same as
        ``make_frames(arm, names, JointMotion(enc_fit[0][None], enc_fit[1][None], enc_fit[2][None]),
        offset[None], BaseTurn(omega_B[None], omega_dot_B[None]), motion, joint_effects).take(0)``),
        in its field order, without the measurement variances. ``omega_B``/``omega_dot_B``
        None: zero."""
        w = self._zeros3 if omega_B is None else omega_B
        wd = self._zeros3 if omega_dot_B is None else omega_dot_B
        delta = self.effect_delta
        if self._varying:
            delta = self._varying_deltas(enc_fit, offset, w, wd, motion)
        out = frame_one(enc_fit, offset, self.effect_joint, delta, w, wd, bool(motion), self.chain,
                        self.axis_is_z, self.mounts, self.links, self.g_mps2, self.lever_m)
        offset_ref = out[1]
        offset_ref.setflags(write=False)
        return out[:10] + (np.float64(out[10]), None, out[11])

    def fields_block(self, enc_fit: np.ndarray, have: np.ndarray, offset: np.ndarray, omega_B: np.ndarray,
                     omega_dot_B: np.ndarray, motion: bool = True) -> tuple:
        """:meth:`fields` at each of B instants in one compiled call (:func:`frame_block`),
        stacked on a first axis: ``enc_fit (B, 3, n)``, ``omega_B``, ``omega_dot_B (B, 3)``
        (zero rows for none), ``offset (n,)`` shared; ``have (B,)`` False: no frame there
        (zero rows)."""
        B = len(enc_fit)
        delta = np.broadcast_to(self.effect_delta, (B, len(self.effect_delta)))
        if self._varying:
            delta = delta.copy()
            for b in np.flatnonzero(have):
                delta[b] = self._varying_deltas(enc_fit[b], offset, omega_B[b], omega_dot_B[b], motion)
        out = frame_block(enc_fit, have, offset, self.effect_joint, delta, omega_B, omega_dot_B, bool(motion),
                          self.chain, self.axis_is_z, self.mounts, self.links, self.g_mps2, self.lever_m)
        out[1].setflags(write=False)
        return out[:11] + (None, out[11])

    def _varying_deltas(self, enc_fit, offset, w, wd, motion) -> np.ndarray:
        """The joint effects' changes at this instant, as :func:`make_frames` computes them
        (its motion state, its context)."""
        from armfusion.models.effects import Context
        from armfusion.models.motion import MotionState

        q = (enc_fit[0] + offset)[None]
        if motion:
            qd, qdd, w_, wd_ = enc_fit[1][None], enc_fit[2][None], w[None], wd[None]
        else:
            qd = qdd = np.zeros_like(q)
            w_ = wd_ = np.zeros((1, 3))
        st = MotionState(np.zeros(1), q, qd, qdd, np.eye(3)[None], w_, wd_, np.zeros((1, 3)), 25.0)
        ctx = Context(self.arm, st)
        delta = self.effect_delta.copy()
        for k, e, th in self._varying:
            delta[k] = float(e.delta(q, th, ctx)[0])
        return delta


# --------------------------------------------------------------------------------------
# the causal differentiators' fit, one window
@njit(cache=True, nogil=True)
def poly_fit_one(t_win, y_win, t_eval, order):  # pragma: no cover - compiled
    """Least-squares polynomial through one window, evaluated at ``t_eval``:
    :func:`armfusion.fusion.tracking.tracker.causal_poly_fit` for K = 1.

    ``t_win (W,)`` s, ``y_win (W, d)`` -> ``(3, d)``: value, first and second derivative
    (per s, per s²; zero beyond ``order``, which is capped by W - 1). With ``τ = t - t_eval``
    and ``h = t_(W-1) - t_0`` the window's span (at least 1 ns), the fit is
    ``y ≈ Σ_k c_k s^k``, ``s = τ / h``,
    from the normal equations ``(AᵀA) c = Aᵀy``, ``A_wk = s_w^k`` (Gaussian elimination
    with partial pivoting); value ``c_0``, rate ``c_1 / h``, acceleration ``2 c_2 / h²``.
    """
    W = t_win.shape[0]
    d = y_win.shape[1]
    order = min(order, W - 1)
    out = np.zeros((3, d))
    if W == 1 or order == 0:
        for c in range(d):
            out[0, c] = y_win[W - 1, c]
        return out
    m = order + 1
    h = max(t_win[W - 1] - t_win[0], 1e-9)  # the window's span (oldest first)
    A = np.empty((W, m))
    for w in range(W):
        s = (t_win[w] - t_eval) / h
        A[w, 0] = 1.0
        for k in range(1, m):
            A[w, k] = s ** float(k)
    M = np.empty((m, m + d))  # [AᵀA | Aᵀy]
    for i in range(m):
        for j in range(m):
            acc = 0.0
            for w in range(W):
                acc += A[w, i] * A[w, j]
            M[i, j] = acc
        for c in range(d):
            acc = 0.0
            for w in range(W):
                acc += A[w, i] * y_win[w, c]
            M[i, m + c] = acc
    for col in range(m):
        piv = col
        for r in range(col + 1, m):
            if abs(M[r, col]) > abs(M[piv, col]):
                piv = r
        if piv != col:
            for c in range(m + d):
                M[col, c], M[piv, c] = M[piv, c], M[col, c]
        for r in range(col + 1, m):
            f = M[r, col] / M[col, col]
            for c in range(col, m + d):
                M[r, c] -= f * M[col, c]
    coef = np.empty((m, d))
    for c in range(d):
        for i in range(m - 1, -1, -1):
            acc = M[i, m + c]
            for j in range(i + 1, m):
                acc -= M[i, j] * coef[j, c]
            coef[i, c] = acc / M[i, i]
    for c in range(d):
        out[0, c] = coef[0, c]
        out[1, c] = coef[1, c] / h
        if order >= 2:
            out[2, c] = 2.0 * coef[2, c] / h**2
    return out


@njit(cache=True, nogil=True)
def push_fit(t_buf, y_buf, t, y, n, order):  # pragma: no cover - compiled
    """One sample into a differentiator's window, and the fit at it.

    ``t_buf (W,)``, ``y_buf (W, d)`` hold the last W samples, oldest first (NaN / zero
    before they fill); both shift by one in place and take ``t``, ``y (d,)`` at the end.
    ``n`` the samples now held (at most W). Returns the fit at ``t`` ``(3, d)``
    (:func:`poly_fit_one` over the last ``n`` samples with ``order`` capped at ``n - 1``;
    one sample: its value, zero derivatives)."""
    W = t_buf.shape[0]
    d = y_buf.shape[1]
    for i in range(W - 1):
        t_buf[i] = t_buf[i + 1]
        for c in range(d):
            y_buf[i, c] = y_buf[i + 1, c]
    t_buf[W - 1] = t
    for c in range(d):
        y_buf[W - 1, c] = y[c]
    if n < 2:
        out = np.zeros((3, d))
        for c in range(d):
            out[0, c] = y[c]
        return out
    o = order if n > order else n - 1
    return poly_fit_one(t_buf[W - n:], y_buf[W - n:], t, o)


@njit(cache=True, nogil=True)
def push_fits(t_buf, y_buf, t, y, pushed, n, order, fit, t_last, have_fit):  # pragma: no cover - compiled
    """A block of B instants through a differentiator, in one call: at each instant ``b``
    with ``pushed[b]``, the sample ``t[b]``, ``y[b] (d,)`` goes in (:func:`push_fit`); then
    the fit at ``t[b]`` (:func:`extrapolate_fit` of the latest fit by ``t[b]`` less its
    time). ``fit (3, d)``, ``t_last``, ``have_fit``: the latest fit before the block, its
    sample's time, whether there is one; ``n`` the samples held before it.

    Returns ``(at (B, 3, d), latest (B, 3, d), have (B,), fit, t_last, n)``: the fit at
    each instant and the latest fit then (zero where ``have`` is False: no sample yet), and
    the differentiator's state after the block."""
    B = t.shape[0]
    W = t_buf.shape[0]
    d = y_buf.shape[1]
    at = np.zeros((B, 3, d))
    latest = np.zeros((B, 3, d))
    have = np.zeros(B, dtype=np.bool_)
    for b in range(B):
        if pushed[b]:
            n = min(n + 1, W)
            fit = push_fit(t_buf, y_buf, t[b], y[b], n, order)
            t_last = t[b]
            have_fit = True
        if have_fit:
            have[b] = True
            at[b] = extrapolate_fit(fit, t[b] - t_last)
            latest[b] = fit
    return at, latest, have, fit, t_last, n


@njit(cache=True, nogil=True)
def extrapolate_fit(fit, dt):  # pragma: no cover - compiled
    """A fit ``(3, d)`` (value, rate, acceleration) carried ``dt`` s on at constant
    acceleration: ``(v + r dt + a dt² / 2, r + a dt, a)``."""
    d = fit.shape[1]
    out = np.empty((3, d))
    for c in range(d):
        v, r, a = fit[0, c], fit[1, c], fit[2, c]
        out[0, c] = v + r * dt + 0.5 * a * dt * dt
        out[1, c] = r + a * dt
        out[2, c] = a
    return out
