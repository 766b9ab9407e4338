"""The model-change alarm: a lasting change of the sensor model while the arm is used.

A link accelerometer knocked loose (its mount rotated by a degree or two) or whose bias
jumped leaves a lasting shift in its innovations that the filter cannot absorb into the
joint angles for every pose; a magnetometer that gained hard iron reads off Earth's field
(the compass's ``disturbed``) and never recovers. :class:`ModelChangeAlarm` watches:

- per link accelerometer, the innovations (g, sensor axes) and the predicted specific
  force, averaged in blocks of ``BLOCK_S`` while the base behaves as modelled; an
  exponential average of the block means over ``TAU_S`` is tested against
  ``max(THRESHOLD_SIGMA`` x its noise, ``FLOOR_G``, ``UNMODELLED_FACTOR`` x the config's
  unmodelled error); a test that holds for ``HOLD_S`` raises one alarm, on the sensor that
  shifted first (the filter, moving joints to follow it, shifts the sensors that share
  them: their tests start again ``QUIET_S`` later). After a re-acquisition (the slip
  detector widening the joints a disagreeing sensor sees, through which the filter follows
  a turned board by degrees), the blocks are taken against the joint offsets held before
  it where the other sensors agree with those (:meth:`ModelChangeAlarm.reacquired`,
  ``REF_HOLD_S``): a turned board shows its turn there, on itself alone; an encoder slip,
  which every sensor beyond the joint follows, does not. The change's onset is the change point
  of the sensor's block means (:func:`onset`); the blocks since then name it
  (:func:`name_shift`): a turned board reads gravity's full size in another direction, so
  its innovation lies across the predicted force (``mount_rotation``, the rotation
  ``dtheta`` of ``nu = [g]x dtheta`` fitted, in degrees); a bias changes the reading's size
  too, so it shows along the force (``bias_jump``, the mean shift, in g). A bias across
  gravity while the pose does not change reads as a turn would: the alarm is raised naming
  both (``Alarm.candidates``, the likelier first) and named again with every block until
  the arm's motion has told them apart (``Alarm.named_s``);
- the compass: disturbed (off Earth's field as estimated) for ``HARD_IRON_AFTER_S`` without
  a break (``hard_iron``, size: the median of the field magnitude's error, µT, its sigma
  their spread).

Each alarm is an :class:`Alarm` (sensor, effect, size with sigma, when it began, when it
was raised, the effects not yet told apart, when it was named);
:attr:`ModelChangeAlarm.version` counts the changes of the active alarms a listener would
publish. An alarmed accelerometer is down-weighted until :meth:`ModelChangeAlarm.clear`
(recalibrated): the variance of its readings per axis is widened by (``WIDEN`` x the
change's size)² (g²; a rotation's size as ``size x 1 g``), :meth:`ModelChangeAlarm.widen`. A
disturbed compass is already not fused (the compass's own verdict).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.tracking.tracker_kernels import add_block_sums
from armfusion.models.rotations import DEG, skew

BLOCK_S = 0.5
"""Innovations are averaged over blocks this long (s) before the test."""
TAU_S = 3.0
"""The test's exponential average of block means (s)."""
THRESHOLD_SIGMA = 6.0
"""The average's size against its noise (white innovations) that counts as a shift."""
FLOOR_G = 0.004
"""And against this floor (g): what the model leaves in ordinary use, below any alarm."""
UNMODELLED_FACTOR = 2.0
"""Or against this many times the config's unmodelled error (``accel_unmodelled_g``)."""
HOLD_S = 3.0
"""A shift must hold this long (s) to raise an alarm."""
WINDOW_S = 60.0
"""The naming fit uses at most this much of the shift's history (s)."""
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
RECENT_S = 20.0
"""A block's noise is at most the median of the last this many seconds' (s)."""
WIDEN = 5.0
"""An alarmed accelerometer's readings are widened by this many times the change's size."""
STICKY_S = 10.0
"""A sensor's first crossing counts for the culprit until its test has not held for this long (s)."""
QUIET_S = 60.0
"""After an accelerometer's alarm, the others' tests start again (s): the filter, moving
joints to follow the changed sensor, shifts the sensors that share them for a while."""
REF_HOLD_S = 60.0
"""The joint offsets held before a re-acquisition are the innovations' reference until this
long after the last one (s): the slip detector widens the joints a disagreeing sensor sees,
and the filter, reading them again, follows a turned board into them (its innovations fall
back under the test); against the offsets held before, the turn shows in full on that
sensor alone."""
HARD_IRON_AFTER_S = 20.0
"""A compass disturbed this long without a break (s) has gained hard iron."""

