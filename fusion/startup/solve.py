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
4. keeps the branches inside the joint limits. With no prior every branch that fits is a
   rival: the joints on which fitting branches differ are flagged ``ambiguous`` with every
   candidate, and :func:`propose_disambiguating_move` finds the smallest safe move after
   which they read differently. A prior (:class:`StartupPrior`: a saved pose, or an earlier
   window's answer carried through the encoder counts) chooses only when it fits the data
   (chi-square test); the ready pose chooses only when the caller asserts the arm is
   parked, and the result says so;
5. gives every joint a sigma from the weighted Jacobian (base tilt included) and a flag.

Nothing here moves the arm. When joints are gravity-blind, :func:`propose_unlock_move`
finds the smallest move of a well-known joint that would make them readable.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from fusion.startup.kernels import lm_solve
from models.arm import ArmModel
from models.kinematics import gravity_chain
from models.rotations import DEG, skew, tilt_from_up, up_from_tilt, wrap_angle
from models.sensor_models import stream_models

FLAGS = ("ok", "ill_conditioned", "gimbal_lock", "ambiguous", "out_of_limits")


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
    fit_chi2: float = 9.0
    """A branch fits the data when its chi-square is within this of the best branch's."""
    prior_fit_p: float = 1e-3
    """A checked prior (saved pose, encoder carry) fits a branch unless the branch lies
    this improbably far from it (chi-square test over the joints both know)."""
    saved_pose_sigma_deg: float = 3.0
    """How far a joint may have settled since its pose was saved at a clean shutdown
    (1 sigma): brakes taking the load, gear play. A pose moved further is stale."""
    ill_grow_max_deg: float = 30.0
    """An ill-conditioned joint's sigma grows to cover a rival minimum up to this far away
    (one valley); a rival further away makes it ``ambiguous``."""
    numbered_sigma_max_deg: float = 45.0
    """A joint whose sigma would exceed this is not given a number: the data do not see it
    (its angle is null and its range the limits)."""
    encoder_carry_sigma_deg: float = 0.1
    """What the encoders add to a pose they carry from one still window to the next (1
    sigma): they count the motor, and the gears between it and the link have play."""
    separation_chi2: float = 100.0
    """A disambiguating move must make every pair of rival branches predict readings this
    far apart (chi-square over the sensors' noise: 10 sigma)."""


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
    range_rad: tuple[float, float] | None = None
    """Where a joint with no number may be: its limits (the data do not narrow it)."""

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "angle_rad": self.angle_rad,
            "sigma_rad": self.sigma_rad,
            "flag": self.flag,
            "alternatives_rad": list(self.alternatives_rad),
            "range_rad": None if self.range_rad is None else list(self.range_rad),
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
class DisambiguatingMove:
    """A small, safe move after which branches that fit the still data equally well predict
    readings far apart: after it and a second still window, the encoders (which counted
    the move) carry each branch forward and only the true one fits."""

    joints: tuple[str, ...]
    delta_rad: tuple[float, ...]
    separation_sigma: float
    """The closest any two rival branches then come, in the sensors' noise (sqrt chi-square)."""
    resolves: tuple[str, ...]

    def as_dict(self) -> dict:
        return {"moves": [{"joint": j, "delta_rad": d}
                          for j, d in zip(self.joints, self.delta_rad, strict=True)],
                "separation_sigma": self.separation_sigma, "resolves": list(self.resolves)}

    def describe(self) -> str:
        moves = " and ".join(f"{j} by {np.degrees(d):+.1f} deg"
                             for j, d in zip(self.joints, self.delta_rad, strict=True))
        return (f"move {moves} (every candidate stays inside the limits), hold still, and "
                f"calibrate again: the candidates of {', '.join(self.resolves)} then read "
                f"{self.separation_sigma:.0f} sigma apart")


@dataclass(frozen=True)
class StartupPrior:
    """What is known of the pose before a still window, and how far it may be used.

    ``kind``:

    - ``"checked"``: candidate poses (the pose saved at the last clean shutdown, or an
      earlier window's answers carried through the encoder counts). They choose between
      branches only where a branch that fits the data lies within their sigma (a chi-square
      test over the joints both know); when none does, the prior is ignored and the result
      says so. Relative encoders lose their count with the power, and a person may move the
      arm by hand: a saved pose is a claim to check, not evidence.
    - ``"assumed"``: the caller asserts where the arm stands (``--assume-parked``): the pose
      picks among the branches as a Gaussian prior, and the result says it rests on that.

    ``sigma_rad`` is per joint; ``inf`` where the prior knows nothing of a joint.
    """

    candidates_rad: np.ndarray  # (C, n)
    sigma_rad: np.ndarray  # (n,)
    kind: str = "checked"
    source: str = "a saved pose"
    covariance_rad2: np.ndarray | None = None
    """(n, n), or (C, n, n) one per candidate: the candidates' covariance where it is known
    (an earlier window's answer: near a singular pair its joints are strongly correlated);
    default ``diag(sigma_rad**2)``."""

    def __post_init__(self):
        c = np.atleast_2d(np.asarray(self.candidates_rad, float))
        object.__setattr__(self, "candidates_rad", c)
        sig = np.broadcast_to(np.asarray(self.sigma_rad, float), (c.shape[1],)).copy()
        object.__setattr__(self, "sigma_rad", sig)
        known = np.isfinite(sig)
        cov = (np.diag(np.where(known, sig, 0.0) ** 2) if self.covariance_rad2 is None
               else np.array(self.covariance_rad2, float))
        cov[..., ~known, :] = 0.0
        cov[..., :, ~known] = 0.0
        object.__setattr__(self, "covariance_rad2", np.where(np.isfinite(cov), cov, 0.0))
        if self.kind not in ("checked", "assumed"):
            raise ValueError(f"prior kind must be 'checked' or 'assumed', not {self.kind!r}")

    @classmethod
    def saved_pose(cls, q_rad: np.ndarray, sigma_deg: float = StartupSettings.saved_pose_sigma_deg,
                   source: str = "the saved pose") -> StartupPrior:
        return cls(np.asarray(q_rad, float)[None], np.full(len(q_rad), sigma_deg * DEG), "checked", source)

    @classmethod
    def assume_parked(cls, arm: ArmModel, sigma_deg: float = StartupSettings.prior_sigma_deg) -> StartupPrior:
        return cls(arm.ready_pose_rad[None], np.full(arm.n_joints, sigma_deg * DEG), "assumed",
                   "the arm assumed parked at its ready pose")


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
    candidates_rad: np.ndarray | None = None
    """(R, n): every branch the result cannot rule out, the reported one first."""
    candidates_covariance: np.ndarray | None = None
    """(R, n + 2, n + 2): each candidate's covariance (the first is ``covariance``)."""
    prior_used: str = "none"
    """What chose the branch: "none" (the data alone), or the prior's source."""
    notes: tuple[str, ...] = ()
    disambiguating_move: DisambiguatingMove | None = None

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
            "disambiguating_move": (None if self.disambiguating_move is None
                                    else self.disambiguating_move.as_dict()),
            "prior": self.prior_used,
            "summary": self.summary,
            "notes": list(self.notes),
        }


