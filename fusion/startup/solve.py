"""Startup absolute calibration: every joint angle from a still arm (:func:`solve_still`).

Gravity fixes two angles per accelerometer only up to a discrete set of branches. The
solve:

1. averages every sensor over a still window (readings in g, with the standard error of
   each mean and a floor for what the sensor model does not capture:
   :mod:`armfusion.fusion.startup.readings`);
2. enumerates every branch in closed form, walking the chain sensor by sensor
   (:mod:`armfusion.fusion.startup.branches`);
3. polishes every branch at once with a batched Levenberg-Marquardt on all joints, the base
   roll and pitch, and every sensor's residual weighted by its noise (``method="joint"``,
   :mod:`armfusion.fusion.startup.problem`), or pair by pair as the thesis did
   (``method="sequential"``, the reference);
4. keeps the branches inside the joint limits. With no prior every branch that fits is a
   rival: the joints on which fitting branches differ are flagged ``ambiguous`` with every
   candidate, and :func:`~armfusion.fusion.startup.moves.propose_disambiguating_move` finds the
   smallest safe move after which they read differently. A prior
   (:class:`~armfusion.fusion.startup.prior.StartupPrior`: a saved pose, or an earlier window's
   answer carried through the encoder counts) chooses only when it fits the data
   (chi-square test); the ready pose chooses only when the caller asserts the arm is
   parked, and the result says so;
5. gives every joint a sigma from the weighted Jacobian (base tilt included), widened where
   the cost is flatter than quadratic (:mod:`armfusion.fusion.startup.confidence`), and a flag.

Nothing here moves the arm. When joints are gravity-blind,
:func:`~armfusion.fusion.startup.moves.propose_unlock_move` finds the smallest move of a well-known
joint that would make them readable.

This module is also where the startup's public names are imported from (they are defined
in the modules named above).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from armfusion.fusion.startup.branches import (
    dedupe,
    dedupe_x,
    feasible_branches,
    fitting_branches,
    limit_margins_rad,
)
from armfusion.fusion.startup.combinations import observable_combinations
from armfusion.fusion.startup.confidence import (
    candidate_covariances,
    follow_weak,
    follow_weak_starts,
    linear_covariance,
    profile_sigma,
    thesis_detector,
    weigh_rivals,
)
from armfusion.fusion.startup.moves import (
    move_delta_rad,
    prior_after_move,
    propose_disambiguating_move,
    propose_unlock_move,
)
from armfusion.fusion.startup.prior import BranchChooser, StartupPrior
from armfusion.fusion.startup.problem import (
    StillWindowProblem,
    axis_to_vertical,
    batched_lm,
    expected_covariance,
    make_problem,
)
from armfusion.fusion.startup.readings import (
    InputCheck,
    StillReadings,
    check_readings,
    readings_from_counts,
    readings_from_recording,
    sensor_floor_g,
)
from armfusion.fusion.startup.results import (
    FLAGS,
    DisambiguatingMove,
    JointEstimate,
    StartupInputError,
    StartupResult,
    UnlockMove,
    summary,
)
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.fusion.startup.tilt_only import base_tilt_only
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, wrap_angle

__all__ = [
    "FLAGS", "DisambiguatingMove", "InputCheck", "JointEstimate", "StartupInputError",
    "StartupPrior", "StartupResult", "StartupSettings", "StillReadings", "UnlockMove",
    "check_readings", "move_delta_rad", "prior_after_move", "propose_disambiguating_move",
    "propose_unlock_move", "readings_from_counts", "readings_from_recording", "solve_still",
    "thesis_detector",
]


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
    if arm.n_joints == 0:
        return base_tilt_only(arm, readings, st, method)
    problem = make_problem(arm, readings)
    chosen = _choose_branch(problem, st, prior, method)
    fit = _linear_fit(problem, chosen, st)
    sig, flags, rivals_x = _follow_weak_and_probes(problem, chosen, fit, st)
    verdict = _final_flags(arm, chosen, fit, sig, flags, rivals_x, st)
    result = _result(problem, readings, chosen, fit, verdict, st, method)
    if propose_unlock and any(f in ("gimbal_lock", "ill_conditioned") for f in verdict.flags):
        result = replace(result, unlock_move=propose_unlock_move(arm, result, readings, st))
    if len(verdict.kept) > 1:
        result = replace(result, disambiguating_move=propose_disambiguating_move(
            arm, result, readings, st, roll_pitch=chosen.xb[arm.n_joints:]))
    return replace(result, summary=_summary_with_sensor_note(arm, problem, result))


@dataclass(frozen=True)
class _ChosenBranch:
    """The branch a still solve settles on, among every branch that fits the data."""

    x: np.ndarray
    """Every fitting branch, polished, best first: ``(B, n + 2)`` (joints, base roll, pitch)."""
    cost: np.ndarray
    """Each branch's cost (half its weighted chi-square), ``(B,)``."""
    candidates: np.ndarray
    """The rows of ``x`` that may be the arm's (the feasible ones)."""
    pool: np.ndarray
    """The rows the chooser keeps (the data's, or the prior's choice)."""
    best: int
    """The chosen row of ``x``."""
    branches_rad: np.ndarray
    """The distinct branches inside the limits, ``(F, n)``."""
    axis_deg: np.ndarray
    """Every joint's axis to vertical on every branch, ``(B, n)`` deg."""
    locked_any: np.ndarray
    """Where that is within ``gimbal_lock_deg``, ``(B, n)``."""
    margin_rad: np.ndarray
    """Per joint, how far outside its limits a branch is still feasible."""
    chooser: BranchChooser
    notes: list[str]
    """What the chooser said, for the result's notes."""
    dof: int
    """The fit's degrees of freedom (two per direction read, less the unknowns)."""

    @property
    def xb(self) -> np.ndarray:
        """The chosen state ``(n + 2,)``."""
        return self.x[self.best]

    @property
    def locked(self) -> np.ndarray:
        """The chosen branch's locked joints ``(n,)``."""
        return self.locked_any[self.best]


