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
  them: their tests start again ``QUIET_S`` later). The change's onset is the change point
  of the sensor's block means (:func:`onset`); the blocks since then name it
  (:func:`name_shift`): a turned board reads gravity's full size in another direction, so
  its innovation lies across the predicted force (``mount_rotation``, the rotation
  ``dtheta`` of ``nu = [g]x dtheta`` fitted, in degrees); a bias changes the reading's size
  too, so it shows along the force (``bias_jump``, the mean shift, in g). A bias across
  gravity while the pose does not change looks like a mount: the arm's motion tells them
  apart;
- the compass: disturbed (off Earth's field as estimated) for ``HARD_IRON_AFTER_S`` without
  a break (``hard_iron``, size: the median of the field magnitude's error, µT, its sigma
  their spread).

Each alarm is an :class:`Alarm` (sensor, effect, size with sigma, when it began, when it
was raised). An alarmed accelerometer is down-weighted until :meth:`ModelChangeAlarm.clear`
(recalibrated): the variance of its readings per axis is widened by (``WIDEN`` x the
change's size)² (g²; a rotation's size as ``size x 1 g``), :meth:`ModelChangeAlarm.widen`. A
disturbed compass is already not fused (the compass's own verdict).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fusion.tracking.tracker_kernels import add_block_sums
from models.rotations import DEG

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
ALONG_RATIO = 0.12
"""A shift whose RMS along the predicted force exceeds this fraction of its RMS across it is
a bias (see :func:`name_shift`)."""
ALONG_SIGMA = 4.0
"""And exceeds this many noise sigmas of the quietest block (and ``FLOOR_G``)."""
RECENT_S = 20.0
"""A block's noise is at most the median of the last this many seconds' (s)."""
WIDEN = 5.0
"""An alarmed accelerometer's readings are widened by this many times the change's size."""
STICKY_S = 10.0
"""A sensor's first crossing counts for the culprit until its test has not held for this long (s)."""
QUIET_S = 60.0
"""After an accelerometer's alarm, the others' tests start again (s): the filter, moving
joints to follow the changed sensor, shifts the sensors that share them for a while."""
HARD_IRON_AFTER_S = 20.0
"""A compass disturbed this long without a break (s) has gained hard iron."""

EFFECTS = ("mount_rotation", "bias_jump", "hard_iron")
UNITS = {"mount_rotation": "deg", "bias_jump": "g", "hard_iron": "uT"}
"""Each effect's size unit."""


@dataclass(frozen=True)
class Alarm:
    """One model change: ``sensor``, ``effect`` (one of :data:`EFFECTS`), ``size`` with
    its 1-sigma ``sigma`` in ``unit`` (``deg``, ``g``, ``uT``), ``since_s`` (when the shift
    began, as the test saw it), ``raised_s`` (when the alarm was raised)."""

    sensor: str
    effect: str
    size: float
    sigma: float
    unit: str
    since_s: float
    raised_s: float

    def line(self) -> str:
        """For a person: ``acc3 mount_rotation 2.10 ± 0.31 deg since 120.5 s``."""
        return (f"{self.sensor} {self.effect} {self.size:.3g} ± {self.sigma:.2g} {self.unit} "
                f"since {self.since_s:.1f} s")

    def as_dict(self) -> dict:
        return {"sensor": self.sensor, "effect": self.effect, "size": round(self.size, 6),
                "sigma": round(self.sigma, 6), "unit": self.unit, "since_s": self.since_s,
                "raised_s": self.raised_s}


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` for each row of ``v (N, 3)``: ``(N, 3, 3)``."""
    z = np.zeros(len(v))
    x, y, w = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], 1)


def onset(nu: np.ndarray) -> int:
    """Where a lasting shift began in the block means ``nu (N, 3)`` (oldest first): the
    start ``k`` whose later blocks' mean, times their count, is largest (a shift from
    then on against none before: the change point of a step in white noise)."""
    tail = np.cumsum(nu[::-1], axis=0)[::-1]  # sum of blocks k..N-1
    n = np.arange(len(nu), 0, -1)
    score = np.square(tail).sum(1) / n
    return int(np.argmax(score[: max(len(nu) - 2, 1)]))


def name_shift(nu_g: np.ndarray, g_pred: np.ndarray, var_g2: np.ndarray,
               quiet_var_g2: float | None = None) -> tuple[str, float, float]:
    """Which effect explains block-mean innovations ``nu_g (N, 3)`` seen with predicted
    specific forces ``g_pred (N, 3)`` (both g, sensor axes; ``var_g2 (N,)`` each block's
    noise variance per axis): ``(effect, size, sigma)``; a bias in g, a rotation in deg.

    A turned board reads gravity's full size, only in another direction: its innovation
    lies across the predicted force (and the filter, moving joints, can only turn the
    prediction, never change its size). A bias changes the size too: it shows along the
    predicted force. The innovation's RMS along the force against ``ALONG_RATIO`` x its
    RMS across (and ``ALONG_SIGMA`` x the quietest block's noise, and ``FLOOR_G``) tells
    them apart."""
    N = len(nu_g)
    # one weight for all blocks: a sensor's variance grows once it disagrees (its gate),
    # which would weigh the blocks before the change over those after it
    w = np.full(N, 1.0 / float(np.mean(var_g2)))
    u = g_pred / np.linalg.norm(g_pred, axis=1, keepdims=True)
    along = (nu_g * u).sum(1)
    across = nu_g - along[:, None] * u
    rms_along = math.sqrt(float((along**2).mean()))
    rms_across = math.sqrt(float(np.square(across).sum(1).mean()))
    # the blocks' noise as it was before the sensor disagreed (its variance grows after):
    # ``quiet_var_g2``, the quietest block's of the sensor's history, when given
    sd = math.sqrt(float(var_g2.min()) if quiet_var_g2 is None else quiet_var_g2)
    dof = max(3 * N - 3, 1)
    if rms_along > max(ALONG_RATIO * rms_across, ALONG_SIGMA * sd, FLOOR_G):
        b = (w[:, None] * nu_g).sum(0) / w.sum()
        rss_b = float((w * np.square(nu_g - b).sum(1)).sum())
        s2 = max(rss_b / dof, 1.0)
        return "bias_jump", float(np.linalg.norm(b)), math.sqrt(s2 / w.sum())
    # nu = [g]x dtheta: the rotation that turns the prediction onto the reading
    H = _skew(g_pred)  # (N, 3, 3)
    A = np.einsum("n,nji,njk->ik", w, H, H) + 1e-9 * np.eye(3)
    y = np.einsum("n,nji,nj->i", w, H, nu_g)
    th = np.linalg.solve(A, y)
    rss_m = float((w * np.square(nu_g - H @ th).sum(1)).sum())
    # sigma from the fit's residual scatter (the blocks are not white: the residual's own
    # variance factor, when it exceeds the noise's)
    cov = max(rss_m / dof, 1.0) * np.linalg.inv(A)
    size = float(np.linalg.norm(th))
    e = th / max(size, 1e-12)
    return "mount_rotation", size / DEG, math.sqrt(max(float(e @ cov @ e), 0.0)) / DEG


class ModelChangeAlarm:
    """The alarm over the link accelerometers ``names`` and the compass (``mag_name``)."""

    def __init__(self, names: tuple[str, ...], mag_name: str | None, t_s: float,
                 unmodelled_g: np.ndarray | None = None):
        n = len(names)
        # the test's floor: FLOOR_G, or UNMODELLED_FACTOR x what the config says its model
        # leaves unexplained (an uncalibrated sensor's lasting, pose-dependent error is
        # no change: only a change well above it is)
        um = np.zeros(n) if unmodelled_g is None else np.asarray(unmodelled_g, float)
        self.floor_g = np.maximum(FLOOR_G, UNMODELLED_FACTOR * um)
        self.names, self.mag_name = names, mag_name
        self._sum_nu = np.zeros((n, 3))
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
        self._hist = np.zeros((n, cap, 7))  # per block: t, nu (3), g (3)
        self._hist_var = np.zeros((n, cap))
        self._hist_n = np.zeros(n, dtype=np.int64)
        self._mag_since: float | None = None
        self.active: dict[str, Alarm] = {}
        """The raised alarms not cleared, by sensor."""
        self.raised: list[Alarm] = []
        """Every alarm raised, oldest first (a log; cleared ones stay)."""
        self.widen_g2 = np.zeros(n)
        """Per link accelerometer: the variance (g², per axis) added to its readings."""


    # -- the accelerometers -------------------------------------------------------------
    def listen(self, t: float, u, nu: np.ndarray, Su: np.ndarray, z_pred: np.ndarray, var: np.ndarray,
               rows: np.ndarray, sel: np.ndarray, calm: bool) -> None:
        """The usable accelerometers ``u`` (a slice of ``sel``, every one in order, or sensor
        indices) gave innovations ``nu (k, 3)`` (g) with covariances ``Su``; ``z_pred`` and
        ``var`` are the update's predictions and measurement variances (``rows``: each
        accelerometer's three, by its place in ``sel``). Only while ``calm`` (the base as
        modelled) are they counted; the link accelerometers (the first ``len(names)``) only.

        A block mean's variance: the measurement noise's share averages down with the
        samples, the filter's own uncertainty (``Su`` less the noise) does not."""
        nl = len(self.names)
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
        # the filter's uncertainty grows once a changed sensor disagrees (its gate, a
        # re-acquisition): the test keeps the noise of the last RECENT_S where that is less
        cap = self._hist.shape[1]
        m = np.minimum(self._hist_n[have], cap)
        recent = int(RECENT_S / BLOCK_S)
        for j, s in enumerate(have.tolist()):
            if m[j] >= recent:
                rows = (self._hist_n[s] - 1 - np.arange(recent)) % cap
                var[j] = min(var[j], float(np.median(self._hist_var[s, rows])))
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
            self._hist_var[s, row] = var[j]
            self._hist_n[s] += 1
            if not over[j] or quiet or self.names[s] in self.active:
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

    def _raise_accel(self, s: int, t: float) -> None:
        m = min(int(self._hist_n[s]), self._hist.shape[1])
        order = np.argsort(self._hist[s, :m, 0])
        h, v = self._hist[s, order], self._hist_var[s, order]
        quiet = float(v.min())
        k = onset(h[:, 1:4])
        since = float(h[k, 0]) - BLOCK_S  # the block's first sample
        h, v = h[k:], v[k:]
        effect, size, sigma = name_shift(h[:, 1:4], h[:, 4:7], v, quiet)
        alarm = Alarm(self.names[s], effect, size, sigma, UNITS[effect],
                      round(since, 3), round(t, 3))
        self.active[alarm.sensor] = alarm
        self.raised.append(alarm)
        size_g = size * DEG if effect == "mount_rotation" else size  # a rotation's force, g
        self.widen_g2[s] = (WIDEN * size_g) ** 2
        self._ema[s] = 0.0

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

    # -- lifecycle ----------------------------------------------------------------------
    def clear(self, sensor: str | None = None) -> None:
        """The sensor (every one, when None) was recalibrated: its alarm is cleared and its
        weight restored."""
        for name in list(self.active) if sensor is None else [sensor]:
            if name not in self.active and name not in self.names and name != self.mag_name:
                raise KeyError(f"no sensor {name[:40]!r}; the alarm watches {list(self.names)}"
                               f"{' and ' + self.mag_name if self.mag_name else ''}")
            self.active.pop(name, None)
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
