"""Startup absolute calibration: every joint angle from a still arm.

Gravity fixes two angles per accelerometer only up to a discrete set of branches. The
solve:

1. averages every sensor over a still window (readings in g, with the standard error of
   each mean and a floor for what the sensor model does not capture);
2. enumerates every branch in closed form, walking the chain sensor by sensor (each pair of
   joints is the Paden-Kahan "subproblem 2": two rotations that carry one direction onto
   another, with up to two solutions);
3. polishes every branch at once with a batched Levenberg-Marquardt on all joints, the base
   roll and pitch, and every sensor's residual weighted by its noise (``method="joint"``),
   or pair by pair as the thesis did (``method="sequential"``, the reference);
4. keeps the branches inside the joint limits and picks one with a prior (the pose saved at
   the last clean shutdown, else the ready pose); where the prior does not clearly decide,
   the joints that differ are flagged ``ambiguous`` and both values reported;
5. gives every joint a sigma from the weighted Jacobian (base tilt included) and a flag.

Nothing here moves the arm. When joints are gravity-blind, :func:`propose_unlock_move`
finds the smallest move of a well-known joint that would make them readable.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from fusion.startup_kernels import lm_solve
from models.arm import ArmModel
from models.kinematics import gravity_chain
from models.sensor_models import stream_models

FLAGS = ("ok", "ill_conditioned", "gimbal_lock", "ambiguous", "out_of_limits")
DEG = np.pi / 180.0


# --------------------------------------------------------------------------------------
# settings and results
@dataclass(frozen=True)
class StartupSettings:
    gimbal_lock_deg: float = 2.5
    """A joint whose axis is within this angle of vertical is gravity-blind: no number."""
    sigma_limit_deg: float = 0.5
    """A joint with a larger sigma is ``ill_conditioned``."""
    prior_sigma_deg: float = 30.0
    """How far the arm may have moved since the prior pose was saved (1 sigma)."""
    prior_decisive_chi2: float = 9.0
    """The prior decides between branches when it prefers one by this much (chi-square)."""
    thesis_detector_g: float = 0.95
    """The thesis's detector: the sensor axis along the joint reads above this (in g)."""
    max_iterations: int = 30
    sigma_safety_factor: float = 1.25
    """Reported sigmas are the statistical ones times this. With exact sigmas, Gaussian tails
    alone put about 4 of 70,000 joint estimates beyond 4 sigma; the factor makes a "within
    4 sigma" claim hold over 10,000 poses (at the price of slightly wider, honest bars)."""
    profile_above_deg: float = 0.08
    """Joints with a linear sigma above this get the profile (non-quadratic) check."""
    limit_margin_deg: float = 0.5
    """Readings are noisy: a branch this close outside a limit is still feasible."""
    limit_reach_deg: float = 45.0
    """A branch at most this far outside a limit is also tried held at the limit."""


@dataclass(frozen=True)
class StillReadings:
    """Averaged still readings in g, per sensor: ``mean_g (3,)`` and ``sigma_g (3,)``.

    ``sigma_g`` is the standard error of each axis's mean combined with the sensor's
    unmodelled-error floor. The IMU entry is the base accelerometer.
    """

    accel_mean_g: dict[str, np.ndarray]
    accel_sigma_g: dict[str, np.ndarray]
    imu_mean_g: np.ndarray | None
    imu_sigma_g: np.ndarray | None
    t_start_s: float = 0.0
    t_end_s: float = 0.0


@dataclass(frozen=True)
class JointEstimate:
    name: str
    angle_rad: float | None
    sigma_rad: float | None
    flag: str
    alternatives_rad: tuple[float, ...] = ()
    axis_to_vertical_deg: float = 90.0
    thesis_detector_locked: bool | None = None

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "angle_rad": self.angle_rad,
            "sigma_rad": self.sigma_rad,
            "flag": self.flag,
            "alternatives_rad": list(self.alternatives_rad),
            "axis_to_vertical_deg": self.axis_to_vertical_deg,
            "thesis_detector_locked": self.thesis_detector_locked,
        }


@dataclass(frozen=True)
class UnlockMove:
    """A small, safe move of joints already known well, after which the blind joints read."""

    joints: tuple[str, ...]
    delta_rad: tuple[float, ...]
    target_rad: tuple[float, ...]
    expected_sigma_rad: tuple[float, ...]
    unlocks: tuple[str, ...]

    def as_dict(self) -> dict:
        return {
            "moves": [{"joint": j, "delta_rad": d, "target_rad": t}
                      for j, d, t in zip(self.joints, self.delta_rad, self.target_rad, strict=True)],
            "expected_sigma_rad": list(self.expected_sigma_rad),
            "unlocks": list(self.unlocks),
        }

    def describe(self) -> str:
        moves = " and ".join(f"{j} by {np.degrees(d):+.1f} deg (to {np.degrees(t):.1f})"
                             for j, d, t in zip(self.joints, self.delta_rad, self.target_rad,
                                                strict=True))
        return (f"move {moves}, then calibrate again: {', '.join(self.unlocks)} become "
                f"readable, worst expected sigma {np.degrees(max(self.expected_sigma_rad)):.3f} deg")


@dataclass(frozen=True)
class StartupResult:
    joints: tuple[JointEstimate, ...]
    roll_rad: float
    pitch_rad: float
    roll_sigma_rad: float
    pitch_sigma_rad: float
    residual_rms_g: float
    chi2_per_dof: float
    q_rad: np.ndarray  # the chosen branch, every joint (locked ones at an arbitrary value)
    covariance: np.ndarray  # (n + 2, n + 2): joints, roll, pitch
    branches_rad: np.ndarray  # (B, n) every feasible branch
    method: str
    t_start_s: float = 0.0
    t_end_s: float = 0.0
    unlock_move: UnlockMove | None = None
    summary: str = ""

    @property
    def flags(self) -> tuple[str, ...]:
        return tuple(j.flag for j in self.joints)

    @property
    def all_ok(self) -> bool:
        return all(f == "ok" for f in self.flags)

    def as_dict(self) -> dict:
        return {
            "t_start": self.t_start_s,
            "t_end": self.t_end_s,
            "method": self.method,
            "base": {"roll_rad": self.roll_rad, "pitch_rad": self.pitch_rad,
                     "roll_sigma_rad": self.roll_sigma_rad, "pitch_sigma_rad": self.pitch_sigma_rad},
            "joints": [j.as_dict() for j in self.joints],
            "residual_rms_g": self.residual_rms_g,
            "chi2_per_dof": self.chi2_per_dof,
            "branches": len(self.branches_rad),
            "unlock_move": None if self.unlock_move is None else self.unlock_move.as_dict(),
            "summary": self.summary,
        }


class StartupInputError(ValueError):
    """The readings cannot give joint angles (NaN, saturated, dead sensor...)."""


# --------------------------------------------------------------------------------------
# geometry helpers
def up_from_tilt(roll, pitch) -> np.ndarray:
    """World up in the base frame for base (roll, pitch): ``[-sp, sr cp, cr cp]``."""
    r, p = np.asarray(roll, float), np.asarray(pitch, float)
    return np.stack([-np.sin(p), np.sin(r) * np.cos(p), np.cos(r) * np.cos(p)], -1)