@dataclass(frozen=True)
class _LinearFit:
    """The fit at the chosen branch: its weighted residuals and Jacobian, and the covariance
    and sigmas they give (the readable joints' sigmas profiled along the cost)."""

    r: np.ndarray
    J: np.ndarray
    chi2_dof: float
    inflate: float
    """The Birge ratio, at least one: how much worse the fit is than its sigmas say."""
    cov: np.ndarray
    """The linear covariance ``(n + 2, n + 2)`` times ``inflate``."""
    sig: np.ndarray
    """Every unknown's sigma ``(n + 2,)``: the linear one, profiled where readable."""
    probes: np.ndarray
    """The profile's probe states, each to roll to its own minimum."""


def _choose_branch(problem: StillWindowProblem, st: StartupSettings, prior: StartupPrior | None,
                   method: str) -> _ChosenBranch:
    """Every fitting branch, those inside the limits, and the one the prior (or, with none,
    the data) chooses."""
    arm, n = problem.arm, problem.arm.n_joints
    free = np.ones(n + 2, dtype=bool)
    margin = limit_margins_rad(arm, st)
    x, cost = fitting_branches(problem, st, prior, method)
    q_all = x[:, :n]
    axis_deg = np.degrees(axis_to_vertical(arm, q_all, x[:, n], x[:, n + 1]))
    locked_any = axis_deg < st.gimbal_lock_deg  # (B, n)
    branches, cand = feasible_branches(arm, q_all, locked_any, margin)
    n_dir = len(problem.names) + 1  # the IMU's direction, or the level-chair prior
    dof = max(2 * n_dir - int(free.sum()), 1)
    inflate0 = max(2.0 * float(cost[cand].min()) / dof, 1.0)
    # which branches may be the arm's: the data's (every feasible one), or the prior's choice
    notes: list[str] = []
    chooser = BranchChooser.make(prior, st, q_all[cand], locked_any[cand],
                                 expected_covariance(problem, x[cand])[:, :n, :n] * inflate0, notes)
    pool = cand[chooser.keep]
    best = pool[int(np.argmin(chooser.rank[chooser.keep]))]
    return _ChosenBranch(x, cost, cand, pool, best, branches, axis_deg, locked_any, margin,
                         chooser, notes, dof)


