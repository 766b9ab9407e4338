"""The kinematic frame of one instant, and the causal fits that feed it, compiled (numba).

The live path (:meth:`fusion.tracking.tracker.Tracker.update_instant`) makes one frame per fused
instant: the mean pose's sensor rotations, joint axes and motion accelerations
(:func:`fusion.tracking.tracker.make_frames` with K = 1). In NumPy that is a few hundred
floating-point operations spread over some two hundred small array calls (the chain's
forward kinematics, the outward recursion's cross products, the sensors' lever arms), so
nearly all of its cost is call overhead. :func:`frame_one` does the same arithmetic in
one compiled loop; :class:`FrameConstants` holds the arm's chain and the sensors' mounts
as a few contiguous arrays, made once per tracker, and turns one instant's inputs into
the fields of a :class:`fusion.tracking.tracker.Frames` record.

The encoder and gyro differentiators (:class:`fusion.tracking.tracker.CausalDifferentiator`) fit
a polynomial to the last few samples at every sample; :func:`push_fit` shifts the window
and solves that one small least-squares problem in one call (:func:`causal_poly_fit` in
:mod:`fusion.tracking.tracker` is the batched NumPy form, for whole recordings).

The tests (tests/fusion/test_frame_kernels.py) hold both to their NumPy forms.
Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from models.arm import ArmModel
from models.kinematics import sensor_indices

# the columns of FrameConstants.chain: one row per joint
_R_PRE, _P_PRE, _AXIS, _R_POST, _P_POST, _OFFSET = 0, 9, 12, 15, 24, 27
CHAIN_COLUMNS = 28
# the columns of FrameConstants.mounts: one row per sensor
_R_LS, _P_LS = 0, 9
MOUNT_COLUMNS = 12


# --------------------------------------------------------------------------------------
# small 3-vector helpers (inlined by the compiler)
@njit(cache=True, nogil=True, inline="always")
def _cross(a0, a1, a2, b0, b1, b2):  # pragma: no cover - compiled
    """``a x b`` as three floats."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, nogil=True, inline="always")
def _mv(R, r, v0, v1, v2):  # pragma: no cover - compiled
    """Row ``r`` of ``R @ v`` for a ``(3, 3)`` matrix ``R``."""
    return R[r, 0] * v0 + R[r, 1] * v1 + R[r, 2] * v2


@njit(cache=True, nogil=True)
def _mm_rows(R, C, c0):  # pragma: no cover - compiled
    """``R @ C`` with ``C`` the nine row-major entries ``C[c0 : c0 + 9]`` -> a new ``(3, 3)``."""
    out = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            out[a, b] = R[a, 0] * C[c0 + b] + R[a, 1] * C[c0 + 3 + b] + R[a, 2] * C[c0 + 6 + b]
    return out