def up_tilt_jacobian(roll, pitch) -> np.ndarray:
    """``d up / d (roll, pitch)``: ``(..., 3, 2)``."""
    r, p = np.asarray(roll, float), np.asarray(pitch, float)
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    z = np.zeros_like(r)
    d_r = np.stack([z, cr * cp, -sr * cp], -1)
    d_p = np.stack([-cp, -sr * sp, -cr * sp], -1)
    return np.stack([d_r, d_p], -1)


def tilt_from_up(up: np.ndarray) -> tuple[float, float]:
    u = np.asarray(up, float)
    return float(np.arctan2(u[1], u[2])), float(np.arctan2(-u[0], np.hypot(u[1], u[2])))


def _skew(w: np.ndarray) -> np.ndarray:
    """``u @ _skew(w) == cross(u, w)`` for rows ``u``; ``_skew(w) @ u == cross(w, u)``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _subproblem1(w: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Angle about unit axis ``w`` taking direction ``p`` closest to ``q``, for rows of
    directions ``p``, ``q`` (``(P, 3)``, or one ``(3,)`` for all): ``(P,)``."""
    pp = p - (p @ w)[..., None] * w
    qq = q - (q @ w)[..., None] * w
    # w . (pp x qq) = pp . (qq x w)
    return np.arctan2((pp * (qq @ _skew(w))).sum(-1), (pp * qq).sum(-1))


def _subproblem2(w1, w2, p, q) -> np.ndarray:
    """Every (t1, t2) with ``Rot(w1, t1) Rot(w2, t2) p = q`` (unit directions; least-squares
    closest when noise makes it inexact), for one direction ``p (3,)`` and rows ``q (P, 3)``:
    ``(P, k, 2)``, k = 2 solutions (1 for parallel axes)."""
    q = np.atleast_2d(q)
    c12 = float(w1 @ w2)
    den = c12**2 - 1.0
    if abs(den) < 1e-9:  # parallel axes: only the sum is defined
        t = _subproblem1(w1, p, q)
        return np.stack([t, np.zeros_like(t)], -1)[:, None]
    qw1 = q @ w1
    pw2 = float(p @ w2)
    a = (c12 * pw2 - qw1) / den
    b = (c12 * qw1 - pw2) / den
    cr = _skew(w1) @ w2
    g2 = (float(p @ p) - a * a - b * b - 2 * a * b * c12) / (cr @ cr)
    # Near the pair's singularity the two solutions merge, and noise can hide one of them
    # (g2 < 0). Start on both sides anyway; the polish finds the real minima, and the
    # duplicates are removed.
    g_min = 0.02
    gamma = np.sqrt(np.maximum(g2, g_min))[:, None, None] * np.array([1.0, -1.0])[:, None]
    c = (a[:, None] * w1 + b[:, None] * w2)[:, None] + gamma * cr  # (P, 2, 3)
    c = c.reshape(-1, 3)
    out = np.empty((len(q), 2, 2))
    out[:, :, 1] = _subproblem1(w2, p, c).reshape(-1, 2)
    out[:, :, 0] = _subproblem1(w1, c, np.repeat(q, 2, 0)).reshape(-1, 2)
    return out


# --------------------------------------------------------------------------------------
@dataclass
class _Problem:
    """The weighted least-squares problem of one still window."""

    arm: ArmModel
    names: list[str]
    meas: np.ndarray  # (S, 3) unit directions measured by the link accelerometers
    sigma: np.ndarray  # (S, 3) sigma of each axis, in g (on the unit direction)
    imu_meas: np.ndarray | None
    imu_sigma: np.ndarray | None
    R_0I: np.ndarray = field(default_factory=lambda: np.eye(3))
    tilt_prior_rad: float = 5.0 * DEG

    def __post_init__(self):
        self._chain = gravity_chain(self.arm, self.names)
        # every row's read-out, weighted and negated: rows = -(D_s v) / sigma = r - meas / sigma
        self._read_w = -self._chain.read_out / self.sigma[:, :, None]  # (S, 3, 3)
        self._layouts: dict = {}
        self._kernel_layouts: dict = {}

    @property
    def n(self) -> int:
        return self.arm.n_joints

    def _layout(self, active: np.ndarray | None, use_imu: bool):
        """Rows of one kind of solve: the sensors used, the IMU or the level-chair prior."""
        key = (None if active is None else np.asarray(active, bool).tobytes(), use_imu)
        hit = self._layouts.get(key)
        if hit is None:
            S = len(self.names)
            used = np.arange(S) if active is None else np.flatnonzero(active)
            imu = use_imu and self.imu_meas is not None
            m = 3 * len(used) + (3 if imu else 2)
            meas_w = np.zeros(m)  # measured / sigma; 0 on the tilt prior's rows
            meas_w[: 3 * len(used)] = (self.meas[used] / self.sigma[used]).reshape(-1)
            reads = [(3 * i, int(self._chain.links[s]), self._read_w[s]) for i, s in enumerate(used)]
            if imu:
                meas_w[3 * len(used):] = self.imu_meas / self.imu_sigma
                reads.append((3 * len(used), 0, -self.R_0I.T / self.imu_sigma[:, None]))
            last = max([k for _, k, _ in reads], default=0) - 1  # the last joint any row needs
            hit = (m, meas_w, reads, imu, 3 * len(used), last)
            # the same, as the compiled kernels take it (fusion.startup_kernels)
            kern = (np.ascontiguousarray(np.stack([W for _, _, W in reads]) if reads
                                         else np.zeros((0, 3, 3))),
                    np.array([row for row, _, _ in reads], dtype=np.int64),
                    np.array([k for _, k, _ in reads], dtype=np.int64),
                    np.ascontiguousarray(meas_w), int(3 * len(used)), bool(imu),
                    float(self.tilt_prior_rad), int(last))
            self._kernel_layouts[key] = (self._chain.step_in, np.ascontiguousarray(
                self._chain.offset_rad, dtype=float)) + kern
            self._layouts[key] = hit
        return hit

    def kernel_layout(self, active: np.ndarray | None, use_imu: bool) -> tuple:
        """The chain and the rows of one kind of solve as :mod:`fusion.startup_kernels` takes
        them: ``(step_in, offset, read_W, read_row, read_link, meas_w, n_sensor_rows, imu,
        tilt_prior, last)``."""
        self._layout(active, use_imu)
        return self._kernel_layouts[(None if active is None else np.asarray(active, bool).tobytes(),
                                     use_imu)]

    def residuals_and_jacobian(self, x: np.ndarray, active: np.ndarray | None = None,
                               use_imu: bool = True):
        """Weighted residuals ``(B, m)`` and Jacobian ``(B, m, n + 2)`` for states ``x (B, n+2)``.

        ``active`` (S,) bool selects the sensors used (sequential solves); ``use_imu=False``
        leaves the base accelerometer out (the level-chair prior takes its place).
        Rows: 3 per sensor used (in config order), then the IMU's 3 or the prior's 2.
        """
        rJ = self._augmented(x, active, use_imu)
        return rJ[:, :, 0], rJ[:, :, 1:]

    def _augmented(self, x: np.ndarray, active: np.ndarray | None, use_imu: bool) -> np.ndarray:
        """Residuals and Jacobian side by side: ``(B, m, 1 + n + 2)``."""
        n = self.n
        B = x.shape[0]
        m, meas_w, reads, imu, n_sensor_rows, last = self._layout(active, use_imu)
        seed = _up_and_tilt_jacobian(x[:, n], x[:, n + 1])  # (B, 3, 3)
        after = self._chain.propagate(x[:, :n], seed, upto_joint=last)
        out = np.empty((B, m, n + 3))  # column 0: the residual's model part; then d/dx
        for row, k, W in reads:
            np.matmul(W, after[k], out=out[:, row:row + 3])
        if not imu:  # no base accelerometer: all we know is that a wheelchair stands roughly level
            prior = out[:, n_sensor_rows:]
            prior[:] = 0.0
            prior[:, :, 0] = x[:, n:] / self.tilt_prior_rad
            prior[:, 0, n + 1] = prior[:, 1, n + 2] = 1.0 / self.tilt_prior_rad
        out[:, :, 0] += meas_w
        return out

    def normal_matrices(self, x: np.ndarray, active: np.ndarray | None = None,
                        use_imu: bool = True) -> np.ndarray:
        """``[r J]^T [r J]`` for states ``x (B, n+2)``: ``(B, n+3, n+3)``, with ``r . r`` at
        [0, 0], ``J^T r`` down the rest of column 0 and ``J^T J`` below right; all LM needs."""
        rJ = self._augmented(x, active, use_imu)
        return np.ascontiguousarray(np.swapaxes(rJ, 1, 2)) @ rJ  # contiguous: a faster product


