"""Naming a link accelerometer's lasting shift (the model-change alarm's second half,
:mod:`armfusion.fusion.tracking.alarm`): where it began in the block means (:func:`onset`),
and which effect explains the blocks since (:func:`name_shift`): a turned board reads
gravity's full size in another direction, so its innovation lies across the predicted force
(``mount_rotation``, the rotation ``dtheta`` of ``nu = [g]x dtheta`` fitted, in degrees); a
bias changes the reading's size too, so it shows along the force (``bias_jump``, the mean
shift, in g)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from armfusion.models.effects.library import AccelBias, MagHardIron, MountRotation
from armfusion.models.rotations import DEG, skew

MOUNT_ROTATION = MountRotation.name
"""The alarm's name for a board turned on its link: the model's own ``mount_rotation``."""
BIAS_JUMP = "bias_jump"
"""The alarm's name for an accelerometer's bias that jumped (the model's ``accel_bias`` changed)."""
HARD_IRON = "hard_iron"
"""The alarm's name for a compass whose hard iron changed (the model's ``mag_hard_iron``)."""
MODEL_EFFECT: dict[str, str] = {MOUNT_ROTATION: MountRotation.name, BIAS_JUMP: AccelBias.name,
                                HARD_IRON: MagHardIron.name}
"""Each change the alarm names, with the model effect (:data:`armfusion.models.effects.EFFECTS`)
whose value it says has changed: what a refit would move."""
ACCEL_EFFECTS = (MOUNT_ROTATION, BIAS_JUMP)
"""The effects an accelerometer's alarm tells apart."""
FLOOR_G = 0.004
"""And against this floor (g): what the model leaves in ordinary use, below any alarm."""
NAME_P = 1e-3
"""The false-naming probability of each of :func:`name_shift`'s tests (chi-square on the
along components): below it the alarm names both effects until the arm's motion separates
them."""
OUTLIER_VAR = 9.0
"""The naming leaves out a block whose variance exceeds this many times the median's (a
sigma three times the typical one)."""
MIN_BLOCKS = 4
"""An effect is decided on at least this many blocks (2 s): a bias on as many kept blocks
since the change, a turn once as many saw a force turned far enough from where the change
began that a bias of the shift's size would have shown along it."""
OBSERVABLE = 1e-4
"""A rotation direction whose information is below this fraction of the best-seen one's is
not fitted (a rotation about a force that never turned)."""


def onset(nu: np.ndarray) -> int:
    """Where a lasting shift began in the block means ``nu (N, 3)`` (oldest first): the
    start ``k`` whose later blocks' mean, times their count, is largest (a shift from
    then on against none before: the change point of a step in white noise)."""
    tail = np.cumsum(nu[::-1], axis=0)[::-1]  # sum of blocks k..N-1
    n = np.arange(len(nu), 0, -1)
    score = np.square(tail).sum(1) / n
    return int(np.argmax(score[: max(len(nu) - 2, 1)]))


@dataclass(frozen=True)
class Naming:
    """What a shift's blocks say: ``effect`` the likelier of :data:`ACCEL_EFFECTS` with its
    ``size`` and 1-sigma ``sigma`` (a rotation in deg, a bias in g), ``candidates`` every
    effect the blocks have not ruled out (``effect`` first; ``(effect,)`` once decided) and
    ``evidence``, the chi-square statistic of the test for ``effect`` (:func:`name_shift`)."""

    effect: str
    size: float
    sigma: float
    candidates: tuple[str, ...]
    evidence: float


def name_shift(nu_g: np.ndarray, g_pred: np.ndarray, var_g2: np.ndarray) -> Naming:
    """Which effect explains block-mean innovations ``nu_g (N, 3)`` seen with predicted
    specific forces ``g_pred (N, 3)`` (both g, sensor axes; ``var_g2 (N,)`` each block's own
    variance per axis: a block more than ``OUTLIER_VAR`` times the median's, where the arm
    lurched or the filter re-acquired, is left out; the others weigh alike).

    A turned board reads gravity's full size, only in another direction: along the
    prediction it is short by ``|g| (1 - cos)`` of the angle between them. A bias changes
    the size too, by ``u . b`` along the predicted force ``u``. The filter, moving joints to
    follow a changed sensor, turns its prediction and so absorbs part of what lies across the
    force, never what lies along it: the components along the force decide, by two
    chi-square tests at ``NAME_P``, the scale from the residuals' own scatter:

    - a bias, when its along part (fitted by least squares, rank-aware: a force that never
      turned fits only ``b`` along it) explains the along components better than the turn
      does (``p`` parameters more), and differs from the turn's by more than ``FLOOR_G`` RMS
      (what the model leaves in ordinary use), on at least ``MIN_BLOCKS`` blocks;
    - a turn, when the shift's mean, taken as a bias, would have shown along the forces seen
      and did not, over the blocks (at least ``MIN_BLOCKS``) where the two differ along the
      force by more than ``FLOOR_G``: the arm turned the sensor far enough since the change;
    - or a turn, when the whole innovation turns with the force as a turned board's does
      (``nu = f x dtheta``, fitted) and a bias's (the shift's mean, constant) does not: the
      turn explains the blocks better than the bias by a chi-square (3 dof) at ``NAME_P``,
      the scale from the turn's residual scatter, over the blocks (at least ``MIN_BLOCKS``)
      where the two differ by more than ``FLOOR_G``. (A force swung far averages a turn's
      innovation out: the mean is no bias that would have shown along it, yet the blocks
      are a turn's. A bias with a part along the force is named by the first test before
      this one is asked.)

    Otherwise both stay candidates (``effect`` the likelier first): a bias across the force
    while the pose does not change is a turn as well, and the arm's motion tells them apart.
    The size: a bias's, the shift's mean; a turn's, the rotation ``dtheta`` of ``nu = [g]x
    dtheta`` fitted to the whole innovation (the rotation about a force that never turned is
    not seen and left at zero), its sigma from the blocks' variance or the fit's residual
    scatter where that is more."""
    blocks = _weigh_blocks(nu_g, g_pred, var_g2)
    turn = _fit_turn(nu_g, g_pred, blocks)
    bias = _fit_bias(nu_g, blocks)
    effect, candidates, evidence = _decide(nu_g, blocks, turn, bias)
    # the size's sigma: the blocks' own variances, or the fit's residual scatter where that
    # is more (the blocks are not white: the filter absorbs part of the change)
    w, sw = blocks.weight, blocks.weight_sum
    dof = max(3 * blocks.count - 3, 1)
    if effect == BIAS_JUMP:
        s2 = max(float((w * np.square(nu_g - bias.mean_g).sum(1)).sum()) / dof, 1.0)
        size, sigma = float(np.linalg.norm(bias.mean_g)), math.sqrt(s2 / sw)
    else:
        th = turn.dtheta_rad
        s2 = max(float((w * np.square(nu_g - turn.H @ th).sum(1)).sum()) / dof, 1.0)
        size = float(np.linalg.norm(th))
        e = th / max(size, 1e-12)
        sigma = math.sqrt(max(float(e @ (s2 * turn.A_pinv) @ e), 0.0)) / DEG
        size /= DEG
    return Naming(effect, size, sigma, candidates, float(evidence))


class _Blocks(NamedTuple):
    """The blocks as the naming weighs them: ``weight (N,)`` (zero for a left-out block),
    ``count`` and ``weight_sum`` of the kept ones, ``u (N, 3)`` the predicted force's
    direction and ``along (N,)`` each innovation's component along it (g)."""

    weight: np.ndarray
    count: int
    weight_sum: float
    u: np.ndarray
    along: np.ndarray


class _TurnFit(NamedTuple):
    """The turn ``nu = [g]x dtheta`` fitted: ``H (N, 3, 3)`` the cross-product matrices of the
    forces, ``dtheta_rad (3,)``, ``A_pinv`` the rank-aware inverse of its information,
    ``rank`` the directions fitted, ``along_g (N,)`` what a turned reading shows along the
    predicted force."""

    H: np.ndarray
    dtheta_rad: np.ndarray
    A_pinv: np.ndarray
    rank: int
    along_g: np.ndarray


class _BiasFit(NamedTuple):
    """The bias: ``mean_g (3,)`` the shift's mean, ``along_g (N,)`` its along part fitted to
    the along components (rank-aware), ``rank`` the directions that fit had."""

    mean_g: np.ndarray
    along_g: np.ndarray
    rank: int


def _weigh_blocks(nu_g: np.ndarray, g_pred: np.ndarray, var_g2: np.ndarray) -> _Blocks:
    """The blocks weigh alike, at their typical variance; one far more uncertain than that
    (the arm lurched, the filter re-acquired) is left out: the variance of the others is no
    block-to-block scatter (the filter's own uncertainty, shared by neighbouring blocks),
    which weighing by it would take for one."""
    var_g2 = np.asarray(var_g2, float)
    v0 = max(float(np.median(var_g2)), 1e-12)
    w = (var_g2 <= OUTLIER_VAR * v0) / v0
    u = g_pred / np.linalg.norm(g_pred, axis=1, keepdims=True)
    return _Blocks(w, int(np.count_nonzero(w)), float(w.sum()), u, (nu_g * u).sum(1))


def _fit_turn(nu_g: np.ndarray, g_pred: np.ndarray, blocks: _Blocks) -> _TurnFit:
    """The turn: ``nu = [g]x dtheta`` over the whole innovation; the rotation about a force
    that never turned is not seen and is left at zero. A turned reading keeps its size:
    along the prediction it is short by ``|g| (1 - cos)`` of the angle between them, whatever
    share of the turn the filter absorbed."""
    w, u, along = blocks.weight, blocks.u, blocks.along
    H = skew(g_pred)  # (N, 3, 3): H @ dtheta == cross(g, dtheta)
    A = np.einsum("n,nji,njk->ik", w, H, H)
    lam, V = np.linalg.eigh(A)
    keep = lam > OBSERVABLE * lam[-1]
    A_pinv = (V[:, keep] / lam[keep]) @ V[:, keep].T
    th = A_pinv @ np.einsum("n,nji,nj->i", w, H, nu_g)
    g_norm = np.linalg.norm(g_pred, axis=1)
    across_rad = np.linalg.norm(nu_g - along[:, None] * u, axis=1) / g_norm
    return _TurnFit(H, th, A_pinv, int(keep.sum()), -g_norm * (1.0 - np.cos(across_rad)))


def _fit_bias(nu_g: np.ndarray, blocks: _Blocks) -> _BiasFit:
    """The bias: its size from the whole innovation, its along part fitted to the along
    components (rank-aware: a force that never turned fits only the bias along it)."""
    w, u, along = blocks.weight, blocks.u, blocks.along
    b_mean = (w[:, None] * nu_g).sum(0) / blocks.weight_sum
    Ab = np.einsum("n,ni,nj->ij", w, u, u)
    lb, Vb = np.linalg.eigh(Ab)
    kb = lb > OBSERVABLE * lb[-1]
    b_along = ((Vb[:, kb] / lb[kb]) @ Vb[:, kb].T) @ (w[:, None] * u * along[:, None]).sum(0)
    return _BiasFit(b_mean, u @ b_along, int(kb.sum()))


def _decide(nu_g: np.ndarray, blocks: _Blocks, turn: _TurnFit,
            bias: _BiasFit) -> tuple[str, tuple[str, ...], float]:
    """The three chi-square tests of :func:`name_shift` and the verdict they give:
    ``(effect, candidates, evidence)``."""
    from scipy.stats import chi2  # (here: the payloads import this module, scipy is slow to import)

    w, N, sw, u, along = blocks
    along_m, along_b, b_mean, p = turn.along_g, bias.along_g, bias.mean_g, bias.rank
    rss_m = float((w * (along - along_m) ** 2).sum())
    rss_b = float((w * (along - along_b) ** 2).sum())
    # a bias: its along part, fitted, beats no along shift (p parameters more: chi-square)
    evidence_b = (rss_m - rss_b) / max(rss_b / max(N - p, 1), 1e-30)
    sep_b = _rms(along_b - along_m, w) > FLOOR_G and N >= MIN_BLOCKS
    # a turn: the shift's own bias would have shown along the forces seen, and did not; the
    # blocks that count are those where the two explanations differ by more than the model
    # leaves (FLOOR_G): a force turned enough since the change
    apart = (w > 0) & (np.abs(u @ b_mean - along_m) > FLOOR_G)
    evidence_m = float((((along - u @ b_mean) ** 2 - (along - along_m) ** 2) * apart).sum()) \
        / max(rss_m / sw, 1e-30)  # over the along components' mean square about the turn
    sep_m = int(apart.sum()) >= MIN_BLOCKS
    # a turn, by the whole innovation: it turns with the force (nu = f x dtheta), a bias stays
    # put; the blocks that count are those where the two differ by more than the floor
    turned = turn.H @ turn.dtheta_rad
    rss_tf = float((w * np.square(nu_g - turned).sum(1)).sum())
    rss_bf = float((w * np.square(nu_g - b_mean).sum(1)).sum())
    apart_f = (w > 0) & (np.linalg.norm(turned - b_mean, axis=1) > FLOOR_G)
    evidence_f = (rss_bf - rss_tf) / max(rss_tf / max(3 * N - turn.rank, 1), 1e-30)
    sep_f = int(apart_f.sum()) >= MIN_BLOCKS
    if evidence_b >= chi2.isf(NAME_P, p) and sep_b:
        return BIAS_JUMP, (BIAS_JUMP,), evidence_b
    if evidence_m >= chi2.isf(NAME_P, 1) and sep_m:  # (an along shift below the floor is no bias)
        return MOUNT_ROTATION, (MOUNT_ROTATION,), evidence_m
    if evidence_f >= chi2.isf(NAME_P, 3) and sep_f:
        return MOUNT_ROTATION, (MOUNT_ROTATION,), evidence_f
    if evidence_b >= chi2.isf(NAME_P, p):  # an along shift, but below what the model leaves
        return BIAS_JUMP, (BIAS_JUMP, MOUNT_ROTATION), evidence_b
    return MOUNT_ROTATION, (MOUNT_ROTATION, BIAS_JUMP), evidence_m


def _rms(x: np.ndarray, w: np.ndarray) -> float:
    return math.sqrt(float((w * x**2).sum() / w.sum()))
