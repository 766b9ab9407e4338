"""The moves the solve proposes, and the prior a counted move carries to the next window.

Nothing here moves the arm. When joints are gravity-blind, :func:`propose_unlock_move`
finds the smallest move of a well-known joint that would make them readable; when rival
branches fit the data equally well, :func:`propose_disambiguating_move` finds the smallest
safe move after which they read far apart. After a move the encoders counted,
:func:`prior_after_move` carries every candidate of the first window to the second
(:func:`move_delta_rad`: what a move changes, every joint).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.fusion.startup.prior import StartupPrior
from armfusion.fusion.startup.problem import (
    StillWindowProblem,
    axis_to_vertical,
    expected_sigma,
    make_problem,
)
from armfusion.fusion.startup.readings import StillReadings
from armfusion.fusion.startup.results import DisambiguatingMove, StartupResult, UnlockMove
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, wrap_angle

MAX_MOVE_DEG = 45.0
"""The largest move of one joint the startup proposes (the unlock and disambiguating moves)."""


def moves_within_limits(arm: ArmModel, q_from_rad: np.ndarray, q_to_rad: np.ndarray,
                        max_move_deg: float = MAX_MOVE_DEG) -> np.ndarray:
    """The checks a proposed move must pass, for moves from ``q_from_rad`` (``(n,)`` or
    ``(M, n)``) to ``q_to_rad (M, n)``: every joint it moves ends inside the arm's limits and
    moves by at most ``max_move_deg`` (a joint it keeps is where the arm is, whatever its
    limits say). ``(M,)`` bool."""
    q0 = np.asarray(q_from_rad, float)
    q1 = np.atleast_2d(np.asarray(q_to_rad, float))
    delta = q1 - q0
    inside = (q1 >= arm.min_rad) & (q1 <= arm.max_rad) & (np.abs(delta) <= max_move_deg * DEG + 1e-12)
    return np.all(inside | (delta == 0), axis=1)


def propose_unlock_move(arm: ArmModel, result: StartupResult, readings: StillReadings,
                        settings: StartupSettings | None = None,
                        prior_q_rad: np.ndarray | None = None,
                        max_move_deg: float = MAX_MOVE_DEG,
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
    problem = make_problem(arm, readings)
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


@dataclass(frozen=True)
class _Rivals:
    """What a disambiguating move is judged against: the rival branches of one still window
    and what the next window will know of them. Built once per proposal."""

    arm: ArmModel
    problem: StillWindowProblem
    candidates_rad: np.ndarray
    """The rival poses, ``(R, n)`` rad."""
    roll_pitch_rad: np.ndarray
    """The base's roll and pitch, ``(2,)`` rad."""
    ambiguous: np.ndarray
    """The joints to resolve, ``(n,)`` bool."""
    unsure: np.ndarray
    """The joints read but not to a number, ``(n,)`` bool: a move of one keeps a margin."""
    pair_a: np.ndarray
    pair_b: np.ndarray
    """Every pair of rivals: ``candidates_rad[pair_a[k]]`` against ``candidates_rad[pair_b[k]]``."""
    carried_cov_rad2: np.ndarray
    """The covariance the next window starts from, as the encoders carry it, ``(n + 2, n + 2)``."""
    settings: StartupSettings


def propose_disambiguating_move(arm: ArmModel, result: StartupResult, readings: StillReadings,
                                settings: StartupSettings | None = None,
                                roll_pitch: np.ndarray | None = None,
                                max_move_deg: float = MAX_MOVE_DEG) -> DisambiguatingMove | None:
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
    rp = np.array([result.roll_rad, result.pitch_rad]) if roll_pitch is None else np.asarray(roll_pitch)
    flags = [j.flag for j in result.joints]
    known = [j for j in range(n) if flags[j] == "ok"]
    # joints the data read but not to a number: ambiguous or weak ones, and those flagged
    # only for resting on a locked joint (their own axis is clear of vertical); a move of
    # one of them keeps a margin inside its limits, at every candidate
    unsure = [j for j in range(n) if flags[j] in ("ambiguous", "ill_conditioned", "out_of_limits")
              or (flags[j] == "gimbal_lock" and result.joints[j].axis_to_vertical_deg
                  >= 2 * st.gimbal_lock_deg)]
    ia, ib = np.triu_indices(len(cands), 1)
    rivals = _Rivals(arm, make_problem(arm, readings), cands, rp,
                     np.array([j.flag == "ambiguous" for j in result.joints]),
                     np.isin(np.arange(n), unsure), ia, ib, _carried_covariance(result, st, n), st)
    found = _smallest_separating_move(rivals, _move_classes(known, unsure, max_move_deg))
    if found is None:
        return None
    m, sep = found
    return DisambiguatingMove(
        joints=tuple(arm.joints[j].name for j, _ in m),
        delta_rad=tuple(float(d) for _, d in m),
        separation_sigma=float(np.sqrt(sep)),
        resolves=tuple(j.name for j in result.joints if j.flag == "ambiguous"))