def _up_and_tilt_jacobian(roll, pitch) -> np.ndarray:
    """``[up, d up / d roll, d up / d pitch]`` as the columns of ``(B, 3, 3)``."""
    sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
    srcp, crcp = sr * cp, cr * cp
    out = np.empty((len(sr), 3, 3))
    out[:, 0, 0] = -sp
    out[:, 1, 0] = srcp
    out[:, 2, 0] = crcp
    out[:, 0, 1] = 0.0
    out[:, 1, 1] = crcp
    out[:, 2, 1] = -srcp
    out[:, 0, 2] = -cp
    out[:, 1, 2] = -sr * sp
    out[:, 2, 2] = -cr * sp
    return out


def _batched_lm(problem: _Problem, x0: np.ndarray, free: np.ndarray, iters,
                active: np.ndarray | None = None, use_imu: bool = True,
                ) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every start, compiled (:func:`fusion.startup_kernels.lm_solve`):
    the same arithmetic as :func:`_batched_lm_numpy`, which says what the arguments are."""
    # fresh writable C arrays of one type each: a single compiled signature
    x = np.array(x0, dtype=float, order="C")
    B, p = x.shape
    free_f = np.array(np.broadcast_to(np.asarray(free, bool), (B, p)), dtype=float, order="C")
    left = np.array(np.broadcast_to(np.asarray(iters), (B,)), dtype=np.int64, order="C")
    return lm_solve(x, free_f, left, *problem.kernel_layout(active, use_imu))


def _batched_lm_numpy(problem: _Problem, x0: np.ndarray, free: np.ndarray, iters,
                      active: np.ndarray | None = None, use_imu: bool = True,
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every start at once (the NumPy form of the compiled solve).
    ``free`` selects the unknowns: ``(n+2,)`` for all starts, or ``(B, n+2)`` per start (a
    held unknown keeps its start value). ``iters``: the most iterations, for all starts or
    ``(B,)`` per start.

    Each start stops on its own once it has converged (its next step below 1e-7 rad, not
    taken, or its damping past 1e8: no step lowers the cost) or used its iterations; the
    others go on without it. Returns the solutions and their final cost (half sum of
    squared weighted residuals).
    """
    x = np.array(x0, float)
    B, p = x.shape
    held_mask = ~np.broadcast_to(np.asarray(free, bool), (B, p))
    masked = bool(held_mask.any())
    iters_left = np.broadcast_to(np.asarray(iters), (B,)).astype(int)
    N = problem.normal_matrices(x, active, use_imu)  # (B, 1 + p, 1 + p): r.r, J^T r, J^T J
    cost = 0.5 * N[:, 0, 0]
    # the starts still iterating, packed: their rows in x, their state
    rows = np.flatnonzero(iters_left > 0)
    xa, Na, ca = x[rows], N[rows], cost[rows]
    lam = np.full(len(rows), 1e-3)
    free_f = (~held_mask[rows]).astype(float)
    held_f = held_mask[rows].astype(float)
    left = iters_left[rows]
    while len(rows):
        if masked:  # a held unknown's column is zero: it takes no step
            A = Na[:, 1:, 1:] * free_f[:, :, None] * free_f[:, None, :]
            g = Na[:, 1:, :1] * free_f[:, :, None]
        else:
            A = Na[:, 1:, 1:].copy()
            g = Na[:, 1:, :1]
        diag = A.reshape(len(A), p * p)[:, :: p + 1]  # a view: damping in place
        diag += lam[:, None] * (diag + 1e-9)
        if masked:
            diag += held_f
        step = -np.linalg.solve(A, g)[..., 0]
        # 1e-7 rad is a thousandth of the smallest sigma these sensors give: converged
        # (that last step is not taken: it could not change anything that is reported)
        done = np.abs(step).max(1) < 1e-7
        if done.any():
            x[rows[done]], cost[rows[done]] = xa[done], ca[done]
            go = ~done
            rows, xa, Na, ca, lam, step = rows[go], xa[go], Na[go], ca[go], lam[go], step[go]
            free_f, held_f, left = free_f[go], held_f[go], left[go]
            if not len(rows):
                break
        xt = xa + step
        Nt = problem.normal_matrices(xt, active, use_imu)
        ct = 0.5 * Nt[:, 0, 0]
        better = ct < ca
        if better.all():
            xa, Na, ca = xt, Nt, ct
        elif better.any():
            xa, Na, ca = (np.where(better[:, None], xt, xa), np.where(better[:, None, None], Nt, Na),
                          np.where(better, ct, ca))
        lam = np.where(better, lam * 0.3, lam * 10.0)
        left = left - 1
        done = (lam > 1e8) | (left <= 0)  # no step lowers the cost, or no iteration left
        if done.any():
            x[rows[done]], cost[rows[done]] = xa[done], ca[done]
            go = ~done
            rows, xa, Na, ca, lam = rows[go], xa[go], Na[go], ca[go], lam[go]
            free_f, held_f, left = free_f[go], held_f[go], left[go]
    return x, cost