@njit(cache=True, nogil=True)
def frame_one(enc_fit, offset, effect_joint, effect_delta, omega_B, omega_dot_B, motion, chain,
              axis_is_z, mounts, links, g_mps2):  # pragma: no cover - compiled
    """The kinematic frame of one instant: every field of :func:`fusion.tracking.tracker.make_frames`
    for K = 1, from the arm's constants (:class:`FrameConstants`).

    Inputs: ``enc_fit (3, n)`` the encoder angles (rad), rates (rad/s) and accelerations
    (rad/s²) at the instant; ``offset (n,)`` the offsets (rad), so that the reference
    angles are ``q_ref = enc_fit[0] + offset``; ``effect_joint (E,)``, ``effect_delta (E,)``
    the joint effects' changes of the geometric angles (rad), added in order:
    ``q_geom[effect_joint[e]] += effect_delta[e]``; ``omega_B``, ``omega_dot_B (3,)`` the
    base's angular velocity (rad/s) and acceleration (rad/s²), base axes. ``motion`` False:
    the rates and accelerations are taken as zero (no motion compensation).

    Forward kinematics (:func:`models.kinematics.chain_poses`), with ``theta = q_geom +
    offset_rad``: ``p <- p + R p_pre``, ``R <- R R_pre``; the joint's axis ``R a`` and
    origin ``p``; ``R <- R exp([a]x theta)`` (``Rz(theta)`` when every axis is z); ``p <- p
    + R p_post``, ``R <- R R_post``.

    The outward recursion (:func:`models.motion.link_motion`, the base's linear
    acceleration zero): at joint i with axis z and origin o, ``a_o = a + ω̇ x r + ω x (ω x
    r)`` with ``r = o - p_i``; ``ω̇ <- ω̇ + z q̈ + ω x z q̇``, ``ω <- ω + z q̇``; on to the next
    link's origin the same way. Each sensor on link k at ``r = R_0k p_LS``:
    ``a_S = a_k + ω̇_k x r + ω_k x (ω_k x r)``, ``R_0S = R_0k R_LS``, ``p_0S = p_k + r``, its
    angular velocity in its own axes ``R_0S^T ω_k``.

    Returns ``(q_ref (n,), offset_ref (n,), R_0S (S, 3, 3), motion_mps2 (S, 3), axes (n, 3),
    p_0S_m (S, 3), omega_dot_B (3,), K (n, 3, 3), motion_g (S,), dist2_m2 (S,),
    omega_dot_norm, omega_S_rad_s (S, 3))``: ``K`` the axes' skew matrices, ``motion_g``
    ``|a_S| / g``, ``dist2_m2`` ``|p_0S|²``, ``omega_dot_norm`` ``|ω̇_B|``.
    """
    n = chain.shape[0]
    S = mounts.shape[0]
    q_ref = np.empty(n)
    offset_ref = np.empty(n)
    theta = np.empty(n)
    for j in range(n):
        offset_ref[j] = offset[j]
        q_ref[j] = enc_fit[0, j] + offset[j]
        theta[j] = q_ref[j]
    for e in range(effect_joint.shape[0]):
        theta[effect_joint[e]] += effect_delta[e]
    for j in range(n):
        theta[j] = theta[j] + chain[j, _OFFSET]

    # forward kinematics: link frames 0 … n, joint axes and origins
    R_0L = np.empty((n + 1, 3, 3))
    p_0L = np.zeros((n + 1, 3))
    axes = np.empty((n, 3))
    origin = np.empty((n, 3))
    R = np.eye(3)
    p0, p1, p2 = 0.0, 0.0, 0.0
    R_0L[0] = R
    for i in range(n):
        c = chain[i]
        v0, v1, v2 = c[_P_PRE], c[_P_PRE + 1], c[_P_PRE + 2]
        p0, p1, p2 = p0 + _mv(R, 0, v0, v1, v2), p1 + _mv(R, 1, v0, v1, v2), p2 + _mv(R, 2, v0, v1, v2)
        R = _mm_rows(R, c, _R_PRE)
        a0, a1, a2 = c[_AXIS], c[_AXIS + 1], c[_AXIS + 2]
        axes[i, 0] = _mv(R, 0, a0, a1, a2)
        axes[i, 1] = _mv(R, 1, a0, a1, a2)
        axes[i, 2] = _mv(R, 2, a0, a1, a2)
        origin[i, 0], origin[i, 1], origin[i, 2] = p0, p1, p2
        th = theta[i]
        Rn = np.empty((3, 3))
        if axis_is_z:  # R Rz(theta): only the first two columns change
            ct, st = math.cos(th), math.sin(th)
            for r in range(3):
                Rn[r, 0] = ct * R[r, 0] + st * R[r, 1]
                Rn[r, 1] = ct * R[r, 1] - st * R[r, 0]
                Rn[r, 2] = R[r, 2]
        else:  # R exp([v]x), v = axis theta (models.rotations.exp_so3)
            x, y, z = a0 * th, a1 * th, a2 * th
            ang = math.sqrt(x * x + y * y + z * z)
            if ang < 1e-8:
                sa = 1.0 - ang**2 / 6.0
                sb = 0.5 - ang**2 / 24.0
            else:
                sa = math.sin(ang) / ang
                sb = (1.0 - math.cos(ang)) / ang**2
            Kv = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
            E = np.empty((3, 3))
            for r in range(3):
                for s in range(3):
                    kk = Kv[r, 0] * Kv[0, s] + Kv[r, 1] * Kv[1, s] + Kv[r, 2] * Kv[2, s]
                    E[r, s] = ((1.0 if r == s else 0.0) + sa * Kv[r, s]) + sb * kk
            for r in range(3):
                for s in range(3):
                    Rn[r, s] = R[r, 0] * E[0, s] + R[r, 1] * E[1, s] + R[r, 2] * E[2, s]
        R = Rn
        v0, v1, v2 = c[_P_POST], c[_P_POST + 1], c[_P_POST + 2]
        p0, p1, p2 = p0 + _mv(R, 0, v0, v1, v2), p1 + _mv(R, 1, v0, v1, v2), p2 + _mv(R, 2, v0, v1, v2)
        R = _mm_rows(R, c, _R_POST)
        R_0L[i + 1] = R
        p_0L[i + 1, 0], p_0L[i + 1, 1], p_0L[i + 1, 2] = p0, p1, p2

    # the outward recursion: every link's angular velocity, acceleration and origin's
    # acceleration (the base origin's own acceleration is zero here)
    om = np.empty((n + 1, 3))
    al = np.empty((n + 1, 3))
    ac = np.zeros((n + 1, 3))
    wd_B = np.zeros(3)
    if motion:
        for a in range(3):
            wd_B[a] = omega_dot_B[a]
            om[0, a] = omega_B[a]
    else:
        for a in range(3):
            om[0, a] = 0.0
    w0, w1, w2 = om[0, 0], om[0, 1], om[0, 2]
    d0, d1, d2 = wd_B[0], wd_B[1], wd_B[2]
    al[0, 0], al[0, 1], al[0, 2] = d0, d1, d2
    c0, c1, c2 = 0.0, 0.0, 0.0  # acceleration of the current link's origin, m/s²
    for i in range(n):
        qd = enc_fit[1, i] if motion else 0.0
        qdd = enc_fit[2, i] if motion else 0.0
        # to the joint's origin, fixed in the link before it
        r0, r1, r2 = origin[i, 0] - p_0L[i, 0], origin[i, 1] - p_0L[i, 1], origin[i, 2] - p_0L[i, 2]
        x0, x1, x2 = _cross(w0, w1, w2, r0, r1, r2)
        t0, t1, t2 = _cross(d0, d1, d2, r0, r1, r2)
        u0, u1, u2 = _cross(w0, w1, w2, x0, x1, x2)
        c0, c1, c2 = (c0 + t0) + u0, (c1 + t1) + u1, (c2 + t2) + u2
        # through the joint
        z0, z1, z2 = axes[i, 0], axes[i, 1], axes[i, 2]
        y0, y1, y2 = z0 * qd, z1 * qd, z2 * qd
        x0, x1, x2 = _cross(w0, w1, w2, y0, y1, y2)
        d0, d1, d2 = (d0 + z0 * qdd) + x0, (d1 + z1 * qdd) + x1, (d2 + z2 * qdd) + x2
        w0, w1, w2 = w0 + y0, w1 + y1, w2 + y2
        # on to the next link's origin, fixed in the link after the joint
        r0 = p_0L[i + 1, 0] - origin[i, 0]
        r1 = p_0L[i + 1, 1] - origin[i, 1]
        r2 = p_0L[i + 1, 2] - origin[i, 2]
        x0, x1, x2 = _cross(w0, w1, w2, r0, r1, r2)
        t0, t1, t2 = _cross(d0, d1, d2, r0, r1, r2)
        u0, u1, u2 = _cross(w0, w1, w2, x0, x1, x2)
        c0, c1, c2 = (c0 + t0) + u0, (c1 + t1) + u1, (c2 + t2) + u2
        om[i + 1, 0], om[i + 1, 1], om[i + 1, 2] = w0, w1, w2
        al[i + 1, 0], al[i + 1, 1], al[i + 1, 2] = d0, d1, d2
        ac[i + 1, 0], ac[i + 1, 1], ac[i + 1, 2] = c0, c1, c2

    # the sensors
    R_0S = np.empty((S, 3, 3))
    acc = np.empty((S, 3))
    p_0S = np.empty((S, 3))
    omega_S = np.empty((S, 3))
    motion_g = np.empty(S)
    dist2 = np.empty(S)
    for s in range(S):
        k = links[s]
        RL = R_0L[k]
        m = mounts[s]
        v0, v1, v2 = m[_P_LS], m[_P_LS + 1], m[_P_LS + 2]
        r0, r1, r2 = _mv(RL, 0, v0, v1, v2), _mv(RL, 1, v0, v1, v2), _mv(RL, 2, v0, v1, v2)
        w0, w1, w2 = om[k, 0], om[k, 1], om[k, 2]
        x0, x1, x2 = _cross(w0, w1, w2, r0, r1, r2)
        t0, t1, t2 = _cross(al[k, 0], al[k, 1], al[k, 2], r0, r1, r2)
        u0, u1, u2 = _cross(w0, w1, w2, x0, x1, x2)
        acc[s, 0] = (ac[k, 0] + t0) + u0
        acc[s, 1] = (ac[k, 1] + t1) + u1
        acc[s, 2] = (ac[k, 2] + t2) + u2
        RS = _mm_rows(RL, m, _R_LS)
        R_0S[s] = RS
        p_0S[s, 0], p_0S[s, 1], p_0S[s, 2] = p_0L[k, 0] + r0, p_0L[k, 1] + r1, p_0L[k, 2] + r2
        for a in range(3):
            omega_S[s, a] = RS[0, a] * w0 + RS[1, a] * w1 + RS[2, a] * w2
        motion_g[s] = math.sqrt(acc[s, 0] ** 2 + acc[s, 1] ** 2 + acc[s, 2] ** 2) / g_mps2
        dist2[s] = p_0S[s, 0] ** 2 + p_0S[s, 1] ** 2 + p_0S[s, 2] ** 2

    # the axes' skew matrices
    K = np.zeros((n, 3, 3))
    for j in range(n):
        x, y, z = axes[j, 0], axes[j, 1], axes[j, 2]
        K[j, 0, 1], K[j, 0, 2] = -z, y
        K[j, 1, 0], K[j, 1, 2] = z, -x
        K[j, 2, 0], K[j, 2, 1] = -y, x
    wd_norm = math.sqrt(wd_B[0] ** 2 + wd_B[1] ** 2 + wd_B[2] ** 2)
    return q_ref, offset_ref, R_0S, acc, axes, p_0S, wd_B, K, motion_g, dist2, wd_norm, omega_S