def _carried_covariance(result: StartupResult, st: StartupSettings, n: int) -> np.ndarray:
    """What the next window knows of each rival: this window's covariance (as the encoders
    carry it), the joints it could not read anywhere in their turn."""
    carried = np.array(result.covariance, float)
    bad = ~np.isfinite(np.diag(carried))
    carried[bad, :] = carried[:, bad] = 0.0
    carried[bad, bad] = np.pi**2
    # (the result's covariance is already scaled to the sigmas its checks arrived at)
    carried[np.diag_indices(n)] += (st.encoder_carry_sigma_deg * DEG) ** 2
    return carried


def _move_classes(known: list[int], unsure: list[int], max_move_deg: float):
    """The candidate moves in classes of growing size, each a function that builds its list
    (built only when the smaller classes found nothing): single moves of the known joints,
    pairs of them, single moves of the unsure joints, pairs of any. A move is a tuple of
    ``(joint index, delta rad)``, each list ordered smallest first."""
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

    return (lambda: singles(known), lambda: pairs(known), lambda: singles(unsure),
            lambda: pairs(known + unsure))


def _smallest_separating_move(rivals: _Rivals, classes, chunk_size: int = 64):
    """The first move, class by class and smallest first, that separates the rivals:
    ``(move, chi-square)`` or None.

    After the move every joint should be readable, whichever rival is true (a joint still
    weak leaves the next window with rivals of its own); failing that, at least the joints
    to resolve. Within the class where a move does the second, one that does the first is
    preferred."""
    fallback = None
    for make in classes:
        moves = make()
        for i in range(0, len(moves), chunk_size):
            found = _separating(rivals, moves[i:i + chunk_size])
            if found is None:
                continue
            m, sep, every = found
            if every:
                fallback = (m, sep)
                break
            fallback = fallback or (m, sep)
        if fallback is not None:
            return fallback
    return None


def _separating(rivals: _Rivals, chunk, unsure_margin_deg=5.0):
    """The first move of ``chunk`` (ordered by size) that keeps every rival inside the
    limits, leaves the ambiguous joints readable (axis off vertical, expected sigma within
    half the limit, at every rival), and separates every pair of rivals by
    ``settings.separation_chi2``: ``(move, chi-square, every joint readable too)``,
    preferring the last; or None."""
    arm, problem, cands, rp = rivals.arm, rivals.problem, rivals.candidates_rad, rivals.roll_pitch_rad
    amb, unsure, ia, ib, st = rivals.ambiguous, rivals.unsure, rivals.pair_a, rivals.pair_b, rivals.settings
    carried = rivals.carried_cov_rad2
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
    axis = np.degrees(axis_to_vertical(arm, x[:, :n], x[:, n], x[:, n + 1]))
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
    """The first of ``moves`` (ordered by size) that keeps the arm inside its limits and
    makes the blind joints ``L`` readable at every value in ``blind_values``, or None."""
    n = arm.n_joints
    targets = np.tile(base, (len(moves), 1))
    for i, m in enumerate(moves):
        for j, d in m:
            targets[i, j] = base[j] + d
    ok_moves = [m for m, ok in zip(moves, moves_within_limits(arm, base, targets, np.inf), strict=True) if ok]
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
    ang = np.degrees(axis_to_vertical(arm, Q, x[:, n], x[:, n + 1])).reshape(len(ok_moves), G, n)
    sig = expected_sigma(problem, x).reshape(len(ok_moves), G, -1)[..., :n]
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