def _profile_sigma(problem: _Problem, xb: np.ndarray, cost_b: float, sig: np.ndarray,
                   joints: np.ndarray, scale: float = 1.0,
                   ks: tuple[float, ...] = (3.0, 10.0, 30.0), cap_rad: float = np.pi / 3,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Sigma of each listed joint from the cost itself, not its curvature: hold the joint at
    +-k linear sigmas (k = 3, 10, 30; at most 60 deg), re-solve everything else, and see how
    much the fit worsens. Near a singular pair the cost is flatter than quadratic (a long
    valley) and the linear sigma far too small. The sigma kept is the half-width of the
    profile-likelihood interval (where the cost has risen by 0.5), at least the linear one.

    Also returns the probes' solutions ``(len(joints) * 6, n + 2)``: released from there,
    LM finds any other minimum along the valley."""
    n = problem.n
    if len(joints) == 0:
        return np.zeros(0), np.zeros((0, n + 2))
    m = 2 * len(ks)
    J = len(joints)
    d = np.minimum(np.multiply.outer(sig[joints], ks), cap_rad)  # (J, k), increasing
    offsets = np.concatenate([d, -d], 1)  # (J, m)
    rows = np.arange(J * m)
    held = np.repeat(joints, m)  # the joint each probe holds
    starts = np.repeat(xb[None], J * m, 0)
    starts[rows, held] += offsets.reshape(-1)
    free = np.ones((J * m, n + 2), bool)
    free[rows, held] = False
    probes, cost = _batched_lm(problem, starts, free, 12)
    dcost = np.maximum(cost.reshape(J, m) - cost_b, 1e-12) / scale**2
    k = len(ks)
    c = np.minimum(dcost[:, :k], dcost[:, k:])  # the easier side
    # the 1-sigma profile interval: where the fit has worsened by 0.5
    crossed = c >= 0.5
    a = np.argmax(crossed, 1)  # the first point past it (0 when none is)
    # crossed before the first point, or still inside at the widest: quadratic from there
    at = np.where(crossed.any(1), 0, k - 1)
    i = np.arange(J)
    quadratic = d[i, at] / np.sqrt(2.0 * c[i, at])
    # between two points: interpolate log(cost) against log(offset)
    a0 = np.maximum(a - 1, 0)
    x0, x1 = np.log(d[i, a0]), np.log(d[i, a])
    y0, y1 = np.log(c[i, a0]), np.log(c[i, a])
    between = crossed.any(1) & (a > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        inner = np.exp(x0 + (np.log(0.5) - y0) * (x1 - x0) / (y1 - y0))
    out = np.where(between, inner, quadratic)
    return np.maximum(out, sig[joints]), probes


def _follow_weak_starts(xb: np.ndarray, sig: np.ndarray, weak: np.ndarray, locked: np.ndarray):
    """The points each weak joint, in turn, is held at while everything else is re-solved
    (a locked joint: its whole turn; an ill-conditioned one: +-3 sigma, at most 60 deg):
    starts ``(P, n + 2)``, their free unknowns, and the joint each holds ``(P,)``."""
    L = np.flatnonzero(weak)
    sweeps = [np.linspace(-np.pi, np.pi, 12, endpoint=False)[1:] if locked[j]
              else np.array([-1, -2 / 3, -1 / 3, 1 / 3, 2 / 3, 1]) * min(3 * sig[j], np.pi / 3)
              for j in L]
    j_of = np.repeat(L, [len(d) for d in sweeps]).astype(int)
    rows = np.arange(len(j_of))
    starts = np.repeat(xb[None], len(j_of), 0)
    starts[rows, j_of] += np.concatenate(sweeps) if sweeps else 0.0
    free = np.ones(starts.shape, bool)
    free[rows, j_of] = False
    return starts, free, j_of


def _follow_weak(x: np.ndarray, cost: np.ndarray, j_of: np.ndarray, xb: np.ndarray,
                 cost_b: float, locked: np.ndarray, inflate: float) -> np.ndarray:
    """How far each joint moves while each weak joint sweeps what the data allow, from the
    re-solved points ``x`` (and their ``cost``) of :func:`_follow_weak_starts`: ``(n_weak,
    n)`` rad. Points whose fit is worse than a 3-sigma change (chi-square 9) are not
    allowed, except for a locked joint (the data say nothing about it)."""
    n = len(locked)
    allowed = locked[j_of] | ((cost - cost_b) / inflate <= 4.5)
    moved = np.abs(_wrap(x[:, :n] - xb[:n])) * allowed[:, None]
    moved[np.arange(len(j_of)), j_of] = 0.0
    return np.stack([moved[j_of == j].max(0) for j in np.unique(j_of)])


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _closed_form_branches(problem: _Problem, roll: float, pitch: float) -> np.ndarray:
    """Every branch of joint angles, walking the chain sensor by sensor: ``(B, n)``.

    Joints no sensor reads stay at the ready pose. A joint whose angle is undefined here
    (its axis along gravity) takes its ready-pose value; the polish and flags handle it.
    Every partial branch is carried at once (rows of ``q``, ``v``).
    """
    arm = problem.arm
    up0 = up_from_tilt(roll, pitch)
    order = np.argsort([arm.sensor(nm).link for nm in problem.names])
    # each partial branch: its joint angles so far, and up expressed in its last frame
    q = arm.ready_pose_rad.astype(float)[None].copy()  # (P, n)
    v = up0[None]  # (P, 3): up in frame prev_link
    prev_link = 0
    ch = arm.chain
    turns = _joint_turn_parts(arm)
    for s in order:
        mount = arm.sensor(problem.names[s])
        k = mount.link
        joints = list(range(prev_link, k))
        if not joints:
            continue
        w = mount.R_LS @ problem.meas[s]  # up in frame k (unit)
        # only the last two joints before the sensor are solved; earlier unread joints
        # (more than two per sensor) stay at their ready values
        solve = joints[-2:]
        u = v
        for j in joints[:-2]:
            u = _turn_back(turns[j], ch.offset_rad[j], q[:, j], u)
        if len(solve) == 1:
            j = solve[0]
            v1 = u @ ch.R_pre[j]  # rows of R_pre^T u
            w1 = ch.R_post[j] @ w
            cand = (_subproblem1(ch.axis[j], w1, v1) - ch.offset_rad[j])[:, None, None]
        else:
            a, b = solve
            v1 = u @ ch.R_pre[a]
            w1 = ch.R_post[b] @ w
            M = ch.R_post[a] @ ch.R_pre[b]
            cand = _subproblem2(ch.axis[a], M @ ch.axis[b], M @ w1, v1) - ch.offset_rad[solve]
        per = cand.shape[1]  # candidates per partial branch, kept in order
        q = np.repeat(q, per, 0)
        q[:, solve] = cand.reshape(-1, len(solve))
        v = np.repeat(v, per, 0)
        for j in joints:
            v = _turn_back(turns[j], ch.offset_rad[j], q[:, j], v)
        prev_link = k
    # bring each angle to the representative closest to the middle of its limits
    mid = (arm.min_rad + arm.max_rad) / 2
    return mid + _wrap(q - mid)


def _joint_turn_parts(arm: ArmModel) -> np.ndarray:
    """Per joint, the three constant parts of the rotation of frame j+1 in frame j:
    ``R(t) = P0 + sin t P1 + (1 - cos t) P2`` (Rodrigues between ``R_pre`` and ``R_post``):
    ``(n, 3, 3, 3)``, built once per arm."""
    parts = arm.__dict__.get("_startup_turn_parts")
    if parts is None:
        ch = arm.chain
        parts = np.empty((arm.n_joints, 3, 3, 3))
        for j in range(arm.n_joints):
            K = _skew(ch.axis[j])
            for i, M in enumerate((np.eye(3), K, K @ K)):
                parts[j, i] = ch.R_pre[j] @ M @ ch.R_post[j]
        arm.__dict__["_startup_turn_parts"] = parts
    return parts


def _turn_back(parts: np.ndarray, offset_rad: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rows ``v (P, 3)`` in frame j, expressed in frame j+1 (joint j at ``q (P,)``; ``parts``
    its :func:`_joint_turn_parts`): ``v @ R(q)``."""
    t = (q + offset_rad)[:, None]
    u = v @ parts  # (3, P, 3)
    return u[0] + np.sin(t) * u[1] + (1.0 - np.cos(t)) * u[2]


def _dedupe(q: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """The rows of ``q`` in order, each left out when within ``tol`` (every angle) of a row
    kept before it."""
    close = (np.abs(_wrap(q[:, None] - q[None])).max(-1) < tol).tolist()  # (B, B)
    keep: list[int] = []
    for i, row in enumerate(close):
        if not any(row[k] for k in keep):
            keep.append(i)
    return q[keep]


# --------------------------------------------------------------------------------------
def solve_still(
    arm: ArmModel,
    readings: StillReadings,
    settings: StartupSettings | None = None,
    prior_q_rad: np.ndarray | None = None,
    method: str = "joint",
    propose_unlock: bool = True,
    prior_sigma_rad: np.ndarray | float | None = None,
) -> StartupResult:
    """Every joint angle of a still arm from averaged readings, with sigma and flags.

    The prior (default: the ready pose, ``settings.prior_sigma_deg`` per joint) only picks
    between branches that fit the data equally; it never pulls a value.
    """
    st = settings or StartupSettings()
    check_readings(readings)
    problem = _make_problem(arm, readings)
    n = arm.n_joints
    # base tilt from the IMU (the thesis's eq. 4.1, in the recording spec's convention)
    if problem.imu_meas is not None:
        roll0, pitch0 = tilt_from_up(problem.R_0I @ problem.imu_meas)
    else:
        roll0 = pitch0 = 0.0
    starts = _closed_form_branches(problem, roll0, pitch0)
    prior = arm.ready_pose_rad if prior_q_rad is None else np.asarray(prior_q_rad, float)
    if method == "joint":
        # Near a singular pair the closed-form starts are noisy and LM from them can miss
        # the branch nearest the prior (it slides into a neighbouring one): start there too.
        starts = np.vstack([starts, prior[None]])
    x0 = np.concatenate([starts, np.tile([roll0, pitch0], (len(starts), 1))], 1)
    free = np.ones(n + 2, dtype=bool)
    if method == "joint":
        x, cost = _batched_lm(problem, x0, free, st.max_iterations)
    elif method == "sequential":
        x, cost = _sequential(problem, x0, st)
    else:
        raise ValueError(f"unknown method {method!r}: use 'joint' or 'sequential'")
    mid = (arm.min_rad + arm.max_rad) / 2
    x[:, :n] = mid + _wrap(x[:, :n] - mid)
    margin = st.limit_margin_deg * DEG
    # A minimum just outside a limit (a flat valley, noise pushing its floor past the limit)
    # leaves a real solution at the limit itself: hold the joints there, re-solve the rest,
    # and let that constrained solution compete like any other branch.
    past = np.maximum(arm.min_rad - margin - x[:, :n], x[:, :n] - arm.max_rad - margin)
    near_out = (past > 0).any(1) & (past.max(1) < st.limit_reach_deg * DEG)
    if near_out.any():
        xc = x[near_out].copy()
        xc[:, :n] = np.clip(xc[:, :n], arm.min_rad, arm.max_rad)
        free_c = np.ones((len(xc), n + 2), dtype=bool)
        free_c[:, :n] = ~(past[near_out] > 0)
        xc, cost_c = _batched_lm(problem, xc, free_c, st.max_iterations)
        xc[:, :n] = mid + _wrap(xc[:, :n] - mid)
        x, cost = np.vstack([x, xc]), np.concatenate([cost, cost_c])
    # drop branches that fit much worse than the best (not real solutions of the data)
    good = cost <= cost.min() + 0.5 * 9.0 + 1e-9
    x, cost = x[good], cost[good]
    order = np.argsort(cost)
    x, cost = x[order], cost[order]
    q_all = x[:, :n]
    axis_deg = np.degrees(_axis_to_vertical(arm, q_all, x[:, n], x[:, n + 1]))
    locked_any = axis_deg < st.gimbal_lock_deg  # (B, n)
    # feasibility: locked joints can take any value, so only readable joints are checked
    inside = (arm.within_limits(q_all, margin) | locked_any).all(1)
    feasible_idx = np.flatnonzero(inside)
    branches = _dedupe(q_all[feasible_idx] if len(feasible_idx) else q_all, 1e-3)
    if len(feasible_idx):
        cand = feasible_idx
    else:
        cand = np.arange(len(x))
    # prior: distance on the readable joints
    psig = np.broadcast_to(st.prior_sigma_deg * DEG if prior_sigma_rad is None
                           else np.asarray(prior_sigma_rad, float), (n,))
    d2 = np.sum((_wrap(q_all[cand] - prior) / psig) ** 2 * ~locked_any[cand], 1)
    best = cand[int(np.argmin(d2))]
    xb = x[best]
    qb = xb[:n]
    # covariance from the weighted Jacobian at the chosen solution
    r, J = problem.residuals_and_jacobian(xb[None])
    r, J = r[0], J[0]
    # a normalised direction carries two constraints, not three; the tilt prior two more
    n_dir = len(problem.names) + 1  # the IMU's direction, or the level-chair prior
    dof = max(2 * n_dir - int(free.sum()), 1)
    chi2_dof = float(r @ r / dof)
    locked = locked_any[best]
    # Information from the data, plus the only thing known about a gravity-blind joint: it
    # is somewhere in its range (a flat prior of width pi). The marginal sigma of every other
    # joint then carries its correlation with the blind ones.
    cols = free.copy()
    Jr = J[:, cols]
    info = Jr.T @ Jr
    # Every joint gets that flat prior: it costs nothing where the data speak, and where
    # they do not (a singular pair: two axes and gravity coplanar) the sigma becomes
    # honestly large instead of being cut off by a pseudo-inverse.
    prior_info = np.full(int(cols.sum()), 1.0 / np.pi**2)
    # the fit itself says when the model is worse than its sigmas (Birge ratio)
    inflate = max(chi2_dof, 1.0)
    cov = np.full((n + 2, n + 2), np.nan)
    cov_r = np.linalg.inv(info + np.diag(prior_info)) * inflate
    cov[np.ix_(cols, cols)] = cov_r
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    # the cost's own verdict on every readable joint (flat valleys near singular pairs)
    # (well-read joints are quadratic over many sigmas: only the wider ones are checked)
    readable = np.flatnonzero(~locked & np.isfinite(sig[:n]) & (sig[:n] > st.profile_above_deg * DEG))
    sig[readable], probes = _profile_sigma(problem, xb, float(0.5 * r @ r), sig, readable,
                                           np.sqrt(inflate))
    flags = np.array(["ok"] * n, dtype=object)
    flags[locked] = "gimbal_lock"
    limit = st.sigma_limit_deg * DEG
    # Joints whose value rests on a weak one (locked, or sigma above the limit): sweep the
    # weak joint across what the data allow, re-solve the rest, and widen the others'
    # sigma by how far they follow. A joint pushed over the limit by a locked joint
    # inherits its flag; by an ill-conditioned one, it becomes ill-conditioned.
    weak = locked | (sig[:n] > limit)
    follow_x0, follow_free, follow_j = _follow_weak_starts(xb, sig, weak, locked)
    # A valley may hold other minima than the branches the starts reached: the profile's
    # probes are released, each rolls to its own; good ones join the branches as rivals
    # below. Those and the sweep are solved in one batch (every row on its own).
    solved, solved_cost = np.zeros((0, n + 2)), np.zeros(0)
    if len(probes) or len(follow_j):
        solved, solved_cost = _batched_lm(
            problem, np.vstack([probes, follow_x0]),
            np.vstack([np.ones(probes.shape, bool), follow_free]),
            np.concatenate([np.full(len(probes), st.max_iterations), np.full(len(follow_j), 12)]))
    xr, cost_r = solved[: len(probes)], solved_cost[: len(probes)]
    if len(probes):
        xr[:, :n] = mid + _wrap(xr[:, :n] - mid)
        keep = ((cost_r <= cost.min() + 0.5 * 9.0 + 1e-9)
                & (arm.within_limits(xr[:, :n], margin) | locked_any[best]).all(1))
        if keep.any():
            xr = _dedupe(xr[keep], 1e-3)
            x = np.vstack([x, xr])
            q_all = x[:, :n]
            d2r = np.sum((_wrap(xr[:, :n] - prior) / psig) ** 2 * ~locked_any[best], 1)
            cand = np.concatenate([cand, np.arange(len(x) - len(xr), len(x))])
            d2 = np.concatenate([d2, d2r])
    if weak.any():
        follow = _follow_weak(solved[len(probes):], solved_cost[len(probes):], follow_j, xb,
                              float(0.5 * r @ r), locked, inflate)
        moved = follow.max(0)  # (n,): the widest any weak joint drags each joint
        widened = np.maximum(sig[:n], moved / 3.0)
        by_locked = follow[locked[weak]].max(0) if locked.any() else np.zeros(n)
        from_locked = ~weak & (widened > limit) & (by_locked / 3.0 > limit)
        sig[:n] = np.where(weak, sig[:n], widened)
        flags[from_locked] = "gimbal_lock"
    sig = sig * st.sigma_safety_factor
    ill = (sig[:n] > limit) & (flags == "ok")
    flags[ill] = "ill_conditioned"
    out_of_limits = ~arm.within_limits(qb, margin) & (flags == "ok")
    flags[out_of_limits] = "out_of_limits"
    alternatives: list[list[float]] = [[] for _ in range(n)]
    if len(cand) > 1:
        # every branch the prior cannot rule out against the chosen one
        rivals = cand[d2 - d2.min() < st.prior_decisive_chi2]
        for other in rivals:
            if other == best:
                continue
            # a joint is ambiguous when the branches disagree by more than its own sigma
            # can cover (close branches come from a nearly singular pair)
            gap = np.abs(_wrap(q_all[other] - qb))
            differ = gap > np.maximum(3 * sig[:n], 1e-3)
            # an ill-conditioned joint already says its number is weak: its sigma grows to
            # cover the other minimum (at 2 sigma) instead of hiding it
            for j in np.flatnonzero(differ & (flags == "ill_conditioned")):
                grow = gap[j] / 2.0 / sig[j]
                sig[j] *= grow
                cov[j, :] *= grow
                cov[:, j] *= grow
            for j in np.flatnonzero(differ & np.isin(flags, ("ok", "ambiguous"))):
                flags[j] = "ambiguous"
                if not alternatives[j]:
                    alternatives[j].append(float(qb[j]))
                if all(abs(_wrap(q_all[other][j] - v)) > 1e-3 for v in alternatives[j]):
                    alternatives[j].append(float(q_all[other][j]))
    thesis = thesis_detector(arm, problem.names, problem.meas, st.thesis_detector_g)
    joints = []
    for j in range(n):
        number = flags[j] not in ("gimbal_lock", "ambiguous")
        joints.append(JointEstimate(
            name=arm.joints[j].name,
            angle_rad=float(qb[j]) if number else None,
            sigma_rad=float(sig[j]) if number and np.isfinite(sig[j]) else None,
            flag=str(flags[j]),
            alternatives_rad=tuple(alternatives[j]),
            axis_to_vertical_deg=float(axis_deg[best, j]),
            thesis_detector_locked=thesis[j],
        ))
    resid_g = (r[: problem.meas.size] * problem.sigma.reshape(-1))
    result = StartupResult(
        joints=tuple(joints),
        roll_rad=float(xb[n]), pitch_rad=float(xb[n + 1]),
        roll_sigma_rad=float(sig[n]), pitch_sigma_rad=float(sig[n + 1]),
        residual_rms_g=float(np.sqrt(np.mean(resid_g**2))),
        chi2_per_dof=chi2_dof,
        q_rad=qb.copy(), covariance=cov * st.sigma_safety_factor**2, branches_rad=branches,
        method=method,
        t_start_s=readings.t_start_s, t_end_s=readings.t_end_s,
    )
    if propose_unlock and any(f in ("gimbal_lock", "ill_conditioned") for f in flags):
        result = replace(result, unlock_move=propose_unlock_move(arm, result, readings, st, prior))
    summary = _summary(result)
    floor_g = max(_sensor_floor_g(arm, nm) for nm in problem.names)
    if floor_g >= 0.005 and any(j.flag == "ill_conditioned" for j in result.joints):
        summary += (f" (the sigmas include the config's unmodelled sensor error, "
                    f"{floor_g * 1000:.0f} mg per axis: calibrating the sensors lowers it)")
    elif arm.calibration.get("correction_covariance") and any(j.flag == "ill_conditioned"
                                                            for j in result.joints):
        summary += (" (the sigmas include what the sensors' calibration could not pin: its held "
                    "elements, with the motion that would separate them, in `calibrate sensors`)")
    return replace(result, summary=summary)


def _sequential(problem: _Problem, x0: np.ndarray, st: StartupSettings):
    """The thesis's method: each accelerometer solves its own joints, given the ones before.

    acc1 -> joints 1-2, acc2 -> 3-4, acc3 -> 5-6, acc4 -> 7, each by LM with the earlier
    joints held; the base tilt comes from the IMU alone, first.
    """
    arm, n = problem.arm, problem.n
    x = x0.copy()
    if problem.imu_meas is not None:
        free = np.zeros(n + 2, dtype=bool)
        free[n:] = True
        x, _ = _batched_lm(problem, x, free, st.max_iterations, active=np.zeros(len(problem.names), bool))
    prev = 0
    links = [arm.sensor(nm).link for nm in problem.names]
    for s in np.argsort(links):
        k = links[s]
        if k <= prev:
            continue
        free = np.zeros(n + 2, dtype=bool)
        free[prev:k] = True
        active = np.zeros(len(problem.names), bool)
        active[s] = True
        # the IMU does not take part in the joint pairs
        x, _ = _batched_lm(problem, x, free, st.max_iterations, active=active, use_imu=False)
        prev = k
    r, _ = problem.residuals_and_jacobian(x)
    return x, 0.5 * np.sum(r**2, 1)


def _axis_to_vertical(arm, q, roll, pitch) -> np.ndarray:
    c = np.abs(gravity_chain(arm).axis_up_cos(q, up_from_tilt(roll, pitch)))
    return np.arccos(np.clip(c, 0.0, 1.0))


def thesis_detector(arm: ArmModel, names, meas: np.ndarray, threshold_g: float) -> list[bool | None]:
    """The thesis's gimbal-lock test: the accelerometer axis parallel to a joint's axis reads
    close to 1 g. It applies only to a joint whose axis is fixed in an accelerometer's link
    (the last joint before each sensor); for the others it says nothing (None)."""
    out: list[bool | None] = [None] * arm.n_joints
    ch = arm.chain
    for s, nm in enumerate(names):
        mount = arm.sensor(nm)
        k = mount.link
        if k == 0:
            continue
        j = k - 1
        axis_k = ch.R_post[j].T @ ch.axis[j]  # joint k's axis in frame k
        axis_s = mount.R_LS.T @ axis_k
        i = int(np.argmax(np.abs(axis_s)))
        if abs(axis_s[i]) < np.cos(10 * DEG) or out[j] is not None:
            continue  # no sensor axis along this joint
        out[j] = bool(abs(meas[s][i]) > threshold_g)
    return out


# --------------------------------------------------------------------------------------
def propose_unlock_move(arm: ArmModel, result: StartupResult, readings: StillReadings,
                        settings: StartupSettings | None = None,
                        prior_q_rad: np.ndarray | None = None,
                        max_move_deg: float = 45.0,
                        blind_range_deg: float = 60.0) -> UnlockMove | None:
    """The smallest move of one well-known joint that makes the blind joints readable.

    The blind joints' values are unknown: a move counts only if it works for every value
    they plausibly have (the prior pose, +-``blind_range_deg``, inside their limits). The
    expected sigmas are the worst over those values, from the solve's own noise model. All
    candidate moves are evaluated in one batch.
    """
    st = settings or StartupSettings()
    blind = np.array([j.flag in ("gimbal_lock", "ill_conditioned") for j in result.joints])
    known = np.array([j.flag == "ok" for j in result.joints])
    if not blind.any() or not known.any():
        return None
    problem = _make_problem(arm, readings)
    prior = arm.ready_pose_rad if prior_q_rad is None else np.asarray(prior_q_rad, float)
    L = np.flatnonzero(blind)
    offsets = np.linspace(-blind_range_deg, blind_range_deg, 5) * DEG
    grid = np.array(np.meshgrid(*[offsets] * len(L), indexing="ij")).reshape(len(L), -1).T
    blind_values = np.clip(prior[L] + grid, arm.min_rad[L], arm.max_rad[L])  # (G, |L|)
    base = result.q_rad.copy()
    K = np.flatnonzero(known)
    steps = np.array([1, 2, 3, 5, 7.5, 10, 15, 20, 30, 45], float)
    steps = steps[steps <= max_move_deg] * DEG
    singles = [((j, sg * d),) for d in steps for j in K for sg in (1, -1)]
    pair_steps = np.array([5, 10, 15, 20, 30], float) * DEG
    pairs = [((j, sj * dj), (k, sk * dk)) for j in K for k in K if j < k
             for dj in pair_steps for dk in pair_steps for sj in (1, -1) for sk in (1, -1)]
    pairs.sort(key=lambda m: sum(abs(d) for _, d in m))
    for moves in (singles, pairs):  # one joint if that is enough, else two
        for i in range(0, len(moves), 48):  # smallest moves first; stop at the first that works
            found = _best_move(arm, problem, result, base, moves[i:i + 48], L, blind_values, st)
            if found is not None:
                return found
    return None


def prior_after_move(result: StartupResult, move: UnlockMove, arm: ArmModel,
                     settings: StartupSettings | None = None,
                     known_sigma_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The prior for the calibration after an unlock move: the joints known before the move
    where they were (plus the move, which the encoders counted), tightly; the blind ones
    loosely around their previous values."""
    st = settings or StartupSettings()
    q = result.q_rad.copy()
    for name, d in zip(move.joints, move.delta_rad, strict=True):
        q[arm.joint_names.index(name)] += d
    sig = []
    for j in result.joints:
        if j.flag == "ok":
            sig.append(known_sigma_deg * DEG)
        elif j.flag == "ill_conditioned" and j.sigma_rad is not None:
            # poorly read, but read: its sigma already covers every minimum the data allow
            # (the prior's own chi-square test then asks for 3 of them before it decides)
            sig.append(max(j.sigma_rad, known_sigma_deg * DEG))
        else:
            sig.append(st.prior_sigma_deg * DEG)
    return q, np.array(sig)


def _best_move(arm, problem, result, base, moves, L, blind_values, st) -> UnlockMove | None:
    n = arm.n_joints
    ok_moves = [m for m in moves
                if all(arm.min_rad[j] <= base[j] + d <= arm.max_rad[j] for j, d in m)]
    if not ok_moves:
        return None
    G = len(blind_values)
    Q = np.tile(base, (len(ok_moves) * G, 1))
    for i, m in enumerate(ok_moves):
        block = Q[i * G:(i + 1) * G]
        for j, d in m:
            block[:, j] += d
        block[:, L] = blind_values
    x = np.concatenate([Q, np.tile([result.roll_rad, result.pitch_rad], (len(Q), 1))], 1)
    ang = np.degrees(_axis_to_vertical(arm, Q, x[:, n], x[:, n + 1])).reshape(len(ok_moves), G, n)
    sig = _expected_sigma(problem, x).reshape(len(ok_moves), G, -1)[..., :n]
    worst = np.nanmax(sig, 1)  # (M, n)
    clear = ang.min(axis=(1, 2)) >= 2 * st.gimbal_lock_deg
    # a quarter of the limit: a margin for noise, for the real pose, and for branches that
    # stay close together just past a singular pair
    good = clear & np.all(worst <= 0.5 * st.sigma_limit_deg * DEG, 1)
    if not good.any():
        return None
    i = int(np.flatnonzero(good)[0])  # moves are ordered by size
    m = ok_moves[i]
    return UnlockMove(
        joints=tuple(arm.joints[j].name for j, _ in m),
        delta_rad=tuple(float(d) for _, d in m),
        target_rad=tuple(float(base[j] + d) for j, d in m),
        expected_sigma_rad=tuple(float(v) for v in worst[i]),
        unlocks=tuple(arm.joints[k].name for k in L),
    )


def _expected_sigma(problem: _Problem, x: np.ndarray) -> np.ndarray:
    """Sigma of every unknown at states ``x (B, n+2)`` from the Jacobian alone."""
    _, J = problem.residuals_and_jacobian(x)
    A = np.einsum("bmi,bmj->bij", J, J) + np.eye(J.shape[-1]) / np.pi**2  # as in the solve
    cov = np.linalg.inv(A)
    return np.sqrt(np.clip(np.einsum("bii->bi", cov), 0, None))


# --------------------------------------------------------------------------------------
def _make_problem(arm: ArmModel, readings: StillReadings) -> _Problem:
    names = [s.name for s in arm.link_accelerometers if s.name in readings.accel_mean_g]
    if not names:
        raise StartupInputError("no link accelerometer readings: nothing to solve from")
    meas, sig = [], []
    for nm in names:
        m = np.asarray(readings.accel_mean_g[nm], float)
        norm = float(np.linalg.norm(m))
        meas.append(m / norm)
        sig.append(np.asarray(readings.accel_sigma_g[nm], float) / norm)
    imu_m = imu_s = None
    R_0I = np.eye(3)
    if readings.imu_mean_g is not None and arm.imu is not None:
        m = np.asarray(readings.imu_mean_g, float)
        norm = float(np.linalg.norm(m))
        imu_m, imu_s = m / norm, np.asarray(readings.imu_sigma_g, float) / norm
        R_0I = arm.imu.R_LS
    return _Problem(arm, names, np.array(meas), np.array(sig), imu_m, imu_s, R_0I)


def _summary(res: StartupResult) -> str:
    bad = [f"{j.name} {j.flag}" for j in res.joints if j.flag != "ok"]
    if not bad:
        worst = max(j.sigma_rad for j in res.joints)
        return f"all {len(res.joints)} joints ok; worst sigma {np.degrees(worst):.3f} deg"
    text = f"{len(res.joints) - len(bad)} of {len(res.joints)} joints ok; " + ", ".join(bad)
    if res.unlock_move is not None:
        text += "; " + res.unlock_move.describe()
    return text


# --------------------------------------------------------------------------------------
# from a recording
@dataclass(frozen=True)
class InputCheck:
    """What was wrong with one sensor's still window, and that it was left out."""

    sensor: str
    message: str


def _sensor_floor_g(arm: ArmModel, name: str) -> float:
    cal = arm.calibration if hasattr(arm, "calibration") else {}
    per = (cal.get("accel_unmodelled_g_per_sensor") or {}).get(name)
    return float(per if per is not None else cal.get("accel_unmodelled_g", 0.0))


def _noise_g(model, n_samples: int) -> np.ndarray:
    """Standard error of a mean of ``n_samples`` counts, in g, rounding to counts included."""
    return np.sqrt(model.noise_counts_rms**2 + 1.0 / 12.0) / np.abs(model.gain) / np.sqrt(n_samples)


def readings_from_recording(
    arm: ArmModel, rec, t_start_s: float, t_end_s: float, window_s: float = 1.0,
    magnitude_range_g: tuple[float, float] = (0.8, 1.2),
) -> tuple[StillReadings, list[InputCheck]]:
    """Average every sensor over the last ``window_s`` of a still segment.

    Counts become g with each sensor's count model (``models.sensor_models``). A sensor
    whose window holds saturated counts, or whose mean is far from 1 g in magnitude (dead,
    disconnected, or the arm was not still), is left out with a message; the others are kept.
    """
    t0 = max(t_start_s, t_end_s - window_s)
    means, sigmas, checks = {}, {}, []
    names = [m.name for m in arm.link_accelerometers] + (["imu_acc"] if arm.imu is not None else [])
    models = stream_models(arm, {nm: (rec.get(nm).rate_hz or 100.0) if rec.get(nm) is not None
                                 else 100.0 for nm in names})
    imu_m = imu_s = None
    for name in names:
        label = "imu" if name == "imu_acc" else name
        s = rec.get(name)
        if s is None:
            checks.append(InputCheck(label, (
                "imu: no accelerometer samples (imu_acc) in the recording; the base tilt rests "
                "on the link accelerometers alone") if name == "imu_acc"
                else f"{name}: no samples in the recording"))
            continue
        w = s.between(t0, t_end_s + 1e-9)
        m, sg, msg = _average(label, w, models[name], magnitude_range_g, t0, t_end_s)
        if msg:
            checks.append(InputCheck(label, msg))
        elif name == "imu_acc":
            imu_m, imu_s = m, sg
        else:
            means[name] = m
            sigmas[name] = np.sqrt(sg**2 + _sensor_floor_g(arm, name) ** 2)
    return StillReadings(means, sigmas, imu_m, imu_s, t0, t_end_s), checks


def _average(name, w, model, mag_range, t0, t1):
    where = f"{name} in t = {t0:.2f}..{t1:.2f} s"
    if len(w) < 3:
        return None, None, f"{where}: only {len(w)} samples; need at least 3"
    v = w.values
    lo, hi = model.counts_min, model.counts_max
    if lo is not None:
        sat = model.saturated(v)
        if sat.any():
            axis = "xyz"[int(np.argmax(sat.sum(0)))]
            return None, None, (f"{where}: axis {axis} saturated ({int(sat.sum(0).max())} of "
                                f"{len(w)} samples at the {lo:.0f}/{hi:.0f} count limit); left out")
    mean_g = model.from_counts(v.mean(0, keepdims=True))[0]
    mag = float(np.linalg.norm(mean_g))
    if not mag_range[0] <= mag <= mag_range[1]:
        return None, None, (f"{where}: reads {mag:.3f} g in magnitude while still, expected about "
                            f"1 g: a dead or disconnected sensor, or a wrong scale; left out")
    return mean_g, _noise_g(model, len(w)), None


def readings_from_counts(arm: ArmModel, mean_counts: dict[str, np.ndarray], n_samples: int,
                         rate_hz: float = 100.0) -> StillReadings:
    """Still readings from per-sensor mean counts over ``n_samples`` (no checks): the same
    conversion and sigmas as :func:`readings_from_recording`, for batch tools."""
    models = stream_models(arm, rate_hz)
    means, sigmas = {}, {}
    for mount in arm.link_accelerometers:
        if mount.name in mean_counts:
            mdl = models[mount.name]
            means[mount.name] = mdl.from_counts(np.asarray(mean_counts[mount.name], float)[None])[0]
            sigmas[mount.name] = np.sqrt(_noise_g(mdl, n_samples) ** 2
                                         + _sensor_floor_g(arm, mount.name) ** 2)
    imu_m = imu_s = None
    if "imu_acc" in mean_counts and "imu_acc" in models:
        mdl = models["imu_acc"]
        imu_m = mdl.from_counts(np.asarray(mean_counts["imu_acc"], float)[None])[0]
        imu_s = _noise_g(mdl, n_samples)
    return StillReadings(means, sigmas, imu_m, imu_s)


def check_readings(readings: StillReadings) -> None:
    """Refuse readings that cannot give a number (non-finite values), naming the sensor."""
    for name, m in readings.accel_mean_g.items():
        if not np.all(np.isfinite(m)) or not np.all(np.isfinite(readings.accel_sigma_g[name])):
            raise StartupInputError(f"{name}: reading {np.asarray(m).tolist()} is not finite")
        mag = float(np.linalg.norm(m))
        if not 0.5 <= mag <= 1.5:
            raise StartupInputError(
                f"{name}: reads {mag:.3f} g in magnitude while still, expected about 1 g")
    if readings.imu_mean_g is not None and not np.all(np.isfinite(readings.imu_mean_g)):
        raise StartupInputError(f"imu: reading {np.asarray(readings.imu_mean_g).tolist()} is not finite")