class StartupInputError(ValueError):
    """The readings cannot give joint angles (NaN, saturated, dead sensor...)."""


# --------------------------------------------------------------------------------------
# geometry helpers
def up_tilt_jacobian(roll, pitch) -> np.ndarray:
    """``d up / d (roll, pitch)``: ``(..., 3, 2)``."""
    r, p = np.asarray(roll, float), np.asarray(pitch, float)
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    z = np.zeros_like(r)
    d_r = np.stack([z, cr * cp, -sr * cp], -1)
    d_p = np.stack([-cp, -sr * sp, -cr * sp], -1)
    return np.stack([d_r, d_p], -1)


def _subproblem1(w: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Angle about unit axis ``w`` taking direction ``p`` closest to ``q``, for rows of
    directions ``p``, ``q`` (``(P, 3)``, or one ``(3,)`` for all): ``(P,)``."""
    pp = p - (p @ w)[..., None] * w
    qq = q - (q @ w)[..., None] * w
    # w . (pp x qq) = pp . (qq x w); for rows u, u @ skew(w) == cross(u, w)
    return np.arctan2((pp * (qq @ skew(w))).sum(-1), (pp * qq).sum(-1))


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
    cr = skew(w1) @ w2
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
            # the same, as the compiled kernels take it (fusion.startup.kernels)
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
        """The chain and the rows of one kind of solve as :mod:`fusion.startup.kernels` takes
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
    """Levenberg-Marquardt on every start, compiled (:func:`fusion.startup.kernels.lm_solve`):
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
    moved = np.abs(wrap_angle(x[:, :n] - xb[:n])) * allowed[:, None]
    moved[np.arange(len(j_of)), j_of] = 0.0
    return np.stack([moved[j_of == j].max(0) for j in np.unique(j_of)])


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
    return mid + wrap_angle(q - mid)


def _joint_turn_parts(arm: ArmModel) -> np.ndarray:
    """Per joint, the three constant parts of the rotation of frame j+1 in frame j:
    ``R(t) = P0 + sin t P1 + (1 - cos t) P2`` (Rodrigues between ``R_pre`` and ``R_post``):
    ``(n, 3, 3, 3)``, built once per arm."""
    parts = arm.__dict__.get("_startup_turn_parts")
    if parts is None:
        ch = arm.chain
        parts = np.empty((arm.n_joints, 3, 3, 3))
        for j in range(arm.n_joints):
            K = skew(ch.axis[j])
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
    close = (np.abs(wrap_angle(q[:, None] - q[None])).max(-1) < tol).tolist()  # (B, B)
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
    prior: StartupPrior | None = None,
    method: str = "joint",
    propose_unlock: bool = True,
) -> StartupResult:
    """Every joint angle of a still arm from averaged readings, with sigma and flags.

    With no ``prior`` the data alone decide: every branch that fits them and lies inside the
    limits is a rival, and the joints on which rivals differ are ``ambiguous`` (every
    candidate listed, a move that would separate them proposed). The ready pose is then only
    a start for the search. A ``prior`` (:class:`StartupPrior`) chooses between branches
    as its kind says; it never pulls a value.
    """
    st = settings or StartupSettings()
    check_readings(readings)
    problem = _make_problem(arm, readings)
    n = arm.n_joints
    # base tilt from the IMU (the thesis's eq. 4.1, in the recording spec's convention)
    if problem.imu_meas is not None:
        roll0, pitch0 = (float(a) for a in tilt_from_up(problem.R_0I @ problem.imu_meas))
    else:
        roll0 = pitch0 = 0.0
    starts = _closed_form_branches(problem, roll0, pitch0)
    if method == "joint":
        # Near a singular pair the closed-form starts are noisy and LM from them can slide
        # into a neighbouring branch: start at the ready pose and the prior's poses too
        # (starts only: where the search begins is no evidence).
        extra = [arm.ready_pose_rad[None]]
        if prior is not None:
            extra.append(np.where(np.isfinite(prior.sigma_rad), prior.candidates_rad, arm.ready_pose_rad))
        starts = np.vstack([starts, *extra])
    x0 = np.concatenate([starts, np.tile([roll0, pitch0], (len(starts), 1))], 1)
    free = np.ones(n + 2, dtype=bool)
    if method == "joint":
        x, cost = _batched_lm(problem, x0, free, st.max_iterations)
    elif method == "sequential":
        x, cost = _sequential(problem, x0, st)
    else:
        raise ValueError(f"unknown method {method!r}: use 'joint' or 'sequential'")
    mid = (arm.min_rad + arm.max_rad) / 2
    x[:, :n] = mid + wrap_angle(x[:, :n] - mid)
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
        xc[:, :n] = mid + wrap_angle(xc[:, :n] - mid)
        x, cost = np.vstack([x, xc]), np.concatenate([cost, cost_c])
    if method == "joint":
        x, cost = _complete_combinations(problem, x, cost, st, mid)
    # drop branches that fit much worse than the best (not solutions of the data)
    good = cost <= cost.min() + 0.5 * st.fit_chi2 + 1e-9
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
    else:  # no branch inside the limits: the ones least outside (flagged out_of_limits below)
        excess = np.sum(np.maximum(0, np.maximum(arm.min_rad - q_all, q_all - arm.max_rad))
                        * ~locked_any, 1)
        cand = np.flatnonzero(excess <= excess.min() + DEG)
    n_dir = len(problem.names) + 1  # the IMU's direction, or the level-chair prior
    dof = max(2 * n_dir - int(free.sum()), 1)
    inflate0 = max(2.0 * float(cost[cand].min()) / dof, 1.0)
    # which branches may be the arm's: the data's (every feasible one), or the prior's choice
    notes: list[str] = []
    chooser = _BranchChooser.make(prior, st, q_all[cand], locked_any[cand],
                                  _expected_covariance(problem, x[cand])[:, :n, :n] * inflate0, notes)
    pool = cand[chooser.keep]
    best = pool[int(np.argmin(chooser.rank[chooser.keep]))]
    xb = x[best]
    qb = xb[:n]
    # covariance from the weighted Jacobian at the chosen solution
    r, J = problem.residuals_and_jacobian(xb[None])
    r, J = r[0], J[0]
    # a normalised direction carries two constraints, not three; the tilt prior two more
    chi2_dof = float(r @ r / dof)
    locked = locked_any[best]
    # Information from the data, plus the only thing known about a gravity-blind joint: it
    # is somewhere in its range (a flat prior of width pi). Every joint gets that flat
    # prior: it costs nothing where the data speak, and where they do not (a singular pair:
    # two axes and gravity coplanar) the sigma becomes honestly large instead of being cut
    # off by a pseudo-inverse. The marginal sigma of every joint carries its correlation
    # with the blind ones.
    cols = free.copy()
    Jr = J[:, cols]
    info = Jr.T @ Jr
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
    rivals_x = x[pool]
    if len(probes):
        xr[:, :n] = mid + wrap_angle(xr[:, :n] - mid)
        keep = ((cost_r <= cost[cand].min() + 0.5 * st.fit_chi2 + 1e-9)
                & (arm.within_limits(xr[:, :n], margin) | locked_any[best]).all(1))
        if keep.any():
            xr = _dedupe(xr[keep], 1e-3)
            joins = chooser.admits(xr[:, :n], np.broadcast_to(locked, (len(xr), n)),
                                   _expected_covariance(problem, xr)[:, :n, :n] * inflate)
            rivals_x = np.vstack([rivals_x, xr[joins]])
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
    # every rival the chooser kept against the chosen one: a joint on which they differ by
    # more than its sigma can cover is ambiguous (an ill-conditioned joint's sigma grows to
    # cover a rival in the same valley instead)
    rivals_x = _dedupe_x(rivals_x, xb)
    alternatives: list[list[float]] = [[] for _ in range(n)]
    kept = [xb]
    for other in rivals_x[1:]:
        gap = np.abs(wrap_angle(other[:n] - qb))
        differ = (gap > np.maximum(3 * sig[:n], 1e-3)) & (flags != "gimbal_lock")
        if not differ.any():
            continue
        # a rival in the same valley (every angle close by) widens the sigmas of the joints
        # that differ, which makes them ill-conditioned; another branch (some angle far off)
        # makes every joint that differs ambiguous
        same_valley = np.all(gap[differ] <= st.ill_grow_max_deg * DEG)
        grow = differ & same_valley
        # one rival per distinct set of readable angles (a locked joint's value is arbitrary),
        # and only one that makes a joint ambiguous (a weak joint's sigma covers the rest)
        if (differ & ~grow).any() and not any(
                np.all((np.abs(wrap_angle(other[:n] - k[:n])) <= np.maximum(3 * sig[:n], 1e-3))
                       | (flags == "gimbal_lock")) for k in kept[1:]):
            kept.append(other)
        for j in np.flatnonzero(grow):
            scale = max(gap[j] / 2.0 / sig[j], 1.0)
            sig[j] *= scale
            cov[j, :] *= scale
            cov[:, j] *= scale
            if flags[j] == "ok" and sig[j] > limit:
                flags[j] = "ill_conditioned"
        for j in np.flatnonzero(differ & ~grow):
            flags[j] = "ambiguous"
            if not alternatives[j]:
                alternatives[j].append(float(qb[j]))
            if all(abs(wrap_angle(other[j] - v)) > 1e-3 for v in alternatives[j]):
                alternatives[j].append(float(other[j]))
    # a joint the data cannot see gets no number (never a sigma of thousands of degrees)
    blind = (sig[:n] > st.numbered_sigma_max_deg * DEG) & ~np.isin(flags, ("gimbal_lock", "ambiguous"))
    flags[blind] = "ill_conditioned"
    thesis = thesis_detector(arm, problem.names, problem.meas, st.thesis_detector_g)
    joints = []
    for j in range(n):
        number = flags[j] not in ("gimbal_lock", "ambiguous") and not blind[j]
        joints.append(JointEstimate(
            name=arm.joints[j].name,
            angle_rad=float(qb[j]) if number else None,
            sigma_rad=float(sig[j]) if number and np.isfinite(sig[j]) else None,
            flag=str(flags[j]),
            alternatives_rad=tuple(alternatives[j]),
            axis_to_vertical_deg=float(axis_deg[best, j]),
            thesis_detector_locked=thesis[j],
            range_rad=None if number or flags[j] == "ambiguous"
            else (float(arm.min_rad[j]), float(arm.max_rad[j])),
        ))
    resid_g = (r[: problem.meas.size] * problem.sigma.reshape(-1))
    # the covariance keeps the linear correlations, scaled to the sigmas the checks arrived
    # at (the profile, the sweep and the rivals widen them), every joint's included
    lin = np.sqrt(np.clip(np.diag(cov), 1e-30, None)) * st.sigma_safety_factor
    widen = np.where(np.isfinite(sig), np.maximum(sig / lin, 1.0), 1.0)
    cov = cov * np.outer(widen, widen)
    result = StartupResult(
        joints=tuple(joints),
        roll_rad=float(xb[n]), pitch_rad=float(xb[n + 1]),
        roll_sigma_rad=float(sig[n]), pitch_sigma_rad=float(sig[n + 1]),
        residual_rms_g=float(np.sqrt(np.mean(resid_g**2))),
        chi2_per_dof=chi2_dof,
        q_rad=qb.copy(), covariance=cov * st.sigma_safety_factor**2, branches_rad=branches,
        method=method,
        t_start_s=readings.t_start_s, t_end_s=readings.t_end_s,
        candidates_rad=np.array([k[:n] for k in kept]),
        candidates_covariance=_candidate_covariances(problem, kept, cov * st.sigma_safety_factor**2,
                                                     inflate * st.sigma_safety_factor**2),
        prior_used=chooser.used,
        notes=tuple(notes),
    )
    if propose_unlock and any(f in ("gimbal_lock", "ill_conditioned") for f in flags):
        result = replace(result, unlock_move=propose_unlock_move(arm, result, readings, st))
    if len(kept) > 1:
        result = replace(result, disambiguating_move=propose_disambiguating_move(
            arm, result, readings, st, roll_pitch=xb[n:]))
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


def _joint_groups(arm: ArmModel, names: list[str]) -> list[np.ndarray]:
    """The joints between one accelerometer and the next along the chain: each group's
    angles are fixed (up to its own branches) by the direction of up at its two ends."""
    links = sorted({arm.sensor(nm).link for nm in names})
    edges = [0, *links]
    groups = [np.arange(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]
    if edges[-1] < arm.n_joints:
        groups.append(np.arange(edges[-1], arm.n_joints))
    return groups


def _complete_combinations(problem: _Problem, x: np.ndarray, cost: np.ndarray,
                           st: StartupSettings, mid: np.ndarray, most: int = 64):
    """Every combination of the groups' solutions, polished. Each group's branches are
    independent of the others' (the twins of a pair leave up the same in the frame after
    them), but near a singular pair the polish from one closed-form start can slide into its
    neighbour's minimum, and a combination goes missing; the true pose may be the one. The
    fitting branches' group values are crossed, and the new combinations solved too."""
    n = problem.n
    good = cost <= cost.min() + 0.5 * st.fit_chi2 + 1e-9
    if good.sum() < 2:
        return x, cost
    q = x[good, :n]
    values = []
    for g in _joint_groups(problem.arm, problem.names):
        v = _dedupe(q[:, g], 0.5 * DEG)
        values.append((g, v))
    total = int(np.prod([len(v) for _, v in values]))
    if total <= 1 or total > most:
        return x, cost
    combos = np.repeat(x[good][:1], total, 0)
    idx = np.indices([len(v) for _, v in values]).reshape(len(values), -1).T  # (total, groups)
    for gi, (g, v) in enumerate(values):
        combos[:, g] = v[idx[:, gi]]
    have = np.abs(wrap_angle(combos[:, None, :n] - q[None])).max(-1).min(1) < 0.5 * DEG
    if have.all():
        return x, cost
    new, new_cost = _batched_lm(problem, combos[~have], np.ones(n + 2, bool), st.max_iterations)
    new[:, :n] = mid + wrap_angle(new[:, :n] - mid)
    return np.vstack([x, new]), np.concatenate([cost, new_cost])