# --------------------------------------------------------------------------------------
class FrameConstants:
    """The arm's chain and the sensors' mounts as contiguous arrays for :func:`frame_one`,
    made once (per tracker): ``chain (n, 28)`` float64, each joint's row ``R_pre`` (9,
    row-major), ``p_pre_m`` (3), ``axis`` (3), ``R_post`` (9), ``p_post_m`` (3),
    ``offset_rad``; ``mounts (S, 12)`` float64, each sensor's ``R_LS`` (9) and ``p_L_m``
    (3); ``links (S,)`` int64.

    ``joint_effects``: the (effect, parameters) pairs of
    :func:`fusion.tracking.tracker.make_frames`. Those that add a constant (``joint_offset``) are
    added in the kernel; any other (sag, play: functions of the gravity torque) is
    evaluated here in NumPy exactly as :func:`make_frames` evaluates it, and its change
    passed on.
    """

    def __init__(self, arm: ArmModel, names, joint_effects=(), g_mps2: float = 9.80665):
        from models.effects.library import JointOffset

        ch = arm.chain
        n = arm.n_joints
        chain = np.empty((n, CHAIN_COLUMNS))
        chain[:, _R_PRE:_R_PRE + 9] = np.asarray(ch.R_pre, float).reshape(n, 9)
        chain[:, _P_PRE:_P_PRE + 3] = ch.p_pre_m
        chain[:, _AXIS:_AXIS + 3] = ch.axis
        chain[:, _R_POST:_R_POST + 9] = np.asarray(ch.R_post, float).reshape(n, 9)
        chain[:, _P_POST:_P_POST + 3] = ch.p_post_m
        chain[:, _OFFSET] = ch.offset_rad
        idx = sensor_indices(arm, list(names))
        S = len(idx)
        mounts = np.empty((S, MOUNT_COLUMNS))
        for s, i in enumerate(idx):
            mounts[s, _R_LS:_R_LS + 9] = np.asarray(arm.sensors[i].R_LS, float).reshape(9)
            mounts[s, _P_LS:_P_LS + 3] = arm.sensors[i].p_L_m
        self.arm = arm
        self.names = tuple(names)
        self.chain = np.ascontiguousarray(chain)
        self.axis_is_z = bool(ch.axis_is_z)
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

    def fields(self, enc_fit: np.ndarray, offset: np.ndarray, omega_B: np.ndarray | None,
               omega_dot_B: np.ndarray | None, motion: bool = True) -> tuple:
        """The fields of the one-instant :class:`fusion.tracking.tracker.Frames` record (the same as
        ``make_frames(arm, names, enc_fit[0][None], offset[None], enc_fit[1][None],
        enc_fit[2][None], omega_B[None], omega_dot_B[None], motion, joint_effects).take(0)``),
        in its field order, without the measurement variances. ``omega_B``/``omega_dot_B``
        None: zero."""
        w = self._zeros3 if omega_B is None else omega_B
        wd = self._zeros3 if omega_dot_B is None else omega_dot_B
        delta = self.effect_delta
        if self._varying:
            delta = self._varying_deltas(enc_fit, offset, w, wd, motion)
        out = frame_one(enc_fit, offset, self.effect_joint, delta, w, wd, bool(motion), self.chain,
                        self.axis_is_z, self.mounts, self.links, self.g_mps2)
        offset_ref = out[1]
        offset_ref.setflags(write=False)
        return out[:10] + (np.float64(out[10]), None, out[11])

    def _varying_deltas(self, enc_fit, offset, w, wd, motion) -> np.ndarray:
        """The joint effects' changes at this instant, as :func:`make_frames` computes them
        (its motion state, its context)."""
        from models.effects import Context
        from models.motion import MotionState

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
    :func:`fusion.tracking.tracker.causal_poly_fit` for K = 1.

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