EFFECTS = ("mount_rotation", "bias_jump", "hard_iron")
ACCEL_EFFECTS = ("mount_rotation", "bias_jump")
"""The effects an accelerometer's alarm tells apart."""
UNITS = {"mount_rotation": "deg", "bias_jump": "g", "hard_iron": "uT"}
"""Each effect's size unit."""


@dataclass(frozen=True)
class Alarm:
    """One model change: ``sensor``, ``effect`` (one of :data:`EFFECTS`), ``size`` with
    its 1-sigma ``sigma`` in ``unit`` (``deg``, ``g``, ``uT``), ``since_s`` (when the shift
    began, as the test saw it), ``raised_s`` (when the alarm was raised); ``candidates``:
    the effects not yet told apart, ``effect`` (the likelier) first, ``(effect,)`` once
    decided (the default), and ``named_s`` when that was (``None`` while undecided)."""

    sensor: str
    effect: str
    size: float
    sigma: float
    unit: str
    since_s: float
    raised_s: float
    candidates: tuple[str, ...] = ()
    named_s: float | None = None

    def __post_init__(self):
        if not self.candidates:
            object.__setattr__(self, "candidates", (self.effect,))
            if self.named_s is None:
                object.__setattr__(self, "named_s", self.raised_s)

    @property
    def decided(self) -> bool:
        return len(self.candidates) == 1

    def line(self) -> str:
        """For a person: ``acc3 mount_rotation 2.10 ± 0.31 deg since 120.5 s``, or while
        undecided ``acc3 mount_rotation 2.10 ± 0.31 deg or bias_jump (not yet told apart)
        since 120.5 s``."""
        alt = "" if self.decided else f" or {', '.join(self.candidates[1:])} (not yet told apart)"
        return (f"{self.sensor} {self.effect} {self.size:.3g} ± {self.sigma:.2g} {self.unit}{alt} "
                f"since {self.since_s:.1f} s")

    @classmethod
    def of_dict(cls, d: dict) -> Alarm:
        """From :meth:`as_dict`'s form."""
        return cls(**{**d, "candidates": tuple(d["candidates"])})

    def as_dict(self) -> dict:
        return {"sensor": self.sensor, "effect": self.effect, "size": round(self.size, 6),
                "sigma": round(self.sigma, 6), "unit": self.unit, "since_s": self.since_s,
                "raised_s": self.raised_s, "candidates": list(self.candidates),
                "named_s": self.named_s}


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
    from scipy.stats import chi2  # (here: the payloads import this module, scipy is slow to import)

    # the blocks weigh alike, at their typical variance; one far more uncertain than that (the
    # arm lurched, the filter re-acquired) is left out: the variance of the others is no
    # block-to-block scatter (the filter's own uncertainty, shared by neighbouring blocks),
    # which weighing by it would take for one
    var_g2 = np.asarray(var_g2, float)
    v0 = max(float(np.median(var_g2)), 1e-12)
    w = (var_g2 <= OUTLIER_VAR * v0) / v0
    N = int(np.count_nonzero(w))
    sw = float(w.sum())
    u = g_pred / np.linalg.norm(g_pred, axis=1, keepdims=True)
    along = (nu_g * u).sum(1)
    # the turn: nu = [g]x dtheta over the whole innovation; the rotation about a force that
    # never turned is not seen and is left at zero
    H = skew(g_pred)  # (N, 3, 3): H @ dtheta == cross(g, dtheta)
    A = np.einsum("n,nji,njk->ik", w, H, H)
    lam, V = np.linalg.eigh(A)
    keep = lam > OBSERVABLE * lam[-1]
    A_pinv = (V[:, keep] / lam[keep]) @ V[:, keep].T
    th = A_pinv @ np.einsum("n,nji,nj->i", w, H, nu_g)
    # a turned reading keeps its size: along the prediction it is short by |g| (1 - cos) of
    # the angle between them, whatever share of the turn the filter absorbed
    g_norm = np.linalg.norm(g_pred, axis=1)
    across_rad = np.linalg.norm(nu_g - along[:, None] * u, axis=1) / g_norm
    along_m = -g_norm * (1.0 - np.cos(across_rad))
    # the bias: its size from the whole innovation, its along part fitted to the along
    # components (rank-aware)
    b_mean = (w[:, None] * nu_g).sum(0) / sw
    Ab = np.einsum("n,ni,nj->ij", w, u, u)
    lb, Vb = np.linalg.eigh(Ab)
    kb = lb > OBSERVABLE * lb[-1]
    b_along = ((Vb[:, kb] / lb[kb]) @ Vb[:, kb].T) @ (w[:, None] * u * along[:, None]).sum(0)
    along_b = u @ b_along
    rss_m = float((w * (along - along_m) ** 2).sum())
    rss_b = float((w * (along - along_b) ** 2).sum())
    p = int(kb.sum())
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
    turn = H @ th
    rss_tf = float((w * np.square(nu_g - turn).sum(1)).sum())
    rss_bf = float((w * np.square(nu_g - b_mean).sum(1)).sum())
    apart_f = (w > 0) & (np.linalg.norm(turn - b_mean, axis=1) > FLOOR_G)
    evidence_f = (rss_bf - rss_tf) / max(rss_tf / max(3 * N - int(keep.sum()), 1), 1e-30)
    sep_f = int(apart_f.sum()) >= MIN_BLOCKS
    if evidence_b >= chi2.isf(NAME_P, p) and sep_b:
        effect, candidates, evidence = "bias_jump", ("bias_jump",), evidence_b
    elif evidence_m >= chi2.isf(NAME_P, 1) and sep_m:  # (an along shift below the floor is no bias)
        effect, candidates, evidence = "mount_rotation", ("mount_rotation",), evidence_m
    elif evidence_f >= chi2.isf(NAME_P, 3) and sep_f:
        effect, candidates, evidence = "mount_rotation", ("mount_rotation",), evidence_f
    elif evidence_b >= chi2.isf(NAME_P, p):  # an along shift, but below what the model leaves
        effect, candidates, evidence = "bias_jump", ("bias_jump", "mount_rotation"), evidence_b
    else:
        effect, candidates, evidence = "mount_rotation", ("mount_rotation", "bias_jump"), evidence_m
    # the size's sigma: the blocks' own variances, or the fit's residual scatter where that
    # is more (the blocks are not white: the filter absorbs part of the change)
    dof = max(3 * N - 3, 1)
    if effect == "bias_jump":
        s2 = max(float((w * np.square(nu_g - b_mean).sum(1)).sum()) / dof, 1.0)
        size, sigma = float(np.linalg.norm(b_mean)), math.sqrt(s2 / sw)
    else:
        s2 = max(float((w * np.square(nu_g - H @ th).sum(1)).sum()) / dof, 1.0)
        size = float(np.linalg.norm(th))
        e = th / max(size, 1e-12)
        sigma = math.sqrt(max(float(e @ (s2 * A_pinv) @ e), 0.0)) / DEG
        size /= DEG
    return Naming(effect, size, sigma, candidates, float(evidence))


