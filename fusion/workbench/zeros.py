"""A held turn read off encoders that give the joints' own angles.

A board turned about the axis of the joint its link turns on reads, in every still pose,
what that joint's zero turned back reads (:mod:`armfusion.fusion.workbench.gauges`): the fit
holds the turn at its prior (none) and lets the recording's joint zeros take it. With
relative encoders that is the only choice: the zeros are the recording's, the turn a
convention. Where the encoders read the joints' own angles (an industrial controller's
absolute angles) the zeros are known, the encoders' own, and the zeros the fit found are
the turn, mis-booked: a config written with the turn at none makes the tracker (which finds
the zeros from gravity through the board) put the link's angle off by the whole turn, on
the UR5 twin the forearm's pitch 0.5-1° off the controller's.

:func:`turns_from_encoder_zeros` moves the fitted zeros of the joints a held turn is the
same as back to the encoders' zeros and books the difference to the held turns, a step
along the gauges (no still reading changes): the turn the data then give is the one the
encoders' zeros imply, known as well as those zeros were fitted.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from armfusion.fusion.identification.data import FitData
from armfusion.fusion.identification.result import Identification
from armfusion.fusion.workbench.gauges import Gauge, still_jacobian
from armfusion.models.rotations import wrap_angle

OWN_ANGLE_Z = 3.0
"""The fitted zeros are the encoders' (the encoders read the joints' own angles) when the turn
that would explain the difference is within this many of its prior σ on every held element:
a relative encoder's zero, the power-up pose's, is tens of degrees off instead."""
GAUGE_TOLERANCE = 1e-6
"""The share of the zeros' still readings the turns must reproduce for the step to be a gauge
(rounding leaves ~1e-12; a zero that a turn cannot stand for leaves its whole reading)."""


@dataclass(frozen=True)
class ZeroTurns:
    """The held turns the encoders' zeros give, and the step that books them."""

    fit: Identification
    """The fit with the zeros at the encoders' and the turns taken up by the held elements."""
    turns: dict[str, tuple[float, float]]
    """Per held element moved, its value and σ (the block's units)."""
    joints: tuple[str, ...]
    """The joints whose fitted zeros were moved back to their encoders'."""


def _zero_index(fit: Identification, joint: str) -> int | None:
    name = f"{joint}.joint_offset[offset]"
    return fit.names.index(name) if name in fit.names else None


def turns_from_encoder_zeros(fit: Identification, data: FitData, gauges: Sequence[Gauge],
                             own_angle: Sequence[str]) -> ZeroTurns | None:
    """The fit with each structural gauge's held turn taken from the encoders' zeros (None where
    there is none, or where the encoders do not read the joints' own angles).

    The encoders read their joints' own angles where both say so: the tracker with the config
    as it is keeps within its σ of them (``own_angle``, the joints
    :func:`armfusion.fusion.workbench.heldout.reads_its_own_angle` finds; every joint a gauge
    names must be among them), and the fit's zeros are the encoders' but for a turn of the
    size the turn's prior allows (:data:`OWN_ANGLE_Z`).

    The zeros of the joints the gauges name (``partners``) are set to the encoders' (``q_ref +
    offset = 0``); the held elements take the turn that changes no still reading
    (:func:`armfusion.fusion.workbench.gauges.still_jacobian`, least squares over the poses),
    with the covariance the fitted zeros give it. Refused (None) when the held elements cannot
    reproduce the zeros' readings (no gauge) or need more than ``OWN_ANGLE_Z`` of their prior."""
    structural = [g for g in gauges if g.structural and any(p.endswith(".joint_offset") for p in g.partners)]
    if not structural:
        return None
    joints = tuple(dict.fromkeys(p.removesuffix(".joint_offset") for g in structural for p in g.partners
                                 if p.endswith(".joint_offset")))
    if not set(joints) <= set(own_angle):
        return None
    held = list(dict.fromkeys(g.held for g in structural))
    # the step takes every element of the gauges' blocks: a gauge's direction is mostly its
    # held element, with a little of the block's others (free in the fit)
    moved = [n for n in fit.names if n.split("[")[0] in {g.block for g in structural}]
    J, names, sig = still_jacobian(fit.model, data)
    col = {n: i for i, n in enumerate(names)}
    zi = [_zero_index(fit, j) for j in joints]
    if any(i is None for i in zi) or any(h not in col for h in moved):
        return None
    jz = np.array([col[f"{j}.joint_offset[offset]"] for j in joints])
    jh = np.array([col[h] for h in moved])
    q_ref = np.array([fit.q_ref_rad[fit.model.arm.joint_names.index(j)] for j in joints])
    zero = wrap_angle(q_ref + fit.x[zi])  # the fitted zeros against the encoders' (rad)
    # J's columns are per prior σ: a step δ in an element is δ / σ in its column
    Jz, Jh = J[:, jz] / sig[jz], J[:, jh] / sig[jh]
    reading = Jz @ zero
    P = np.linalg.pinv(Jh) @ Jz  # turns per zero: the turns that read as the zeros do
    turn = P @ zero
    left = float(np.linalg.norm(Jh @ turn - reading))
    if left > GAUGE_TOLERANCE * float(np.linalg.norm(reading)):
        return None
    hi = [fit.names.index(h) for h in moved]
    prior = fit.prior_sigma[hi]
    if np.any(np.abs(fit.x[hi] + turn - fit.x0[hi]) > OWN_ANGLE_Z * prior):
        return None
    x = fit.x.copy()
    x[zi] -= zero
    x[hi] += turn
    # new = A·old: the moved elements take P·zero on, the zeros are the encoders' (no doubt of
    # their own left); the covariance given the held turns (their prior no longer the doubt)
    A = np.eye(len(fit.x))
    A[np.ix_(hi, zi)] += P
    A[zi, :] = 0.0
    given = _given(fit.covariance, [fit.names.index(h) for h in held])
    cov = A @ given @ A.T
    cov = (cov + cov.T) / 2.0
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    held_mask = fit.held.copy()
    held_mask[hi] = False
    held_mask[zi] = True
    out = replace(fit, x=x, covariance=cov, sigma=sigma, held=held_mask,
                  holds=tuple(h for h in fit.holds if h.element not in held))
    return ZeroTurns(out, {h: (float(x[fit.names.index(h)]), float(sigma[fit.names.index(h)])) for h in held},
                     joints)


def _given(cov: np.ndarray, held: Sequence[int]) -> np.ndarray:
    """``cov`` conditioned on the elements ``held`` (their doubt, the gauge's prior that the
    fit's zeros carry, taken out): what the data tell of the rest with the turns fixed."""
    h = np.asarray(held, int)
    C_hh = cov[np.ix_(h, h)]
    out = cov - cov[:, h] @ np.linalg.solve(C_hh, cov[h, :])
    return (out + out.T) / 2.0
