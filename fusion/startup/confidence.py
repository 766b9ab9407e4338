"""How far each joint's number can be trusted, beyond the Jacobian's linear sigma.

Near a singular pair the cost is flatter than quadratic: :func:`profile_sigma` measures
each wide joint's sigma from the cost itself; :func:`follow_weak_starts` and
:func:`follow_weak` sweep each weak joint across what the data allow and see how far the
others follow; :func:`candidate_covariances` gives every rival its own covariance; and
:func:`thesis_detector` is the thesis's own gimbal-lock test, reported beside ours. The linear
sigmas themselves come from :func:`linear_covariance`, and :func:`weigh_rivals` widens them
(or flags a joint ambiguous) where a rival branch fits as well.
"""

from __future__ import annotations

import numpy as np
from armfusion.fusion.startup.problem import StillWindowProblem, batched_lm, expected_covariance
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, wrap_angle


def profile_sigma(problem: StillWindowProblem, xb: np.ndarray, cost_b: float, sig: np.ndarray,
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
    probes, cost = batched_lm(problem, starts, free, 12)
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


def follow_weak_starts(xb: np.ndarray, sig: np.ndarray, weak: np.ndarray, locked: np.ndarray):
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


def follow_weak(x: np.ndarray, cost: np.ndarray, j_of: np.ndarray, xb: np.ndarray,
                 cost_b: float, locked: np.ndarray, inflate: float) -> np.ndarray:
    """How far each joint moves while each weak joint sweeps what the data allow, from the
    re-solved points ``x`` (and their ``cost``) of :func:`follow_weak_starts`: ``(n_weak,
    n)`` rad. Points whose fit is worse than a 3-sigma change (chi-square 9) are not
    allowed, except for a locked joint (the data say nothing about it)."""
    n = len(locked)
    allowed = locked[j_of] | ((cost - cost_b) / inflate <= 4.5)
    moved = np.abs(wrap_angle(x[:, :n] - xb[:n])) * allowed[:, None]
    moved[np.arange(len(j_of)), j_of] = 0.0
    return np.stack([moved[j_of == j].max(0) for j in np.unique(j_of)])


def candidate_covariances(problem: StillWindowProblem, kept: list[np.ndarray], cov_best: np.ndarray,
                           scale: float) -> np.ndarray:
    """Each candidate's covariance: the chosen one's as the checks left it; a rival's from
    its own Jacobian, its sigmas no smaller than the chosen one's (the profile and the sweep
    widened those; a rival's linear sigmas know nothing of its valley)."""
    out = [cov_best]
    if len(kept) > 1:
        rivals = expected_covariance(problem, np.array(kept[1:])) * scale
        floor = np.sqrt(np.clip(np.diag(cov_best), 0, None))
        for c in rivals:
            lin = np.sqrt(np.clip(np.diag(c), 1e-30, None))
            w = np.maximum(np.where(np.isfinite(floor), floor, 0.0) / lin, 1.0)
            out.append(c * np.outer(w, w))
    return np.array(out)


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


def linear_covariance(J: np.ndarray, free: np.ndarray, inflate: float) -> np.ndarray:
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


def weigh_rivals(st: StartupSettings, rivals_x: np.ndarray, sig: np.ndarray, cov: np.ndarray,
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