def _candidate_covariances(problem: _Problem, kept: list[np.ndarray], cov_best: np.ndarray,
                           scale: float) -> np.ndarray:
    """Each candidate's covariance: the chosen one's as the checks left it; a rival's from
    its own Jacobian, its sigmas no smaller than the chosen one's (the profile and the sweep
    widened those; a rival's linear sigmas know nothing of its valley)."""
    out = [cov_best]
    if len(kept) > 1:
        rivals = _expected_covariance(problem, np.array(kept[1:])) * scale
        floor = np.sqrt(np.clip(np.diag(cov_best), 0, None))
        for c in rivals:
            lin = np.sqrt(np.clip(np.diag(c), 1e-30, None))
            w = np.maximum(np.where(np.isfinite(floor), floor, 0.0) / lin, 1.0)
            out.append(c * np.outer(w, w))
    return np.array(out)


def _dedupe_x(rivals_x: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """The chosen state first, then every other rival once."""
    return _dedupe(np.vstack([xb[None], rivals_x]), 1e-3) if len(rivals_x) else xb[None]


@dataclass
class _BranchChooser:
    """Which of the fitting branches the result may not rule out, and which to report.

    ``keep`` (B,): the branches in the pool; ``rank`` (B,): lower is reported first;
    ``admits``: whether a further minimum found later joins the pool; ``used``: what chose.
    """

    keep: np.ndarray
    rank: np.ndarray
    used: str
    prior: StartupPrior | None
    threshold: float
    settings: StartupSettings

    @classmethod
    def make(cls, prior: StartupPrior | None, st: StartupSettings, q: np.ndarray,
             locked: np.ndarray, cov: np.ndarray, notes: list[str]) -> _BranchChooser:
        B = len(q)
        by_cost = np.arange(B, dtype=float)  # q comes ordered by cost
        if prior is None:
            return cls(np.ones(B, bool), by_cost, "none", None, np.inf, st)
        if prior.kind == "assumed":
            d2 = _prior_d2(prior, q, locked, np.zeros_like(cov))
            notes.append(f"the branch rests on an assumption: {prior.source} (--assume-parked); "
                         f"without it every branch that fits would be reported")
            return cls(d2 - d2.min() < st.prior_decisive_chi2, d2, prior.source, prior,
                       float(d2.min() + st.prior_decisive_chi2), st)
        d2, k = _prior_d2(prior, q, locked, cov, with_dof=True)
        thr = _chi2_quantile(k, st.prior_fit_p)
        fits = d2 <= thr
        if not fits.any():
            i = int(np.argmin(d2 / np.maximum(thr, 1e-9)))
            notes.append(f"{prior.source} does not fit the still data (chi-square {d2[i]:.0f} "
                         f"over {int(k[i])} joints at the nearest branch, above {thr[i]:.0f}): "
                         f"ignored; the arm was moved since, or its count lost")
            return cls(np.ones(B, bool), by_cost, "none", None, np.inf, st)
        # it fits: it chooses, as evidence, among the branches that agree with it (those it
        # does not prefer by a chi-square of prior_decisive_chi2 stay rivals)
        best = float(d2[fits].min())
        keep = fits & (d2 - best < st.prior_decisive_chi2)
        notes.append(f"{prior.source} fits the still data (chi-square {best:.1f} over "
                     f"{int(k[fits].max())} joints); it chose among {B} fitting branch"
                     f"{'es' if B != 1 else ''}")
        return cls(keep, d2, prior.source, prior, best + st.prior_decisive_chi2, st)

    def admits(self, q: np.ndarray, locked: np.ndarray, cov: np.ndarray) -> np.ndarray:
        if self.prior is None:
            return np.ones(len(q), bool)
        if self.prior.kind == "assumed":
            return _prior_d2(self.prior, q, locked, np.zeros_like(cov)) < self.threshold
        d2, k = _prior_d2(self.prior, q, locked, cov, with_dof=True)
        return (d2 <= _chi2_quantile(k, self.settings.prior_fit_p)) & (d2 < self.threshold)


def _prior_d2(prior: StartupPrior, q: np.ndarray, locked: np.ndarray, cov: np.ndarray,
              with_dof: bool = False):
    """Per branch ``q (B, n)``: the chi-square of its nearest prior candidate over the joints
    both know (readable in the branch, known to the prior), with the branch's own covariance
    ``cov (B, n, n)`` added to the prior's (full matrices: along a valley the joints move
    together, and a rival that is many sigmas away as a whole may be within each joint's
    own sigma); and the number of those joints."""
    known = ~locked & np.isfinite(prior.sigma_rad)  # (B, n)
    C = len(prior.candidates_rad)
    Cp = np.broadcast_to(prior.covariance_rad2, (C, *prior.covariance_rad2.shape[-2:]))
    S = cov[:, None] + Cp[None]  # (B, C, n, n)
    both = (known[:, :, None] & known[:, None, :])[:, None]
    S = np.where(both, S, 0.0) + np.eye(q.shape[1]) * np.where(known, 0.0, 1.0)[:, None, None]
    dq = wrap_angle(q[:, None, :] - prior.candidates_rad[None]) * known[:, None]  # (B, C, n)
    w = np.linalg.solve(S, dq[..., None])[..., 0]
    d2 = np.sum(dq * w, -1).min(1)
    return (d2, known.sum(1)) if with_dof else d2


def _chi2_quantile(k, p: float) -> np.ndarray:
    """The chi-square value exceeded with probability ``p`` at ``k`` degrees of freedom."""
    from scipy.special import chdtri

    k = np.maximum(np.asarray(k, float), 1.0)
    return chdtri(k, p)


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


def move_delta_rad(move: UnlockMove | DisambiguatingMove, arm: ArmModel) -> np.ndarray:
    """What a proposed move changes, every joint: ``(n,)`` rad (zero for the joints it keeps)."""
    delta = np.zeros(arm.n_joints)
    for name, d in zip(move.joints, move.delta_rad, strict=True):
        delta[arm.joint_names.index(name)] += d
    return delta


def prior_after_move(result: StartupResult, move, arm: ArmModel,
                     settings: StartupSettings | None = None) -> StartupPrior:
    """The prior for the still window after a move that the encoders counted: every
    candidate pose of ``result`` (its rivals too, when some joints were ambiguous) moved by
    the move, each joint with the result's sigma and the encoders' own (a joint the result
    could not read: unknown). ``move``: an :class:`UnlockMove`, a
    :class:`DisambiguatingMove`, or the encoder-counted change of every joint ``(n,)`` rad.
    It is a checked prior: if the arm was moved otherwise, it does not fit and is ignored."""
    st = settings or StartupSettings()
    n = arm.n_joints
    delta = (move_delta_rad(move, arm) if isinstance(move, UnlockMove | DisambiguatingMove)
             else np.asarray(move, float).reshape(n))
    cands = (result.candidates_rad if result.candidates_rad is not None else result.q_rad[None]) + delta
    stat = np.sqrt(np.clip(np.diag(result.covariance)[:n], 0, None))
    sig = np.full(n, np.inf)
    for j, je in enumerate(result.joints):
        if je.sigma_rad is not None:
            sig[j] = je.sigma_rad
        elif je.flag == "ambiguous" and np.isfinite(stat[j]):
            sig[j] = stat[j]  # each candidate is a minimum known to the branch's own sigma
    # the result's correlations, scaled to the sigmas it reports (the profile and the
    # sweep widen a sigma beyond the linear one), plus what the encoders add
    enc_var = (st.encoder_carry_sigma_deg * DEG) ** 2
    if result.candidates_covariance is not None:  # each candidate's own (a valley's shape)
        cov = np.array(result.candidates_covariance, float)[:, :n, :n] + np.eye(n) * enc_var
    else:
        cov = np.array(result.covariance, float)[:n, :n] + np.eye(n) * enc_var
    sig = np.sqrt(sig**2 + enc_var)
    return StartupPrior(cands, sig, "checked", covariance_rad2=cov, source=(
        f"the still window at t = {result.t_start_s:.1f}..{result.t_end_s:.1f} s carried "
        "through the encoder counts"))


def propose_disambiguating_move(arm: ArmModel, result: StartupResult, readings: StillReadings,
                                settings: StartupSettings | None = None,
                                roll_pitch: np.ndarray | None = None,
                                max_move_deg: float = 45.0) -> DisambiguatingMove | None:
    """The smallest safe move after which every pair of rival branches predicts readings
    ``settings.separation_chi2`` apart.

    The encoders count the move, so each rival moves by the same joint deltas. Joints the
    data know (``ok``) are tried first, one at a time, then pairs, then moves of the
    ambiguous joints themselves; a move counts only if every rival stays inside the limits
    (the arm is on one of them), which are the checks of the unlock move. All candidate
    moves of one size class are evaluated in one batch.
    """
    st = settings or StartupSettings()
    cands = result.candidates_rad
    if cands is None or len(cands) < 2:
        return None
    n = arm.n_joints
    problem = _make_problem(arm, readings)
    rp = np.array([result.roll_rad, result.pitch_rad]) if roll_pitch is None else np.asarray(roll_pitch)
    flags = [j.flag for j in result.joints]
    known = [j for j in range(n) if flags[j] == "ok"]
    # joints the data read but not to a number: ambiguous or weak ones, and those flagged
    # only for resting on a locked joint (their own axis is clear of vertical); a move of
    # one of them keeps a margin inside its limits, at every candidate
    unsure = [j for j in range(n) if flags[j] in ("ambiguous", "ill_conditioned", "out_of_limits")
              or (flags[j] == "gimbal_lock" and result.joints[j].axis_to_vertical_deg
                  >= 2 * st.gimbal_lock_deg)]
    resolves = tuple(j.name for j in result.joints if j.flag == "ambiguous")
    amb = np.array([j.flag == "ambiguous" for j in result.joints])
    steps = np.array([2, 3, 5, 7.5, 10, 15, 20, 30, 45], float)
    steps = steps[steps <= max_move_deg] * DEG
    pair_steps = np.array([5, 10, 15, 20, 30], float) * DEG

    def singles(js):
        return [((j, sg * d),) for d in steps for j in js for sg in (1, -1)]

    # the pairs' step sizes, smallest total first (a stable sort keeps joint order within)
    sizes = sorted(((dj, dk) for dj in pair_steps for dk in pair_steps), key=lambda p: p[0] + p[1])

    def pairs(js):
        return [((j, sj * dj), (k, sk * dk)) for dj, dk in sizes for j in js for k in js if j < k
                for sj in (1, -1) for sk in (1, -1)]

    R = len(cands)
    ia, ib = np.triu_indices(R, 1)
    # what the next window knows of each rival: this window's covariance (as the encoders
    # carry it), the joints it could not read anywhere in their turn
    carried = np.array(result.covariance, float)
    bad = ~np.isfinite(np.diag(carried))
    carried[bad, :] = carried[:, bad] = 0.0
    carried[bad, bad] = np.pi**2
    # (the result's covariance is already scaled to the sigmas its checks arrived at)
    carried[np.diag_indices(n)] += (st.encoder_carry_sigma_deg * DEG) ** 2
    # After the move every joint should be readable, whichever rival is true (a joint still
    # weak leaves the next window with rivals of its own); failing that, at least the joints
    # to resolve. Moves are tried smallest first, class by class; within the class where a
    # move does the second, one that does the first is preferred.
    fallback = None
    for make in (lambda: singles(known), lambda: pairs(known), lambda: singles(unsure),
                 lambda: pairs(known + unsure)):
        moves = make()  # built only when the smaller classes found nothing
        for i in range(0, len(moves), 64):
            found = _separating(arm, problem, cands, rp, moves[i:i + 64], amb, ia, ib, st,
                                np.isin(np.arange(n), unsure), carried)
            if found is None:
                continue
            m, sep, every = found
            if every:
                fallback = (m, sep)
                break
            fallback = fallback or (m, sep)
        if fallback is not None:
            m, sep = fallback
            return DisambiguatingMove(
                joints=tuple(arm.joints[j].name for j, _ in m),
                delta_rad=tuple(float(d) for _, d in m),
                separation_sigma=float(np.sqrt(sep)), resolves=resolves)
    return None


def _separating(arm, problem, cands, rp, chunk, amb, ia, ib, st, unsure, carried,
                unsure_margin_deg=5.0):
    """The first move of ``chunk`` (ordered by size) that keeps every rival inside the
    limits, leaves the ``amb`` joints readable (axis off vertical, expected sigma within half
    the limit, at every rival), and separates every pair of rivals by ``st.separation_chi2``:
    ``(move, chi-square, every joint readable too)``, preferring the last; or None."""
    n, R = arm.n_joints, len(cands)
    delta = np.zeros((len(chunk), n))
    for c, m in enumerate(chunk):
        for j, d in m:
            delta[c, j] += d
    moved = cands[None] + delta[:, None]  # (M, R, n)
    margin = np.where((delta != 0) & unsure, unsure_margin_deg * DEG, 0.0)[:, None]  # (M, 1, n)
    # only the moved joints can leave their limits (a joint that stays is where the arm is)
    inside = (((moved >= arm.min_rad + margin) & (moved <= arm.max_rad - margin))
              | (delta == 0)[:, None]).all((1, 2))
    if not inside.any():
        return None
    x = np.concatenate([moved.reshape(-1, n), np.tile(rp, (len(chunk) * R, 1))], 1)
    axis = np.degrees(_axis_to_vertical(arm, x[:, :n], x[:, n], x[:, n + 1]))
    clear = (axis >= 2 * st.gimbal_lock_deg).reshape(len(chunk), R, n).all(1)  # (M, n)
    pred, J = problem.residuals_and_jacobian(x)  # residuals: (prediction - reading) / sigma
    # How far apart two rivals then read, in the noise, when each may be anywhere its
    # carried uncertainty allows (linearised: d' (I + J C J')^-1 d): a weak joint can
    # absorb part of the difference, and a separation it can absorb resolves nothing.
    m = pred.shape[1]
    pred = pred.reshape(len(chunk), R, m)
    d = pred[:, ia] - pred[:, ib]  # (M, P, m)
    sep = np.full(len(chunk), -np.inf)
    # (I + J C J')^-1 only lowers d'd: moves that fail on d'd alone need no more
    go = np.flatnonzero(inside & clear[:, amb].all(1)
                        & (np.einsum("kpi,kpi->kp", d, d).min(1) >= st.separation_chi2))
    if len(go):
        Ja = J.reshape(len(chunk), R, m, -1)[go][:, ia]  # (G, P, m, p)
        S = np.eye(m) + Ja @ carried @ np.swapaxes(Ja, -1, -2)
        dg = d[go]
        sep[go] = np.einsum("kpi,kpi->kp", dg, np.linalg.solve(S, dg[..., None])[..., 0]).min(1)
    good = inside & clear[:, amb].all(1) & (sep >= st.separation_chi2)
    if not good.any():
        return None
    # expected sigmas (the solve's noise model, its flat prior and safety factor), for the
    # moves still in the running only
    idx = np.flatnonzero(good)
    Jg = J.reshape(len(chunk), R, *J.shape[1:])[idx].reshape(-1, *J.shape[1:])
    info = np.einsum("bmi,bmj->bij", Jg, Jg) + np.eye(J.shape[-1]) / np.pi**2
    sig = np.sqrt(np.clip(np.einsum("bii->bi", np.linalg.inv(info)), 0, None))[:, :n]
    sig = (sig * st.sigma_safety_factor).reshape(len(idx), R, n).max(1)  # (G, n): worst rival
    readable = clear[idx] & (sig <= 0.5 * st.sigma_limit_deg * DEG)
    # the joints to resolve need not be sharp (a floor of unmodelled error may forbid it), but
    # their rivals must stand 6 of their sigmas apart for the next window to choose
    gap = np.abs(wrap_angle(cands[ia] - cands[ib]))  # (pairs, n)
    gap = np.where(gap > 1e-3, gap, np.inf).min(0)  # the closest two distinct values, per joint
    ok = (clear[idx] & (6 * sig <= gap))[:, amb].all(1)
    if not ok.any():
        return None
    every = ok & readable.all(1)
    c = int(idx[np.flatnonzero(every)[0]] if every.any() else idx[np.flatnonzero(ok)[0]])
    return chunk[c], float(sep[c]), bool(every.any())


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


def _expected_covariance(problem: _Problem, x: np.ndarray) -> np.ndarray:
    """Covariance of every unknown at states ``x (B, n+2)`` from the Jacobian alone (with the
    solve's flat prior): ``(B, n+2, n+2)``."""
    _, J = problem.residuals_and_jacobian(x)
    A = np.einsum("bmi,bmj->bij", J, J) + np.eye(J.shape[-1]) / np.pi**2  # as in the solve
    return np.linalg.inv(A)


def _expected_sigma(problem: _Problem, x: np.ndarray) -> np.ndarray:
    """Sigma of every unknown at states ``x (B, n+2)`` from the Jacobian alone."""
    return np.sqrt(np.clip(np.einsum("bii->bi", _expected_covariance(problem, x)), 0, None))


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
    if res.disambiguating_move is not None:
        text += "; to tell the branches apart: " + res.disambiguating_move.describe()
    elif any(j.flag == "ambiguous" for j in res.joints):
        text += "; no safe move of up to 45 deg separates the branches: a person must confirm the pose"
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