def _linear_fit(problem: StillWindowProblem, chosen: _ChosenBranch, st: StartupSettings) -> _LinearFit:
    """The covariance from the weighted Jacobian at the chosen solution, and each readable
    joint's sigma from the cost's own profile."""
    n = problem.arm.n_joints
    free = np.ones(n + 2, dtype=bool)
    xb = chosen.xb
    r, J = problem.residuals_and_jacobian(xb[None])
    r, J = r[0], J[0]
    # a normalised direction carries two constraints, not three; the tilt prior two more
    chi2_dof = float(r @ r / chosen.dof)
    # the fit itself says when the model is worse than its sigmas (Birge ratio)
    inflate = max(chi2_dof, 1.0)
    cov = linear_covariance(J, free, inflate)
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    # the cost's own verdict on every readable joint (flat valleys near singular pairs)
    # (well-read joints are quadratic over many sigmas: only the wider ones are checked)
    readable = np.flatnonzero(~chosen.locked & np.isfinite(sig[:n]) & (sig[:n] > st.profile_above_deg * DEG))
    sig[readable], probes = profile_sigma(problem, xb, float(0.5 * r @ r), sig, readable,
                                          np.sqrt(inflate))
    return _LinearFit(r, J, chi2_dof, inflate, cov, sig, probes)


