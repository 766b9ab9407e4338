"""The planned self-calibration maneuver (``armfusion plan-maneuver``): which still poses,
held how long and joined by which moves, make the identification's parameters best known in
the time given, and how well they will be known after it.

Nothing here moves the arm: the plan is a :class:`~armfusion.models.trajectories.planned.PlannedManeuver`
for the arm's controller (or the simulator) to play.

* **Information.** A still pose held ``T`` seconds gives the fit ``T·rate/window`` window
  means; their information is ``JᵀWJ`` per window, ``J`` the fit's own Jacobian
  (:class:`~armfusion.fusion.identification.problem.FitProblem`: the model's effects, the encoder
  zeros and scales, the base attitude) at the priors. In prior-σ units the fit's
  information is ``A = I + D H D`` (``D``: the prior σ).
* **The gauges left out.** What no pose of the chair parked can tell (a sensor's mount about
  the last joint's axis against that joint's zero, the heading, the compass's hard iron,
  the time offsets and motion terms a still pose cannot see, …): the identifiability
  analysis of a pool of random poses sharing the whole duration holds them; the criterion is
  taken over the others only.
* **Greedy, sequential.** From the current pose, :attr:`PlanSettings.candidates` random moves
  that pass the unlock move's checks (:func:`armfusion.fusion.startup.moves.moves_within_limits`:
  inside the limits, at most 45° per joint), a peak joint rate and a tool speed for a person
  beside the arm (:attr:`PlanSettings.max_tool_speed_mps`); each scored by its gain in the
  criterion per second of its move and dwell, held each of :attr:`PlanSettings.dwell_choices_s`:
  D-optimal ``log det`` (by the determinant lemma, ``log det(I + w Jc A⁻¹ Jcᵀ)``),
  E-optimal (the smallest eigenvalue of ``A``) or ``startup`` (:func:`_startup_rows`: the
  joints' startup variances, linearised at random still poses, ``noise + gᵀA⁻¹g``; the sum
  of their logs, by Woodbury per candidate). The best pose and dwell are appended until the
  time is spent.
* **Predicted σ** (:func:`~armfusion.fusion.identification.prediction.predict_maneuver`, in
  :mod:`~armfusion.fusion.identification.prediction`, importable from here too): the maneuver
  played noise-free at the priors, turned into the fit's data as a recording would be, the
  identifiability analysis and the consider covariance of the fit; the startup's σ of each
  joint after it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from armfusion.fusion.configfile import read_yaml_of
from armfusion.fusion.identification.data import FitData, fit_streams
from armfusion.fusion.identification.identifiability import Hold, analyse_information
from armfusion.fusion.identification.prediction import (  # the prediction, importable from here too
    Prediction,
    predict_maneuver,
    predicted_identification,
    startup_sigmas,
)
from armfusion.fusion.identification.problem import FitProblem
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.startup.moves import MAX_MOVE_DEG, moves_within_limits
from armfusion.models.arm import ArmModel
from armfusion.models.effects import Model
from armfusion.models.effects.base import JointEffect, SensorEffect
from armfusion.models.effects.library import EncoderScale
from armfusion.models.kinematics import chain_poses
from armfusion.models.motion import MotionState
from armfusion.models.rotations import DEG
from armfusion.models.sensor_models import stream_models
from armfusion.models.trajectories.paths import min_jerk_progress
from armfusion.models.trajectories.planned import PlannedManeuver
from armfusion.models.trajectories.scenario import margin_limits

CRITERIA = ("D", "E", "startup")
FOCUS = ("all", "startup")
FILE_ROUNDING = 1e-3
"""A rate or speed may exceed its bound by this share: a maneuver file keeps 4 decimals of
its angles (degrees) and times (seconds)."""


@dataclass(frozen=True)
class PlanSettings:
    """What the planner may do (units in the names)."""

    duration_s: float = 60.0
    start_still_s: float = 5.0
    """The first pose (the ready pose) held still: the startup's still second that finds
    the recording's joint angles, as ``renk-maneuver``'s 5 s."""
    dwell_s: float = 2.0
    """Each later pose held still this long when ``dwell_choices_s`` is empty."""
    peak_rate_deg_s: float = 20.0
    """The fastest any joint moves (a minimum-jerk move peaks at 1.875× its mean rate);
    ``renk-maneuver``'s roll peaks at 21.8 °/s."""
    max_move_deg: float = MAX_MOVE_DEG
    """The largest move of one joint between two poses: the unlock move's."""
    max_tool_speed_mps: float = 0.25
    """The fastest any link's origin moves: 250 mm/s, ISO 10218-1's reduced speed for a
    robot working beside a person."""
    min_move_s: float = 1.0
    candidates: int = 192
    criterion: str = "D"
    focus: str = "all"
    """The elements the criterion counts (besides leaving the gauges out): ``all``, or
    ``startup``: those the startup calibration uses (each link accelerometer's and the IMU
    accelerometer's sensor stage, the joints' offsets, sag, play and encoder scales)."""
    seed: int = 0
    window: int = 25
    rate_hz: float = 100.0
    pool_poses: int = 400
    """Random poses whose shared information decides the gauges left out."""
    dwell_choices_s: tuple[float, ...] = ()
    """The dwells each candidate pose is scored with (the best gain per second of move and
    dwell wins); empty (the default): every later pose is held ``dwell_s``. With (1, 1.5, 2,
    3) a D-optimal 60 s plan on the WMRA holds 15 poses, most of them 1 s, instead of 13
    held 2 s (the start's 5 s counted), and its worst joint's predicted startup σ falls
    from 0.20° to 0.17°, but on
    seed 2's realistic arm its fit put the compass's elements (soft iron, the IMU's mount
    about z, the arm's steel) 4-11σ off, where the 2 s plan's were within 3σ: not the
    default until that is understood (``docs/maneuver-planning.md``, Limits)."""
    startup_poses: int = 16
    """``criterion="startup"``: the random still poses (chair tilted N(0, 3°)) the startup's
    σ is taken over."""
    startup_sigma_limit_deg: float = 0.5
    """``criterion="startup"``: a joint whose startup σ from the gauges alone exceeds this (the
    startup's own ``sigma_limit_deg``) will be flagged whatever the maneuver: left out."""

    def check(self) -> None:
        if self.focus not in FOCUS:
            raise ValueError(f"focus must be one of {', '.join(FOCUS)}, not {self.focus[:20]!r}")
        if self.criterion not in CRITERIA:
            raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, not {self.criterion[:20]!r}")
        for name in ("duration_s", "dwell_s", "peak_rate_deg_s", "max_move_deg", "max_tool_speed_mps",
                     "min_move_s", "rate_hz"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if self.duration_s > 3600:
            raise ValueError(f"duration_s: plan at most 3600 s, got {self.duration_s:g}")
        if self.duration_s < self.start_still_s + self.min_move_s + self.dwell_s:
            raise ValueError(f"duration_s: {self.duration_s:g} s leaves no time for a move after the "
                             f"{self.start_still_s:g} s still start; give at least "
                             f"{self.start_still_s + self.min_move_s + self.dwell_s:g} s")
        if not 1 <= self.candidates <= 4096 or not 10 <= self.pool_poses <= 20000:
            raise ValueError("candidates must be in 1..4096 and pool_poses in 10..20000")
        if not 1 <= self.startup_poses <= 256:
            raise ValueError(f"startup_poses must be in 1..256, not {self.startup_poses!r}")
        if len(self.dwell_choices_s) > 8 or not all(isinstance(d, int | float) and np.isfinite(d)
                                                     and 0.5 <= d <= 60 for d in self.dwell_choices_s):
            raise ValueError("dwell_choices_s: at most 8 dwells, each 0.5 to 60 s, got "
                             f"{str(tuple(self.dwell_choices_s))[:40]}")


@dataclass(frozen=True)
class Plan:
    """A planned maneuver, the criterion's columns and what it holds out as gauges."""

    maneuver: PlannedManeuver
    criterion: str
    names: tuple[str, ...]
    gauges: tuple[str, ...]
    """Elements the criterion leaves out: held by the identifiability analysis of the pool."""
    candidates_scored: int
    startup_joints: tuple[str, ...] = ()
    """``criterion="startup"``: the joints whose startup σ it counted (the others are a held
    gauge's partners: flagged after any parked maneuver)."""


def _tool_speed_mps(arm: ArmModel, q_from: np.ndarray, q_to: np.ndarray, move_s: np.ndarray,
                    points: int = 17) -> np.ndarray:
    """The fastest any link's origin moves during each minimum-jerk move ``(M,)``: positions at
    ``points`` instants of each move, differenced."""
    q_from = np.atleast_2d(q_from)
    q_to = np.atleast_2d(q_to)
    M, n = q_to.shape
    tau = np.linspace(0.0, 1.0, points)
    s = min_jerk_progress(tau)
    q = q_from[:, None] + (q_to - q_from)[:, None] * s[None, :, None]  # (M, points, n)
    p = chain_poses(arm, q.reshape(-1, n)).p_0L_m.reshape(M, points, -1, 3)
    dp = np.linalg.norm(np.diff(p, axis=1), axis=-1).max(axis=(1, 2))  # (M,)
    return dp / (np.asarray(move_s, float) / (points - 1))


def move_durations_s(settings: PlanSettings, q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
    """Each move's duration: its largest joint at the peak rate, at least ``min_move_s``."""
    d = np.abs(np.atleast_2d(q_to) - q_from)
    return np.maximum(settings.min_move_s, 1.875 * d.max(axis=1) / (settings.peak_rate_deg_s * DEG))


def maneuver_problems(arm: ArmModel, maneuver: PlannedManeuver, settings: PlanSettings | None = None,
                      limit: int = 10) -> list[str]:
    """What makes ``maneuver`` unsafe to play on ``arm`` (at most ``limit`` messages): a pose
    outside the joint limits, a move larger than the unlock move's (:func:`moves_within_limits`),
    a joint faster than ``peak_rate_deg_s`` or a link faster than ``max_tool_speed_mps``."""
    st = settings or PlanSettings()
    if tuple(maneuver.joint_names) != tuple(arm.joint_names):
        return [f"the maneuver's joints {list(maneuver.joint_names)[:10]} are not the arm's "
                f"{list(arm.joint_names)}"]
    out: list[str] = []
    Q = maneuver.poses_rad
    outside = (Q < arm.min_rad - 1e-9) | (Q > arm.max_rad + 1e-9)
    for k, j in zip(*np.nonzero(outside), strict=True):
        out.append(f"pose {k}: {arm.joint_names[j]} at {np.degrees(Q[k, j]):.1f}° is outside its limits "
                   f"[{np.degrees(arm.min_rad[j]):.0f}°, {np.degrees(arm.max_rad[j]):.0f}°]")
    if len(Q) > 1:
        ok = moves_within_limits(arm, Q[:-1], Q[1:], st.max_move_deg)
        for k in np.flatnonzero(~ok):
            d = np.degrees(np.abs(Q[k + 1] - Q[k]))
            j = int(np.argmax(d))
            out.append(f"move {k} -> {k + 1}: {arm.joint_names[j]} moves {d[j]:.1f}°, more than the "
                       f"unlock move's {st.max_move_deg:g}° (or leaves its limits)")
        T = maneuver.move_s
        rate = np.degrees(1.875 * np.abs(Q[1:] - Q[:-1]) / T[:, None])
        for k in np.flatnonzero(rate.max(1) > st.peak_rate_deg_s * (1 + FILE_ROUNDING)):
            j = int(np.argmax(rate[k]))
            out.append(f"move {k} -> {k + 1}: {arm.joint_names[j]} peaks at {rate[k, j]:.1f}°/s, over "
                       f"{st.peak_rate_deg_s:g}°/s")
        v = _tool_speed_mps(arm, Q[:-1], Q[1:], T)
        for k in np.flatnonzero(v > st.max_tool_speed_mps * (1 + FILE_ROUNDING)):
            out.append(f"move {k} -> {k + 1}: a link moves at {v[k]:.2f} m/s, over "
                       f"{st.max_tool_speed_mps:g} m/s (a person beside the arm)")
    return out[:limit]


def load_maneuver(path: str | Path) -> PlannedManeuver:
    """A maneuver file (``plan-maneuver --out``), its shape checked (``ValueError`` naming the key)."""
    p = Path(path)
    if not p.exists():  # (one that is there but not a file, /dev/zero or a FIFO: read_yaml says so)
        raise FileNotFoundError(f"maneuver file not found: {str(p)[:80]}")
    return PlannedManeuver.from_dict(read_yaml_of(p, "maneuver file"), p.name[:60])


def safe_maneuver(arm: ArmModel, path: str | Path) -> PlannedManeuver:
    """:func:`load_maneuver`, refused (``ValueError``, its first three problems named) unless
    it is safe to play on ``arm`` (:func:`maneuver_problems`)."""
    plan = load_maneuver(path)
    problems = maneuver_problems(arm, plan)
    if problems:
        raise ValueError(f"{Path(path).name[:60]}: not safe to play on {arm.name}: "
                         + "; ".join(problems[:3])
                         + (f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""))
    return plan


def _static_problem(model: Model, poses_rad: np.ndarray, settings: PlanSettings,
                    q_ref_rad: np.ndarray) -> FitProblem:
    """The fit's problem over still poses, one window each, the chair level (the readings are
    not needed: only the Jacobian is)."""
    arm = model.arm
    sm = stream_models(arm, settings.rate_hz)
    streams = [s for s in fit_streams(arm) if s in sm]
    N = len(poses_rad)
    counts = {s: np.zeros((N, np.size(sm[s].sigma_counts))) for s in streams}
    sig = {s: np.asarray(sm[s].sigma_counts, float) / np.sqrt(settings.window) for s in streams}
    data = FitData(MotionState.static(poses_rad, temperature_c=25.0), counts, sig,
                   np.asarray(q_ref_rad, float), settings.window)
    return FitProblem(model, data, streams, True, np.zeros(3), encoder_scale=True)


def _rows_per_pose(pb: FitProblem) -> np.ndarray:
    """The weighted Jacobian of each still pose, ``(N, rows, size)`` (one window each)."""
    _, J = pb.jacobian(pb.x0, np.arange(pb.size))
    N = pb.data.n
    out, o = [], 0
    for s in pb.streams:
        k = pb.data.counts[s].shape[1]
        out.append(J[o:o + N * k].reshape(N, k, -1))
        o += N * k
    return np.concatenate(out, axis=1)


def startup_elements(model: Model) -> set[str]:
    """The elements the startup calibration uses: the sensor stage of every accelerometer it
    reads (the link accelerometers and the IMU's), the joint stage and the encoder scales."""
    arm = model.arm
    streams = {s.name for s in arm.link_accelerometers} | {"imu_acc"}
    names = model.element_names()
    out = set()
    for e in model.effects:
        if (isinstance(e, JointEffect) or e.name == EncoderScale.name
                or (isinstance(e, SensorEffect) and streams & set(e.streams))):
            sl = model.index[e.block_name]
            out |= set(names[sl.start:sl.stop])
    return out


class _StartupRows(NamedTuple):
    """The startup's joint angles linearised (:func:`_startup_rows`): the rows ``G (R, cols)``
    in the criterion's prior units, each row's noise variance ``(R,)`` (rad²), each row's
    joint ``(R,)``, and the names of the joints counted."""

    G: np.ndarray
    noise: np.ndarray
    joint: np.ndarray
    counted: list[str]


def _startup_rows(model: Model, settings: PlanSettings, q_ref_rad: np.ndarray, cols: np.ndarray,
                  unanswered: set[str], rng: np.random.Generator) -> _StartupRows:
    """The startup's joint angles, linearised: at ``startup_poses`` random still poses (the
    chair tilted N(0, 3°), as :func:`startup_sigmas`), 1 s of the accelerometers' readings
    (the link accelerometers' and the IMU's) solved for the geometric joint angles and the
    base's roll and pitch by weighted least squares (the saved pose's 10° as a prior). Its
    answer moves by ``-S ∂y/∂x`` when an element ``x`` of the accelerometers' sensor stage
    is off; in the criterion's prior units those rows are ``G``.

    Returns ``G (R, len(cols))``, the noise variance of each row ``(R,)`` (rad²), the joint
    of each row ``(R,)`` and the names of the joints counted: the joints ``unanswered`` (a
    gauge's partners: the startup flags them after any parked maneuver) are left out, and so
    is a joint at a pose where the readings' noise alone puts its σ over half of
    ``startup_sigma_limit_deg`` (near a singular pose: the startup flags it there)."""
    arm = model.arm
    K = settings.startup_poses
    lo, hi = margin_limits(arm)
    Q = rng.uniform(lo, hi, (K, arm.n_joints))
    tilt = rng.normal(0.0, 3.0 * DEG, (K, 2))
    sm = stream_models(arm, settings.rate_hz)
    accel = [s.name for s in arm.link_accelerometers] + (["imu_acc"] if arm.imu is not None else [])
    streams = [s for s in fit_streams(arm) if s in sm and s in accel]
    counts = {s: np.zeros((K, np.size(sm[s].sigma_counts))) for s in streams}
    sig = {s: np.asarray(sm[s].sigma_counts, float) / np.sqrt(settings.rate_hz) for s in streams}  # 1 s
    data = FitData(MotionState.static(Q, temperature_c=25.0), counts, sig, np.asarray(q_ref_rad, float), 1,
                   stance=np.arange(K))
    pb = FitProblem(model, data, streams, True, np.zeros(3), encoder_scale=True)
    z = pb.x0.copy()
    z[pb.P:].reshape(K, 3)[:, :2] = tilt
    _, J = pb.jacobian(z, np.arange(pb.size))
    # rows per pose: the stream blocks are stacked stream by stream, each (K, axes)
    J = np.concatenate([J[o:o + K * counts[s].shape[1]].reshape(K, counts[s].shape[1], -1)
                        for o, s in zip(np.cumsum([0] + [K * counts[s].shape[1] for s in streams])[:-1],
                                        streams, strict=True)], axis=1)  # (K, rows, size)
    names = list(pb.names)
    joint_cols = [names.index(f"{j}.joint_offset[offset]") for j in arm.joint_names]
    sensor = np.zeros(pb.size, bool)
    for e in model.effects:
        if isinstance(e, SensorEffect) and set(e.streams) & set(accel):
            sensor[model.index[e.block_name]] = True
    prior = np.full(arm.n_joints + 2, 1.0 / (10.0 * DEG) ** 2)
    prior[-2:] = 1.0 / (3.0 * DEG) ** 2
    G, noise, joint = [], [], []
    for k in range(K):
        u_cols = joint_cols + [pb.P + 3 * k, pb.P + 3 * k + 1]
        H = J[k][:, u_cols]
        N = np.linalg.inv(H.T @ H + np.diag(prior))
        S = N @ H.T  # (u, rows): the answer's sensitivity to the (weighted) readings
        E = np.where(sensor, J[k], 0.0)
        G.append(S[:arm.n_joints] @ E)  # (n, size)
        noise.append(np.diag(N)[:arm.n_joints])
    G = np.concatenate(G)  # (K n, size)
    noise = np.concatenate(noise)
    joint = np.tile(np.arange(arm.n_joints), K)
    ok = np.array([j not in unanswered for j in arm.joint_names])
    rows = ok[joint] & (np.sqrt(noise) <= 0.5 * settings.startup_sigma_limit_deg * DEG)
    return _StartupRows(G[rows][:, cols] * pb.sigma0[cols], noise[rows], joint[rows],
                        [j for j, o in zip(arm.joint_names, ok, strict=True) if o])


def _startup_value(var_rows: np.ndarray, joint: np.ndarray, n_joints: int) -> np.ndarray:
    """The criterion of ``criterion="startup"``, ``(..., R) -> (...)``: the sum over the joints
    of the log of each joint's mean startup variance over the poses (the log of their product:
    the D-criterion of the startup's answers; greedy, it lowers the worst joint's σ further
    than a 4-norm or the plain sum of the variances, which chase one joint each step)."""
    K = np.bincount(joint, minlength=n_joints)
    per = np.stack([var_rows[..., joint == j].sum(-1) / K[j] for j in np.unique(joint)], -1)
    return np.sum(np.log(per), -1)


def _gauges(model: Model, st: PlanSettings, q0: np.ndarray, rng: np.random.Generator
            ) -> tuple[FitProblem, list[Hold]]:
    """The problem over a pool of :attr:`PlanSettings.pool_poses` random poses sharing the
    whole duration, and what its identifiability analysis holds: the gauges no maneuver of
    the chair parked can tell, which the criterion leaves out."""
    arm = model.arm
    lo, hi = margin_limits(arm)
    pool = rng.uniform(lo, hi, (st.pool_poses, arm.n_joints))
    pb = _static_problem(model, pool, st, q0)
    Jp = _rows_per_pose(pb)
    windows_per_s = st.rate_hz / st.window
    H_pool = np.einsum("nri,nrj->ij", Jp, Jp) * (st.duration_s * windows_per_s / st.pool_poses)
    return pb, analyse_information(H_pool, pb.sigma0, pb.names, np.ones(pb.size, bool), IdentifySettings())


def _dwell_choices_s(st: PlanSettings) -> np.ndarray:
    """The dwells a pose may be held, shortest first."""
    return np.array(sorted(set(st.dwell_choices_s) or {st.dwell_s}))


def _candidates(arm: ArmModel, st: PlanSettings, q: np.ndarray, time_left_s: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The random next poses from ``q`` that pass the unlock move's checks, the tool speed and
    the time left (with the shortest dwell), and each one's move duration (s)."""
    lo, hi = margin_limits(arm)
    cand = np.clip(q + rng.uniform(-1, 1, (st.candidates, arm.n_joints)) * st.max_move_deg * DEG, lo, hi)
    T = move_durations_s(st, q, cand)
    ok = (moves_within_limits(arm, q, cand, st.max_move_deg)
          & (_tool_speed_mps(arm, np.broadcast_to(q, cand.shape), cand, T) <= st.max_tool_speed_mps)
          & (T + _dwell_choices_s(st)[0] <= time_left_s))
    return cand[ok], T[ok]


def _best_move(st: PlanSettings, A: np.ndarray, Jc: np.ndarray, move_s: np.ndarray, time_left_s: float,
               startup: _StartupRows | None, n_joints: int) -> tuple[int, float]:
    """The candidate and dwell with the best gain in the criterion per second of move and
    dwell: ``A`` the information so far and ``Jc (C, rows, cols)`` each candidate's rows, in
    prior units; ``startup`` the startup's rows for ``criterion="startup"``."""
    windows_per_s = st.rate_hz / st.window
    Ainv = np.linalg.inv(A)
    K = np.einsum("cri,ij,csj->crs", Jc, Ainv, Jc)  # (C, r, r)
    if startup is not None:
        GA = startup.G @ Ainv
        v_now = startup.noise + np.einsum("Rp,Rp->R", GA, startup.G)
        f_now = _startup_value(v_now, startup.joint, n_joints)
        U = np.einsum("Rp,crp->cRr", GA, Jc)  # (C, R, r)
    else:
        lam0 = np.linalg.eigvalsh(A)[0]
    best_rate, best = -np.inf, None
    for d in _dwell_choices_s(st):
        fits = move_s + d <= time_left_s
        if not fits.any():
            continue
        w = d * windows_per_s
        if st.criterion == "D":
            gain = np.linalg.slogdet(np.eye(Jc.shape[1]) + w * K)[1]
        elif st.criterion == "E":
            gain = np.array([np.linalg.eigvalsh(A + w * J.T @ J)[0] - lam0 for J in Jc])
        else:  # Woodbury: each row's variance falls by w uᵀ(I + w K)⁻¹u
            Mi = np.linalg.inv(np.eye(Jc.shape[1]) + w * K)
            drop = w * np.einsum("cRr,crs,cRs->cR", U, Mi, U)
            gain = f_now - _startup_value(v_now - drop, startup.joint, n_joints)
        rate = np.where(fits, gain / (move_s + d), -np.inf)
        i = int(np.argmax(rate))
        if rate[i] > best_rate:
            best_rate, best = rate[i], (i, float(d))
    return best


def plan_maneuver(model: Model, settings: PlanSettings | None = None, progress=None) -> Plan:
    """Choose the poses of a maneuver of ``settings.duration_s`` for ``model``'s parameters
    (module docstring). Starts at the arm's ready pose, held ``start_still_s``; then, while
    the time allows, the best of the candidate moves (:func:`_candidates`, :func:`_best_move`)."""
    st = settings or PlanSettings()
    st.check()
    arm = model.arm
    rng = np.random.default_rng([st.seed, 0x91A])
    q0 = np.clip(np.asarray(arm.ready_pose_rad, float), arm.min_rad, arm.max_rad)
    windows_per_s = st.rate_hz / st.window
    pb, holds = _gauges(model, st, q0, rng)
    gauges = {h.element for h in holds}
    wanted = set(pb.names) if st.focus == "all" else startup_elements(model)
    cols = np.array([i for i, n in enumerate(pb.names) if n not in gauges and n in wanted])
    D = pb.sigma0[cols]

    def scaled_rows(Q):
        J = _rows_per_pose(_static_problem(model, Q, st, q0))
        return J[:, :, cols] * D  # prior units

    J0 = scaled_rows(q0[None])[0]
    A = np.eye(len(cols)) + (J0.T @ J0) * (st.start_still_s * windows_per_s)
    startup = None
    if st.criterion == "startup":
        unanswered = {j for h in holds for p, _ in h.partners for j in arm.joint_names
                      if p == f"{j}.joint_offset[offset]"}
        startup = _startup_rows(model, st, q0, cols, unanswered, np.random.default_rng([st.seed, 0x57A]))
    poses, dwells, moves = [q0], [st.start_still_s], []
    t = st.start_still_s
    scored = 0
    while st.duration_s - t >= st.min_move_s + _dwell_choices_s(st)[0]:
        cand, T = _candidates(arm, st, poses[-1], st.duration_s - t, rng)
        if not len(cand):
            break
        scored += len(cand)
        Jc = scaled_rows(cand)  # (C, r, p)
        i, d = _best_move(st, A, Jc, T, st.duration_s - t, startup, arm.n_joints)
        A = A + d * windows_per_s * Jc[i].T @ Jc[i]
        poses.append(cand[i])
        moves.append(float(T[i]))
        dwells.append(d)
        t += T[i] + d
        if progress is not None:
            progress(t / st.duration_s)
    dwells[-1] += max(0.0, st.duration_s - t)  # the time left: the last pose held longer
    m = PlannedManeuver(tuple(arm.joint_names), np.array(poses), np.array(dwells), np.array(moves))
    return Plan(m, st.criterion, pb.names, tuple(sorted(gauges)), scored,
                tuple(startup.counted) if startup is not None else ())


__all__ = ["CRITERIA", "Plan", "PlanSettings", "Prediction", "maneuver_problems", "move_durations_s",
           "plan_maneuver", "predict_maneuver", "predicted_identification", "startup_sigmas"]
