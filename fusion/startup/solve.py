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

from dataclasses import replace

import numpy as np
from armfusion.fusion.startup.branches import (
    closed_form_branches,
    complete_combinations,
    dedupe,
    dedupe_x,
    sequential_solve,
)
from armfusion.fusion.startup.combinations import observable_combinations
from armfusion.fusion.startup.confidence import (
    candidate_covariances,
    follow_weak,
    follow_weak_starts,
    profile_sigma,
    thesis_detector,
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
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, tilt_from_up, wrap_angle

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
        return _base_tilt_only(arm, readings, st, method)
    problem = make_problem(arm, readings)
    n = arm.n_joints
    free = np.ones(n + 2, dtype=bool)
    mid = (arm.min_rad + arm.max_rad) / 2
    margin = limit_margins_rad(arm, st)
    x, cost = _fitting_branches(problem, st, prior, method)
    q_all = x[:, :n]
    axis_deg = np.degrees(axis_to_vertical(arm, q_all, x[:, n], x[:, n + 1]))
    locked_any = axis_deg < st.gimbal_lock_deg  # (B, n)
    branches, cand = _feasible_branches(arm, q_all, locked_any, margin)
    n_dir = len(problem.names) + 1  # the IMU's direction, or the level-chair prior
    dof = max(2 * n_dir - int(free.sum()), 1)
    inflate0 = max(2.0 * float(cost[cand].min()) / dof, 1.0)
    # which branches may be the arm's: the data's (every feasible one), or the prior's choice
    notes: list[str] = []
    chooser = BranchChooser.make(prior, st, q_all[cand], locked_any[cand],
                                 expected_covariance(problem, x[cand])[:, :n, :n] * inflate0, notes)
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
    # the fit itself says when the model is worse than its sigmas (Birge ratio)
    inflate = max(chi2_dof, 1.0)
    cov = _linear_covariance(J, free, inflate)
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    # the cost's own verdict on every readable joint (flat valleys near singular pairs)
    # (well-read joints are quadratic over many sigmas: only the wider ones are checked)
    readable = np.flatnonzero(~locked & np.isfinite(sig[:n]) & (sig[:n] > st.profile_above_deg * DEG))
    sig[readable], probes = profile_sigma(problem, xb, float(0.5 * r @ r), sig, readable,
                                          np.sqrt(inflate))
    flags = np.array(["ok"] * n, dtype=object)
    flags[locked] = "gimbal_lock"
    limit = st.sigma_limit_deg * DEG
    # Joints whose value rests on a weak one (locked, or sigma above the limit): sweep the
    # weak joint across what the data allow, re-solve the rest, and widen the others'
    # sigma by how far they follow. A joint pushed over the limit by a locked joint
    # inherits its flag; by an ill-conditioned one, it becomes ill-conditioned.
    weak = locked | (sig[:n] > limit)
    follow_x0, follow_free, follow_j = follow_weak_starts(xb, sig, weak, locked)
    # A valley may hold other minima than the branches the starts reached: the profile's
    # probes are released, each rolls to its own; good ones join the branches as rivals
    # below. Those and the sweep are solved in one batch (every row on its own).
    solved, solved_cost = np.zeros((0, n + 2)), np.zeros(0)
    if len(probes) or len(follow_j):
        solved, solved_cost = batched_lm(
            problem, np.vstack([probes, follow_x0]),
            np.vstack([np.ones(probes.shape, bool), follow_free]),
            np.concatenate([np.full(len(probes), st.max_iterations), np.full(len(follow_j), 12)]))
    xr, cost_r = solved[: len(probes)], solved_cost[: len(probes)]
    rivals_x = x[pool]
    if len(probes):
        xr[:, :n] = mid + wrap_angle(xr[:, :n] - mid)
        keep = ((cost_r <= cost[cand].min() + 0.5 * st.fit_chi2 + 1e-9)
                & (arm.within_limits(xr[:, :n], margin) | locked).all(1))
        if keep.any():
            xr = dedupe(xr[keep], 1e-3)
            joins = chooser.admits(xr[:, :n], np.broadcast_to(locked, (len(xr), n)),
                                   expected_covariance(problem, xr)[:, :n, :n] * inflate)
            rivals_x = np.vstack([rivals_x, xr[joins]])
    if weak.any():
        follow = follow_weak(solved[len(probes):], solved_cost[len(probes):], follow_j, xb,
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
    kept, alternatives = _weigh_rivals(st, dedupe_x(rivals_x, xb), sig, cov, flags)
    # a joint the data cannot see gets no number (never a sigma of thousands of degrees)
    blind = (sig[:n] > st.numbered_sigma_max_deg * DEG) & ~np.isin(flags, ("gimbal_lock", "ambiguous"))
    flags[blind] = "ill_conditioned"
    joints = _joint_estimates(arm, problem, st, qb, sig, flags, blind, alternatives, axis_deg[best])
    resid_g = (r[: problem.meas.size] * problem.sigma.reshape(-1))
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
        chi2_per_dof=chi2_dof,
        q_rad=qb.copy(), covariance=cov * st.sigma_safety_factor**2, branches_rad=branches,
        method=method,
        t_start_s=readings.t_start_s, t_end_s=readings.t_end_s,
        candidates_rad=np.array([k[:n] for k in kept]),
        candidates_covariance=candidate_covariances(problem, kept, cov * st.sigma_safety_factor**2,
                                                    inflate * st.sigma_safety_factor**2),
        prior_used=chooser.used,
        notes=tuple(notes),
    )
    result = replace(result, combinations=startup_combinations(arm, result, linear, st))
    if propose_unlock and any(f in ("gimbal_lock", "ill_conditioned") for f in flags):
        result = replace(result, unlock_move=propose_unlock_move(arm, result, readings, st))
    if len(kept) > 1:
        result = replace(result, disambiguating_move=propose_disambiguating_move(
            arm, result, readings, st, roll_pitch=xb[n:]))
    return replace(result, summary=_summary_with_sensor_note(arm, problem, result))


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


def _base_tilt_only(arm: ArmModel, readings: StillReadings, st: StartupSettings,
                    method: str) -> StartupResult:
    """An arm with no joints (an IMU alone): the base's roll and pitch from its IMU's
    averaged reading in closed form (:func:`armfusion.models.rotations.tilt_from_up`, as the joint
    solve starts from), their covariance from the reading's sigma (its noise over the
    window, as the joint solve takes the IMU's: what the IMU accelerometer is off by is
    the tracker's ``imu_bias`` state, whose prior is the config's unmodelled error) through
    the same direction's Jacobian, times the safety factor. No joint, no branch."""
    if readings.imu_mean_g is None or arm.imu is None:
        raise StartupInputError("an arm with no joints is started from its base IMU, and the still "
                                "window has no IMU accelerometer reading")
    f = np.asarray(readings.imu_mean_g, float)
    norm = float(np.linalg.norm(f))
    if not norm > 0.0:
        raise StartupInputError("the IMU accelerometer's still reading is zero: no tilt to read")
    R_0I = arm.imu.R_LS
    up = R_0I @ (f / norm)
    roll, pitch = (float(a) for a in tilt_from_up(up))
    # d up / d (roll, pitch), base axes; the reading's per-axis sigma turned into them
    sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
    J = np.array([[0.0, -cp], [cr * cp, -sr * sp], [-sr * cp, -cr * sp]])
    sig_I = np.asarray(readings.imu_sigma_g, float) / norm
    C_up = R_0I @ np.diag(sig_I**2) @ R_0I.T
    info = J.T @ np.linalg.inv(C_up) @ J  # J is normal to up: the norm's own error drops out
    cov = np.linalg.inv(info) * st.sigma_safety_factor**2
    resid = f / norm - R_0I.T @ up  # zero: the direction is read exactly; kept for the record
    result = StartupResult(
        joints=(), roll_rad=roll, pitch_rad=pitch,
        roll_sigma_rad=float(np.sqrt(cov[0, 0])), pitch_sigma_rad=float(np.sqrt(cov[1, 1])),
        residual_rms_g=float(np.sqrt(np.mean(resid**2))), chi2_per_dof=0.0,
        q_rad=np.zeros(0), covariance=cov, branches_rad=np.zeros((1, 0)), method=method,
        t_start_s=readings.t_start_s, t_end_s=readings.t_end_s,
        candidates_rad=np.zeros((1, 0)), candidates_covariance=cov[None],
        notes=("no joints: the base tilt from the IMU accelerometer alone",))
    sig_deg = np.degrees([result.roll_sigma_rad, result.pitch_sigma_rad])
    return replace(result, summary=(f"no joints; base roll {np.degrees(roll):.2f} deg, pitch "
                                    f"{np.degrees(pitch):.2f} deg (sigma {sig_deg[0]:.3f}, "
                                    f"{sig_deg[1]:.3f} deg)"))


def _fitting_branches(problem: StillWindowProblem, st: StartupSettings, prior: StartupPrior | None,
                      method: str) -> tuple[np.ndarray, np.ndarray]:
    """Every branch that fits the data, polished, best first: states ``(B, n + 2)`` (joint
    angles brought to the representative nearest the middle of their limits) and costs.

    The closed-form branches (and, for the joint method, the ready pose and the prior's
    poses as further starts), polished; minima just outside a limit re-solved held at it;
    the groups' solutions crossed; those fitting much worse than the best dropped."""
    arm, n = problem.arm, problem.n
    # base tilt from the IMU (the thesis's eq. 4.1, in the recording spec's convention)
    if problem.imu_meas is not None:
        roll0, pitch0 = (float(a) for a in tilt_from_up(problem.R_0I @ problem.imu_meas))
    else:
        roll0 = pitch0 = 0.0
    starts = closed_form_branches(problem, roll0, pitch0)
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
        x, cost = batched_lm(problem, x0, free, st.max_iterations)
    elif method == "sequential":
        x, cost = sequential_solve(problem, x0, st)
    else:
        raise ValueError(f"unknown method {method!r}: use 'joint' or 'sequential'")
    mid = (arm.min_rad + arm.max_rad) / 2
    x[:, :n] = mid + wrap_angle(x[:, :n] - mid)
    margin = limit_margins_rad(arm, st)
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
        xc, cost_c = batched_lm(problem, xc, free_c, st.max_iterations)
        xc[:, :n] = mid + wrap_angle(xc[:, :n] - mid)
        x, cost = np.vstack([x, xc]), np.concatenate([cost, cost_c])
    if method == "joint":
        x, cost = complete_combinations(problem, x, cost, st, mid)
    # drop branches that fit much worse than the best (not solutions of the data)
    good = cost <= cost.min() + 0.5 * st.fit_chi2 + 1e-9
    x, cost = x[good], cost[good]
    order = np.argsort(cost)
    return x[order], cost[order]


def limit_margins_rad(arm: ArmModel, st: StartupSettings) -> np.ndarray:
    """Per joint, how far outside its limits a branch is still feasible (rad): the readings'
    ``limit_margin_deg`` plus ``limit_zero_sigmas`` of the joint's zero offset's sigma (the
    config's ``joint_offset`` sigma, else the effect's datasheet-typical one): the limits are
    in the joint's numbering, the branches in its geometric angle."""
    return st.limit_margin_deg * DEG + st.limit_zero_sigmas * _zero_offset_sigma_rad(arm)


def _zero_offset_sigma_rad(arm: ArmModel) -> np.ndarray:
    """Per joint, its zero offset's sigma (rad), worked out once per arm (kept on it, as the
    arm keeps its chain arrays: every solve asks)."""
    zero = arm.__dict__.get("_zero_offset_sigma_rad")
    if zero is not None:
        return zero
    from armfusion.models.effects.base import TargetError
    from armfusion.models.effects.entries import build_effect, entry_dict

    entries = [entry_dict(e) for e in arm.effects]
    stated = {e.get("target"): (e.get("sigma") or {}).get("offset_rad") for e in entries
              if e.get("effect") == "joint_offset"}
    zero = np.zeros(arm.n_joints)
    for j, name in enumerate(arm.joint_names):
        sig = stated.get(name)
        if sig is None:
            try:
                sig = build_effect(arm, "joint_offset", name).default_sigma()
            except TargetError:
                sig = [0.0]
        zero[j] = float(np.ravel(np.asarray(sig, float))[0])
    zero.setflags(write=False)
    arm.__dict__["_zero_offset_sigma_rad"] = zero
    return zero


def _feasible_branches(arm: ArmModel, q_all: np.ndarray, locked_any: np.ndarray,
                       margin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct branches inside the limits ``(F, n)`` (every branch when none is), and
    the rows of ``q_all`` that may be the arm's: the feasible ones, or when none is, those
    least outside (flagged out_of_limits later). Locked joints can take any value, so only
    readable joints are checked."""
    inside = (arm.within_limits(q_all, margin) | locked_any).all(1)
    feasible_idx = np.flatnonzero(inside)
    branches = dedupe(q_all[feasible_idx] if len(feasible_idx) else q_all, 1e-3)
    if len(feasible_idx):
        return branches, feasible_idx
    excess = np.sum(np.maximum(0, np.maximum(arm.min_rad - q_all, q_all - arm.max_rad))
                    * ~locked_any, 1)
    return branches, np.flatnonzero(excess <= excess.min() + DEG)


def _linear_covariance(J: np.ndarray, free: np.ndarray, inflate: float) -> np.ndarray:
    """The covariance of every unknown ``(n + 2, n + 2)`` from the weighted Jacobian ``J (m,
    n + 2)`` at the chosen solution, times ``inflate`` (NaN for unknowns not ``free``).

    Information from the data, plus the only thing known about a gravity-blind joint: it
    is somewhere in its range (a flat prior of width pi). Every joint gets that flat
    prior: it costs nothing where the data speak, and where they do not (a singular pair:
    two axes and gravity coplanar) the sigma becomes honestly large instead of being cut
    off by a pseudo-inverse. The marginal sigma of every joint carries its correlation
    with the blind ones."""
    cols = free.copy()
    Jr = J[:, cols]
    info = Jr.T @ Jr
    prior_info = np.full(int(cols.sum()), 1.0 / np.pi**2)
    cov = np.full((len(free), len(free)), np.nan)
    cov_r = np.linalg.inv(info + np.diag(prior_info)) * inflate
    cov[np.ix_(cols, cols)] = cov_r
    return cov


def _weigh_rivals(st: StartupSettings, rivals_x: np.ndarray, sig: np.ndarray, cov: np.ndarray,
                  flags: np.ndarray) -> tuple[list[np.ndarray], list[list[float]]]:
    """Every rival the chooser kept against the chosen state (``rivals_x[0]``): a joint on
    which they differ by more than its sigma can cover is ambiguous; an ill-conditioned
    joint's sigma grows to cover a rival in the same valley instead. Widens ``sig`` and
    ``cov`` and sets ``flags`` in place; returns the candidates kept (the chosen first) and
    each joint's alternative values."""
    n = len(flags)
    xb = rivals_x[0]
    qb = xb[:n]
    limit = st.sigma_limit_deg * DEG
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
    return kept, alternatives


def _joint_estimates(arm: ArmModel, problem: StillWindowProblem, st: StartupSettings,
                     qb: np.ndarray, sig: np.ndarray, flags: np.ndarray, blind: np.ndarray,
                     alternatives: list[list[float]], axis_deg: np.ndarray,
                     ) -> tuple[JointEstimate, ...]:
    """Each joint's estimate: a number and sigma unless it is locked, ambiguous or blind
    (then its range: the limits, or for an ambiguous one its alternatives)."""
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