def _rms(x: np.ndarray, w: np.ndarray) -> float:
    return math.sqrt(float((w * x**2).sum() / w.sum()))


class ModelChangeAlarm:
    """The alarm over the link accelerometers ``names`` and the compass (``mag_name``)."""

    def __init__(self, names: tuple[str, ...], mag_name: str | None, t_s: float,
                 unmodelled_g: np.ndarray | None = None, sees: np.ndarray | None = None):
        n = len(names)
        # which joints each link accelerometer sees (S, n_joints): a turn it follows moves those
        self._sees = np.zeros((n, 0), bool) if sees is None else np.asarray(sees, bool)[:n]
        self._offset_ref: np.ndarray | None = None
        self._ref_until = -np.inf
        # the test's floor: FLOOR_G, or UNMODELLED_FACTOR x what the config says its model
        # leaves unexplained (an uncalibrated sensor's lasting, pose-dependent error is
        # no change: only a change well above it is)
        um = np.zeros(n) if unmodelled_g is None else np.asarray(unmodelled_g, float)
        self.floor_g = np.maximum(FLOOR_G, UNMODELLED_FACTOR * um)
        self.names, self.mag_name = names, mag_name
        self._sum_nu = np.zeros((n, 3))
        self._sum_moved = np.zeros((n, 3))  # the offsets' move's share (see _moved), while held
        self._sum_g = np.zeros((n, 3))
        self._sum_var = np.zeros(n)
        self._sum_r = np.zeros(n)
        self._n = np.zeros(n, dtype=np.int64)
        self._every = np.arange(n, dtype=np.int64)
        self._block_t = float(t_s)
        self._ema = np.zeros((n, 3))
        self._ema_t = np.full(n, np.nan)
        self._over_since = np.full(n, np.nan)
        self._quiet_until = -np.inf
        self._first_over = np.full(n, np.nan)  # sticky: kept STICKY_S after the test last held
        self._last_over = np.full(n, -np.inf)
        cap = int(WINDOW_S / BLOCK_S) + 1
        self._hist = np.zeros((n, cap, 8))  # per block: t, nu (3), g (3), its own variance
        self._hist_var = np.zeros((n, cap))
        self._hist_n = np.zeros(n, dtype=np.int64)
        self._mag_since: float | None = None
        self.active: dict[str, Alarm] = {}
        """The raised alarms not cleared, by sensor."""
        self.raised: list[Alarm] = []
        """Every alarm raised, oldest first (a log; cleared ones stay)."""
        self.widen_g2 = np.zeros(n)
        """Per link accelerometer: the variance (g², per axis) added to its readings."""
        self.version = 0
        """Counts the changes of :attr:`active` (an alarm raised, named again or cleared)."""


    # -- the accelerometers -------------------------------------------------------------
    def reacquired(self, t: float, offset_rad: np.ndarray) -> None:
        """The slip detector re-acquires at ``t`` (it widens joints for the filter to read
        again): the joint offsets ``offset_rad`` the filter held until now are kept as the
        reference (:meth:`listen` tests the innovations against them) until ``REF_HOLD_S``
        after the last re-acquisition."""
        if not t < self._ref_until:
            self._offset_ref = np.array(offset_rad, dtype=float)
        self._ref_until = t + REF_HOLD_S

    def _moved(self, idx: np.ndarray, z_pred: np.ndarray, rows: np.ndarray, frame,
               offset_rad: np.ndarray | None) -> np.ndarray:
        """How much the filter's move of the joint offsets since the reference
        (:meth:`reacquired`) changed the predictions of the link accelerometers ``idx``
        (``rows (k, 3)``: their rows of ``z_pred``): the innovation against the reference is
        the filter's plus this, to first order ``f x (R_0S^T w)``, ``w = sum_j (offset_j -
        ref_j) a_j`` over the joints each sees (``a_j`` their axes, ``f`` the predicted force)."""
        if offset_rad is None or frame is None:
            return np.zeros((len(idx), 3))
        d = np.asarray(offset_rad, float) - self._offset_ref
        w = (self._sees[idx] * d) @ frame.axes  # (k, 3), base axes
        a = np.einsum("kji,kj->ki", frame.R_0S[idx], w)  # in each sensor's axes
        return np.cross(z_pred[rows], a)

    def listen(self, t: float, u, nu: np.ndarray, Su: np.ndarray, z_pred: np.ndarray, var: np.ndarray,
               rows: np.ndarray, sel: np.ndarray, calm: bool, frame=None,
               offset_rad: np.ndarray | None = None) -> None:
        """The usable accelerometers ``u`` (a slice of ``sel``, every one in order, or sensor
        indices) gave innovations ``nu (k, 3)`` (g) with covariances ``Su``; ``z_pred`` and
        ``var`` are the update's predictions and measurement variances (``rows``: each
        accelerometer's three, by its place in ``sel``). Only while ``calm`` (the base as
        modelled) are they counted; the link accelerometers (the first ``len(names)``) only.
        ``frame`` (the instant's kinematics) and ``offset_rad`` (the filter's joint offsets)
        give the innovations against the offsets held before a re-acquisition
        (:meth:`reacquired`).

        A block mean's variance: the measurement noise's share averages down with the
        samples, the filter's own uncertainty (``Su`` less the noise) does not."""
        nl = len(self.names)
        if calm and self._offset_ref is not None and t < self._ref_until:
            if type(u) is slice:
                pos = np.arange(min(nl, len(nu)))
                idx = self._every[pos]
            else:
                pos = np.flatnonzero(u < nl)
                idx = u[pos]
            if len(pos):
                self._sum_moved[idx] += self._moved(idx, z_pred, rows[np.searchsorted(sel, idx)], frame,
                                                    offset_rad)
        if calm:  # (the sums, compiled: add_block_sums)
            if type(u) is slice:
                k = min(nl, len(nu))
                add_block_sums(self._every[:k], nu[:k], Su[:k], z_pred, var, rows[:k], self._sum_nu,
                               self._sum_g, self._sum_r, self._sum_var, self._n)
            else:
                keep = u < nl
                idx = u[keep]
                add_block_sums(idx, nu[keep], Su[keep], z_pred, var, rows[np.searchsorted(sel, idx)],
                               self._sum_nu, self._sum_g, self._sum_r, self._sum_var, self._n)
        if t - self._block_t >= BLOCK_S:
            if self._n.any():
                self._block(t)
            self._sum_nu[:] = 0.0
            self._sum_moved[:] = 0.0
            self._sum_g[:] = 0.0
            self._sum_r[:] = 0.0
            self._sum_var[:] = 0.0
            self._n[:] = 0
            self._block_t = t

    def _block(self, t: float) -> None:
        have = np.flatnonzero(self._n > 0)
        n_ = self._n[have].astype(float)
        nu = self._sum_nu[have] / n_[:, None]
        g = self._sum_g[have] / n_[:, None]
        # per axis, of a block mean: the noise's share over n samples, the state's whole
        var = self._sum_r[have] / n_ / n_ + self._sum_var[have] / n_
        own = var.copy()  # the block's own, for the naming: a far more uncertain block is left out
        # the filter's uncertainty grows once a changed sensor disagrees (its gate, a
        # re-acquisition): the test keeps the noise of the last RECENT_S where that is less
        cap = self._hist.shape[1]
        m = np.minimum(self._hist_n[have], cap)
        recent = int(RECENT_S / BLOCK_S)
        for j, s in enumerate(have.tolist()):
            if m[j] >= recent:
                rows = (self._hist_n[s] - 1 - np.arange(recent)) % cap
                var[j] = min(var[j], float(np.median(self._hist_var[s, rows])))
        nu = self._reference_or_filter(nu, self._sum_moved[have] / n_[:, None], var, self.floor_g[have])
        last = self._ema_t[have]
        dt = np.where(np.isnan(last), BLOCK_S, t - last)
        a = np.minimum(1.0, dt / TAU_S)
        self._ema_t[have] = t
        self._ema[have] += a[:, None] * (nu - self._ema[have])
        sd = np.sqrt(var * a / (2.0 - a))
        size = np.linalg.norm(self._ema[have], axis=1) / np.maximum(THRESHOLD_SIGMA * sd, self.floor_g[have])
        over = size > 1.0
        ratio = np.zeros(len(self.names))
        ratio[have] = size
        quiet = t < self._quiet_until
        for j, s in enumerate(have.tolist()):
            row = self._hist_n[s] % cap
            self._hist[s, row, 0] = t
            self._hist[s, row, 1:4] = nu[j]
            self._hist[s, row, 4:7] = g[j]
            self._hist[s, row, 7] = own[j]
            self._hist_var[s, row] = var[j]
            self._hist_n[s] += 1
            al = self.active.get(self.names[s])
            if al is not None and not al.decided:  # wait for the motion to tell the effects apart
                h = self._history(s)
                self._name(s, h[h[:, 0] > al.since_s], al.since_s, al.raised_s, t)
            if not over[j] or quiet or al is not None:
                self._over_since[s] = np.nan
                if quiet or t - self._last_over[s] > STICKY_S:
                    self._first_over[s] = np.nan
                continue
            self._last_over[s] = t
            if np.isnan(self._over_since[s]):
                self._over_since[s] = t
            if np.isnan(self._first_over[s]):
                self._first_over[s] = t
        held = np.flatnonzero(t - self._over_since >= HOLD_S)  # (nan compares False)
        if len(held):
            # the culprit: the first sensor to shift, though the filter may since have
            # pulled its innovation back under the test by moving the joints it shares with
            # the others (which then shift); the largest shift among those that shifted together
            on = np.flatnonzero(~np.isnan(self._first_over))
            first = self._first_over[on].min()
            tied = on[self._first_over[on] < first + 0.5 * BLOCK_S]  # the same block
            self._raise_accel(int(tied[np.argmax(ratio[tied])]), t)
            self._over_since[:] = np.nan
            self._first_over[:] = np.nan
            self._quiet_until = t + QUIET_S

    @staticmethod
    def _reference_or_filter(nu: np.ndarray, moved: np.ndarray, var: np.ndarray,
                             floor_g: np.ndarray) -> np.ndarray:
        """The block means to test: the filter's innovations ``nu`` or those against the
        offsets held before a re-acquisition (``nu + moved``), whichever the sensors whose
        predictions the move changed (by more than the floor) agree with, but for the one
        that disagrees most (a changed sensor is one): an encoder that slipped moves every
        sensor beyond its joint, which agree with the filter's new offsets; a turned board
        the filter followed leaves the others agreeing with the reference. A move that at
        most one sensor sees is a slip as well as a turn: the filter's innovations stay."""
        M = np.linalg.norm(moved, axis=1) > floor_g
        if M.sum() < 2:
            return nu
        ref = (np.square(nu + moved).sum(1) / var)[M]
        new = (np.square(nu).sum(1) / var)[M]
        if ref.sum() - ref.max() < new.sum() - new.max():
            return nu + moved
        return nu

    def _history(self, s: int) -> np.ndarray:
        """Sensor ``s``'s blocks kept (at most ``WINDOW_S``), oldest first: ``(m, 8)``."""
        m = min(int(self._hist_n[s]), self._hist.shape[1])
        h = self._hist[s, :m]
        return h[np.argsort(h[:, 0])]

    def _raise_accel(self, s: int, t: float) -> None:
        h = self._history(s)
        k = onset(h[:, 1:4])
        since = round(float(h[k, 0]) - BLOCK_S, 3)  # the block's first sample
        self._name(s, h[k:], since, round(t, 3), t)
        self._ema[s] = 0.0

    def _name(self, s: int, h: np.ndarray, since_s: float, raised_s: float, t: float) -> None:
        """Name (or name again) sensor ``s``'s alarm from its blocks ``h`` since the change."""
        n = name_shift(h[:, 1:4], h[:, 4:7], h[:, 7])
        alarm = Alarm(self.names[s], n.effect, n.size, n.sigma, UNITS[n.effect], since_s, raised_s,
                      n.candidates, round(t, 3) if len(n.candidates) == 1 else None)
        old = self.active.get(alarm.sensor)
        self.active[alarm.sensor] = alarm
        if old is None or set(old.candidates) != set(alarm.candidates):  # published again (the size
            # and which candidate is the likelier ride along with the next)
            self.version += 1
        if old is None:
            self.raised.append(alarm)
        else:  # the same change, named better: the log keeps one entry for it
            self.raised[self.raised.index(old)] = alarm
        size_g = n.size * DEG if n.effect == "mount_rotation" else n.size  # a rotation's force, g
        self.widen_g2[s] = (WIDEN * size_g) ** 2

    def widen(self, sel: np.ndarray, var: np.ndarray) -> None:
        """Add each alarmed accelerometer's widening to the update's variances ``var`` (the
        accelerometers ``sel`` first, three rows each), in place."""
        if not self.widen_g2.any():  # (a compass alarm only, or an arm without link accelerometers)
            return
        k = len(sel)
        extra = self.widen_g2[np.minimum(sel, len(self.names) - 1)] * (sel < len(self.names))
        var[:3 * k] += np.repeat(extra, 3)

    # -- the compass --------------------------------------------------------------------
    def compass(self, t: float, disturbed: bool, magnitude_error_ut: float) -> None:
        """The compass's verdict at ``t``: ``disturbed`` and the field magnitude's error."""
        if self.mag_name is None:
            return
        if not disturbed:
            self._mag_since = None
            self._mag_err = []
            return
        if self._mag_since is None:
            self._mag_since, self._mag_err = t, []
        self._mag_err.append(magnitude_error_ut)
        if len(self._mag_err) > 4096:
            self._mag_err = self._mag_err[::2]
        if self.mag_name not in self.active and t - self._mag_since >= HARD_IRON_AFTER_S:
            e = np.abs(np.asarray(self._mag_err))
            alarm = Alarm(self.mag_name, "hard_iron", float(np.median(e)), float(np.std(e)),
                          UNITS["hard_iron"],
                          round(self._mag_since, 3), round(t, 3))
            self.active[self.mag_name] = alarm
            self.raised.append(alarm)
            self.version += 1

    # -- lifecycle ----------------------------------------------------------------------
    def clear(self, sensor: str | None = None) -> None:
        """The sensor (every one, when None) was recalibrated: its alarm is cleared and its
        weight restored."""
        for name in list(self.active) if sensor is None else [sensor]:
            if name not in self.active and name not in self.names and name != self.mag_name:
                raise KeyError(f"no sensor {name[:40]!r}; the alarm watches {list(self.names)}"
                               f"{' and ' + self.mag_name if self.mag_name else ''}")
            if self.active.pop(name, None) is not None:
                self.version += 1
            if name in self.names:
                s = self.names.index(name)
                self.widen_g2[s] = 0.0
                self._ema[s] = 0.0
                self._over_since[s] = self._first_over[s] = np.nan
                self._hist_n[s] = 0
            elif name == self.mag_name:
                self._mag_since = None

    @property
    def alarms(self) -> tuple[Alarm, ...]:
        """The active alarms, by the time each was raised."""
        return tuple(sorted(self.active.values(), key=lambda a: a.raised_s))