def _follow_weak_and_probes(problem: StillWindowProblem, chosen: _ChosenBranch, fit: _LinearFit,
                            st: StartupSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every sigma widened by how far it follows a weak joint, the first flags, and the rival
    states (the chooser's pool, and the profile's probes that rolled to a minimum as good).

    Joints whose value rests on a weak one (locked, or sigma above the limit): sweep the
    weak joint across what the data allow, re-solve the rest, and widen the others' sigma by
    how far they follow. A joint pushed over the limit by a locked joint inherits its flag;
    by an ill-conditioned one, it becomes ill-conditioned. A valley may hold other minima
    than the branches the starts reached: the profile's probes are released, each rolls to
    its own; good ones join the branches as rivals. Those and the sweep are solved in one
    batch (every row on its own). Returns ``(sig, flags, rivals_x)``."""
    arm, n = problem.arm, problem.arm.n_joints
    xb, locked, probes, r = chosen.xb, chosen.locked, fit.probes, fit.r
    sig = fit.sig.copy()
    flags = np.array(["ok"] * n, dtype=object)
    flags[locked] = "gimbal_lock"
    limit = st.sigma_limit_deg * DEG
    weak = locked | (sig[:n] > limit)
    follow_x0, follow_free, follow_j = follow_weak_starts(xb, sig, weak, locked)
    solved, solved_cost = np.zeros((0, n + 2)), np.zeros(0)
    if len(probes) or len(follow_j):
        solved, solved_cost = batched_lm(
            problem, np.vstack([probes, follow_x0]),
            np.vstack([np.ones(probes.shape, bool), follow_free]),
            np.concatenate([np.full(len(probes), st.max_iterations), np.full(len(follow_j), 12)]))
    xr, cost_r = solved[: len(probes)], solved_cost[: len(probes)]
    rivals_x = chosen.x[chosen.pool]
    if len(probes):
        mid = (arm.min_rad + arm.max_rad) / 2
        xr[:, :n] = mid + wrap_angle(xr[:, :n] - mid)
        keep = ((cost_r <= chosen.cost[chosen.candidates].min() + 0.5 * st.fit_chi2 + 1e-9)
                & (arm.within_limits(xr[:, :n], chosen.margin_rad) | locked).all(1))
        if keep.any():
            xr = dedupe(xr[keep], 1e-3)
            joins = chosen.chooser.admits(xr[:, :n], np.broadcast_to(locked, (len(xr), n)),
                                          expected_covariance(problem, xr)[:, :n, :n] * fit.inflate)
            rivals_x = np.vstack([rivals_x, xr[joins]])
    if weak.any():
        follow = follow_weak(solved[len(probes):], solved_cost[len(probes):], follow_j, xb,
                             float(0.5 * r @ r), locked, fit.inflate)
        moved = follow.max(0)  # (n,): the widest any weak joint drags each joint
        widened = np.maximum(sig[:n], moved / 3.0)
        by_locked = follow[locked[weak]].max(0) if locked.any() else np.zeros(n)
        from_locked = ~weak & (widened > limit) & (by_locked / 3.0 > limit)
        sig[:n] = np.where(weak, sig[:n], widened)
        flags[from_locked] = "gimbal_lock"
    return sig, flags, rivals_x


class _Verdict(NamedTuple):
    """Each joint's last word: its sigma and flag, whether it gets a number, the rivals kept
    and every joint's alternative values."""

    sig: np.ndarray
    """Every unknown's sigma ``(n + 2,)``, the safety factor and the rivals' widening in."""
    flags: np.ndarray
    blind: np.ndarray
    """The joints the data cannot see ``(n,)``: no number."""
    cov: np.ndarray
    """The linear covariance, widened where a rival in the same valley widens a sigma."""
    kept: list[np.ndarray]
    """The candidates kept, the chosen first."""
    alternatives: list[list[float]]


def _final_flags(arm: ArmModel, chosen: _ChosenBranch, fit: _LinearFit, sig: np.ndarray,
                 flags: np.ndarray, rivals_x: np.ndarray, st: StartupSettings) -> _Verdict:
    """The safety factor on every sigma, then each joint's last flags: ill-conditioned over
    the limit, out of limits, ambiguous between rivals
    (:func:`~armfusion.fusion.startup.confidence.weigh_rivals`), and blind (no number) where
    the data cannot see it."""
    n = arm.n_joints
    sig = sig * st.sigma_safety_factor
    cov = fit.cov.copy()
    ill = (sig[:n] > st.sigma_limit_deg * DEG) & (flags == "ok")
    flags[ill] = "ill_conditioned"
    out_of_limits = ~arm.within_limits(chosen.xb[:n], chosen.margin_rad) & (flags == "ok")
    flags[out_of_limits] = "out_of_limits"
    kept, alternatives = weigh_rivals(st, dedupe_x(rivals_x, chosen.xb), sig, cov, flags)
    # a joint the data cannot see gets no number (never a sigma of thousands of degrees)
    blind = (sig[:n] > st.numbered_sigma_max_deg * DEG) & ~np.isin(flags, ("gimbal_lock", "ambiguous"))
    flags[blind] = "ill_conditioned"
    return _Verdict(sig, flags, blind, cov, kept, alternatives)


def _result(problem: StillWindowProblem, readings: StillReadings, chosen: _ChosenBranch,
            fit: _LinearFit, verdict: _Verdict, st: StartupSettings, method: str) -> StartupResult:
    """The result of the solve, before its moves and summary: every joint's estimate, the
    base tilt, the covariance widened to the sigmas the checks arrived at, the candidates
    and the combinations the linear covariance knows."""
    arm, n = problem.arm, problem.arm.n_joints
    xb, cov, sig, kept = chosen.xb, verdict.cov, verdict.sig, verdict.kept
    joints = _joint_estimates(problem, st, xb[:n], verdict, chosen.axis_deg[chosen.best])
    resid_g = (fit.r[: problem.meas.size] * problem.sigma.reshape(-1))
    # the covariance keeps the linear correlations, scaled to the sigmas the checks arrived
    # at (the profile, the sweep and the rivals widen them), every joint's included
    linear = cov * st.sigma_safety_factor**2  # (what the combinations are read from)
    lin = np.sqrt(np.clip(np.diag(cov), 1e-30, None)) * st.sigma_safety_factor
    widen = np.where(np.isfinite(sig), np.maximum(sig / lin, 1.0), 1.0)
    cov = cov * np.outer(widen, widen)
    result = StartupResult(
        joints=joints,
        roll_rad=float(xb[n]), pitch_rad=float(xb[n + 1]),
        roll_sigma_rad=float(sig[n]), pitch_sigma_rad=float(sig[n + 1]),
        residual_rms_g=float(np.sqrt(np.mean(resid_g**2))),
        chi2_per_dof=fit.chi2_dof,
        q_rad=xb[:n].copy(), covariance=cov * st.sigma_safety_factor**2, branches_rad=chosen.branches_rad,
        method=method,
        t_start_s=readings.t_start_s, t_end_s=readings.t_end_s,
        candidates_rad=np.array([k[:n] for k in kept]),
        candidates_covariance=candidate_covariances(problem, kept, cov * st.sigma_safety_factor**2,
                                                    fit.inflate * st.sigma_safety_factor**2),
        prior_used=chosen.chooser.used,
        notes=tuple(chosen.notes),
    )
    return replace(result, combinations=startup_combinations(arm, result, linear, st))


TILT_NAMES = ("base roll", "base pitch")
"""The base's tilt as a combination names it."""


def startup_combinations(arm: ArmModel, result: StartupResult, cov: np.ndarray,
                         st: StartupSettings) -> tuple:
    """The combinations of the joints not ``ok`` (nor ``gimbal_lock``: gravity reads them not
    at all; nor ``ambiguous``: rival branches) (and of the base's roll and pitch where
    their sigma is above ``sigma_limit_deg``) that ``cov`` knows within
    ``combination_sigma_max_deg`` (:func:`armfusion.fusion.startup.combinations.observable_combinations`).
    ``cov``: the solve's linear covariance (with the safety factor), before each joint's
    sigma is widened to what the profile, the sweep and the rivals found: that widening scales
    a joint's row and column whole, and two joints read only as a sum, each widened to
    hundreds of degrees, would have their sum widened by as much."""
    n = len(result.joints)
    x = np.concatenate([result.q_rad, [result.roll_rad, result.pitch_rad]])
    cand = np.array([j.flag not in ("ok", "gimbal_lock", "ambiguous") for j in result.joints]
                    + [s > st.sigma_limit_deg * DEG for s in (result.roll_sigma_rad, result.pitch_sigma_rad)])
    names = [*arm.joint_names[:n], *TILT_NAMES]
    return observable_combinations(cov, x, names, st.combination_sigma_max_deg * DEG, cand)


def _joint_estimates(problem: StillWindowProblem, st: StartupSettings, qb: np.ndarray,
                     verdict: _Verdict, axis_deg: np.ndarray) -> tuple[JointEstimate, ...]:
    """Each joint's estimate: a number and sigma unless it is locked, ambiguous or blind
    (then its range: the limits, or for an ambiguous one its alternatives)."""
    arm = problem.arm
    sig, flags, blind, alternatives = verdict.sig, verdict.flags, verdict.blind, verdict.alternatives
    thesis = thesis_detector(arm, problem.names, problem.meas, st.thesis_detector_g)
    joints = []
    for j in range(arm.n_joints):
        number = flags[j] not in ("gimbal_lock", "ambiguous") and not blind[j]
        joints.append(JointEstimate(
            name=arm.joints[j].name,
            angle_rad=float(qb[j]) if number else None,
            sigma_rad=float(sig[j]) if number and np.isfinite(sig[j]) else None,
            flag=str(flags[j]),
            alternatives_rad=tuple(alternatives[j]),
            axis_to_vertical_deg=float(axis_deg[j]),
            thesis_detector_locked=thesis[j],
            range_rad=None if number or flags[j] == "ambiguous"
            else (float(arm.min_rad[j]), float(arm.max_rad[j])),
            turns_rad=turn_branches(float(qb[j]), float(arm.min_rad[j]), float(arm.max_rad[j]))
            if number else (),
        ))
    return tuple(joints)


def turn_branches(q_rad: float, lo_rad: float, hi_rad: float) -> tuple[float, ...]:
    """Every angle inside ``[lo_rad, hi_rad]`` a whole number of turns from ``q_rad``
    (ascending), where more than one is: gravity reads a revolute joint only modulo a turn.
    Empty where one alone fits."""
    two_pi = 2.0 * np.pi
    first = q_rad + two_pi * np.ceil((lo_rad - q_rad) / two_pi)
    turns = tuple(float(first + two_pi * k) for k in range(int((hi_rad - first) // two_pi) + 1))
    return turns if len(turns) > 1 else ()


def _summary_with_sensor_note(arm: ArmModel, problem: StillWindowProblem,
                              result: StartupResult) -> str:
    """The result's summary, saying where ill-conditioned sigmas come from the sensors'
    unmodelled error (the config's floor, or what their calibration could not pin)."""
    text = summary(result)
    floor_g = max(sensor_floor_g(arm, nm) for nm in problem.names)
    if floor_g >= 0.005 and any(j.flag == "ill_conditioned" for j in result.joints):
        text += (f" (the sigmas include the config's unmodelled sensor error, "
                 f"{floor_g * 1000:.0f} mg per axis: calibrating the sensors lowers it)")
    elif arm.calibration.correction_covariance and any(j.flag == "ill_conditioned"
                                                            for j in result.joints):
        text += (" (the sigmas include what the sensors' calibration could not pin: its held "
                 "elements, with the motion that would separate them, in `calibrate sensors`)")
    return text
