"""The branches of a still pose: every set of joint angles that puts gravity where the
sensors read it.

Gravity fixes two angles per accelerometer only up to a discrete set of branches.
:func:`closed_form_branches` enumerates them, walking the chain sensor by sensor (each
pair of joints is the Paden-Kahan "subproblem 2": two rotations that carry one direction
onto another, with up to two solutions); :func:`complete_combinations` crosses the
groups' solutions where the polish lost one; :func:`sequential_solve` is the thesis's
pair-by-pair method (the reference); :func:`dedupe` keeps each branch once.
:func:`fitting_branches` runs them all into every branch that fits a window, and
:func:`feasible_branches` keeps those inside the limits (:func:`limit_margins_rad`).
"""

from __future__ import annotations

import numpy as np
from armfusion.fusion.startup.prior import StartupPrior
from armfusion.fusion.startup.problem import StillWindowProblem, batched_lm
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.models.arm import ArmModel
from armfusion.models.effects.library import JointOffset
from armfusion.models.rotations import DEG, skew, tilt_from_up, up_from_tilt, wrap_angle


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



def closed_form_branches(problem: StillWindowProblem, roll: float, pitch: float) -> np.ndarray:
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


def dedupe(q: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """The rows of ``q`` in order, each left out when within ``tol`` (every angle) of a row
    kept before it."""
    close = (np.abs(wrap_angle(q[:, None] - q[None])).max(-1) < tol).tolist()  # (B, B)
    keep: list[int] = []
    for i, row in enumerate(close):
        if not any(row[k] for k in keep):
            keep.append(i)
    return q[keep]


def _joint_groups(arm: ArmModel, names: list[str]) -> list[np.ndarray]:
    """The joints between one accelerometer and the next along the chain: each group's
    angles are fixed (up to its own branches) by the direction of up at its two ends."""
    links = sorted({arm.sensor(nm).link for nm in names})
    edges = [0, *links]
    groups = [np.arange(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]
    if edges[-1] < arm.n_joints:
        groups.append(np.arange(edges[-1], arm.n_joints))
    return groups


def complete_combinations(problem: StillWindowProblem, x: np.ndarray, cost: np.ndarray,
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
        v = dedupe(q[:, g], 0.5 * DEG)
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
    new, new_cost = batched_lm(problem, combos[~have], np.ones(n + 2, bool), st.max_iterations)
    new[:, :n] = mid + wrap_angle(new[:, :n] - mid)
    return np.vstack([x, new]), np.concatenate([cost, new_cost])


def dedupe_x(rivals_x: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """The chosen state first, then every other rival once."""
    return dedupe(np.vstack([xb[None], rivals_x]), 1e-3) if len(rivals_x) else xb[None]


def sequential_solve(problem: StillWindowProblem, x0: np.ndarray, st: StartupSettings):
    """The thesis's method: each accelerometer solves its own joints, given the ones before.

    acc1 -> joints 1-2, acc2 -> 3-4, acc3 -> 5-6, acc4 -> 7, each by LM with the earlier
    joints held; the base tilt comes from the IMU alone, first.
    """
    arm, n = problem.arm, problem.n
    x = x0.copy()
    if problem.imu_meas is not None:
        free = np.zeros(n + 2, dtype=bool)
        free[n:] = True
        x, _ = batched_lm(problem, x, free, st.max_iterations, active=np.zeros(len(problem.names), bool))
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
        x, _ = batched_lm(problem, x, free, st.max_iterations, active=active, use_imu=False)
        prev = k
    r, _ = problem.residuals_and_jacobian(x)
    return x, 0.5 * np.sum(r**2, 1)


def fitting_branches(problem: StillWindowProblem, st: StartupSettings, prior: StartupPrior | None,
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
              if e.get("effect") == JointOffset.name}
    zero = np.zeros(arm.n_joints)
    for j, name in enumerate(arm.joint_names):
        sig = stated.get(name)
        if sig is None:
            try:
                sig = build_effect(arm, JointOffset.name, name).default_sigma()
            except TargetError:
                sig = [0.0]
        zero[j] = float(np.ravel(np.asarray(sig, float))[0])
    zero.setflags(write=False)
    arm.__dict__["_zero_offset_sigma_rad"] = zero
    return zero


def feasible_branches(arm: ArmModel, q_all: np.ndarray, locked_any: np.ndarray,
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
