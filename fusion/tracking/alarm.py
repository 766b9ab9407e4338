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

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.alarm_naming import (
    ACCEL_EFFECTS,
    BIAS_JUMP,
    FLOOR_G,
    HARD_IRON,
    MOUNT_ROTATION,
    name_shift,
    onset,
)
from armfusion.fusion.tracking.tracker_kernels import add_block_sums
from armfusion.models.rotations import DEG

BLOCK_S = 0.5
"""Innovations are averaged over blocks this long (s) before the test."""
TAU_S = 3.0
"""The test's exponential average of block means (s)."""
THRESHOLD_SIGMA = 6.0
"""The average's size against its noise (white innovations) that counts as a shift."""
UNMODELLED_FACTOR = 2.0
"""Or against this many times the config's unmodelled error (``accel_unmodelled_g``)."""
HOLD_S = 3.0
"""A shift must hold this long (s) to raise an alarm."""
WINDOW_S = 60.0
"""The naming fit uses at most this much of the shift's history (s)."""
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

EFFECTS = (*ACCEL_EFFECTS, HARD_IRON)
UNITS = {MOUNT_ROTATION: "deg", BIAS_JUMP: "g", HARD_IRON: "uT"}
"""Each effect's size unit."""


class AccelRows(NamedTuple):
    """The accelerometer update as the alarm reads it (one per update)."""

    z_pred: np.ndarray
    """The update's predictions ``(m,)`` (g)."""
    var: np.ndarray
    """Its measurement variances ``(m,)`` (g²)."""
    rows: np.ndarray
    """Each accelerometer's three rows ``(S, 3)``, by its place in ``sel``."""
    sel: np.ndarray
    """The update's accelerometers (sensor indices), in order."""


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


def reference_or_filter(nu: np.ndarray, moved: np.ndarray, var: np.ndarray,
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


def moved_by_offsets(sees: np.ndarray, offset_ref_rad: np.ndarray, offset_rad: np.ndarray | None, frame,
                     idx: np.ndarray, f_pred_g: np.ndarray) -> np.ndarray:
    """How much the filter's move of the joint offsets since the reference
    (:meth:`ModelChangeAlarm.reacquired`) changed the predictions ``f_pred_g (k, 3)`` of the
    link accelerometers ``idx`` (``sees (k, n)``: the joints each sees): the innovation against
    the reference is the filter's plus this, to first order ``f x (R_0S^T w)``, ``w = sum_j
    (offset_j - ref_j) a_j`` over the joints each sees (``a_j`` their axes, from ``frame``, the
    instant's kinematics). Zero without ``frame`` or ``offset_rad``."""
    if offset_rad is None or frame is None:
        return np.zeros((len(idx), 3))
    d = np.asarray(offset_rad, float) - offset_ref_rad
    w = (sees * d) @ frame.axes  # (k, 3), base axes
    a = np.einsum("kji,kj->ki", frame.R_0S[idx], w)  # in each sensor's axes
    return np.cross(f_pred_g, a)


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
        self._sum_moved = np.zeros((n, 3))  # the offsets' move's share (moved_by_offsets), while held
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

    def listen(self, t: float, u, nu: np.ndarray, Su: np.ndarray, update: AccelRows, calm: bool,
               frame=None, offset_rad: np.ndarray | None = None) -> None:
        """The usable accelerometers ``u`` (a slice of ``update.sel``, every one in order, or
        sensor indices) gave innovations ``nu (k, 3)`` (g) with covariances ``Su``; ``update``
        holds the update's predictions and measurement variances and where each
        accelerometer's rows are. Only while ``calm`` (the base as modelled) are they counted;
        the link accelerometers (the first ``len(names)``) only.
        ``frame`` (the instant's kinematics) and ``offset_rad`` (the filter's joint offsets)
        give the innovations against the offsets held before a re-acquisition
        (:meth:`reacquired`).

        A block mean's variance: the measurement noise's share averages down with the
        samples, the filter's own uncertainty (``Su`` less the noise) does not."""
        nl = len(self.names)
        z_pred, var, rows, sel = update
        if calm and self._offset_ref is not None and t < self._ref_until:
            if type(u) is slice:
                pos = np.arange(min(nl, len(nu)))
                idx = self._every[pos]
            else:
                pos = np.flatnonzero(u < nl)
                idx = u[pos]
            if len(pos):
                self._sum_moved[idx] += moved_by_offsets(self._sees[idx], self._offset_ref, offset_rad, frame,
                                                         idx, z_pred[rows[np.searchsorted(sel, idx)]])
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
        """A block's end: each sensor's block mean tested against its noise (an exponential
        average over ``TAU_S``), kept in its history, named again where an alarm waits for the
        motion, and an alarm raised where the test has held ``HOLD_S``."""
        have = np.flatnonzero(self._n > 0)
        n_ = self._n[have].astype(float)
        nu = self._sum_nu[have] / n_[:, None]
        g = self._sum_g[have] / n_[:, None]
        var, own = self._block_variances(have, n_)
        nu = reference_or_filter(nu, self._sum_moved[have] / n_[:, None], var, self.floor_g[have])
        size = self._test(t, have, nu, var)
        over = size > 1.0
        ratio = np.zeros(len(self.names))
        ratio[have] = size
        quiet = t < self._quiet_until
        for j, s in enumerate(have.tolist()):
            self._record(s, t, nu[j], g[j], own[j], var[j])
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
        if (t - self._over_since >= HOLD_S).any():  # (nan compares False)
            self._raise_first(t, ratio)

    def _block_variances(self, have: np.ndarray, n_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per axis, of the block means of the sensors ``have`` (``n_`` samples each): the
        variance the test uses, and the block's own (for the naming: a far more uncertain
        block is left out). The noise's share averages down over the samples, the state's
        does not; the filter's uncertainty grows once a changed sensor disagrees (its gate, a
        re-acquisition), so the test keeps the noise of the last ``RECENT_S`` where that is
        less."""
        var = self._sum_r[have] / n_ / n_ + self._sum_var[have] / n_
        own = var.copy()
        cap = self._hist.shape[1]
        m = np.minimum(self._hist_n[have], cap)
        recent = int(RECENT_S / BLOCK_S)
        for j, s in enumerate(have.tolist()):
            if m[j] >= recent:
                rows = (self._hist_n[s] - 1 - np.arange(recent)) % cap
                var[j] = min(var[j], float(np.median(self._hist_var[s, rows])))
        return var, own

    def _test(self, t: float, have: np.ndarray, nu: np.ndarray, var: np.ndarray) -> np.ndarray:
        """The block means ``nu`` folded into each sensor's exponential average; its size over
        the test's line (``THRESHOLD_SIGMA`` of its noise, at least the floor): over 1.0 is a
        shift."""
        last = self._ema_t[have]
        dt = np.where(np.isnan(last), BLOCK_S, t - last)
        a = np.minimum(1.0, dt / TAU_S)
        self._ema_t[have] = t
        self._ema[have] += a[:, None] * (nu - self._ema[have])
        sd = np.sqrt(var * a / (2.0 - a))
        return np.linalg.norm(self._ema[have], axis=1) / np.maximum(THRESHOLD_SIGMA * sd, self.floor_g[have])

    def _record(self, s: int, t: float, nu: np.ndarray, g: np.ndarray, own: float, var: float) -> None:
        """Sensor ``s``'s block kept in its ring of history (``WINDOW_S``): its time, mean
        innovation, mean predicted force and own variance, and the test's variance."""
        row = self._hist_n[s] % self._hist.shape[1]
        self._hist[s, row, 0] = t
        self._hist[s, row, 1:4] = nu
        self._hist[s, row, 4:7] = g
        self._hist[s, row, 7] = own
        self._hist_var[s, row] = var
        self._hist_n[s] += 1

    def _raise_first(self, t: float, ratio: np.ndarray) -> None:
        """The test has held: the alarm raised on the culprit, the first sensor to shift,
        though the filter may since have pulled its innovation back under the test by moving
        the joints it shares with the others (which then shift); the largest shift (``ratio``)
        among those that shifted together. Then quiet for ``QUIET_S``."""
        on = np.flatnonzero(~np.isnan(self._first_over))
        first = self._first_over[on].min()
        tied = on[self._first_over[on] < first + 0.5 * BLOCK_S]  # the same block
        self._raise_accel(int(tied[np.argmax(ratio[tied])]), t)
        self._over_since[:] = np.nan
        self._first_over[:] = np.nan
        self._quiet_until = t + QUIET_S

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
        size_g = n.size * DEG if n.effect == MOUNT_ROTATION else n.size  # a rotation's force, g
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
            alarm = Alarm(self.mag_name, HARD_IRON, float(np.median(e)), float(np.std(e)),
                          UNITS[HARD_IRON],
                          round(self._mag_since, 3), round(t, 3))
            self.active[self.mag_name] = alarm
            self.raised.append(alarm)
            self.version += 1

    # -- lifecycle ----------------------------------------------------------------------
    def snapshot(self) -> dict:
        """What a restart must not forget (the tracker's snapshot): the active alarms, the
        log of those raised and each accelerometer's widening. The tests' running averages
        start afresh on :meth:`restore`: an active alarm stays raised and its sensor
        down-weighted until :meth:`clear`, as it was."""
        return {"names": list(self.names), "mag_name": self.mag_name,
                "active": [a.as_dict() for a in self.alarms],
                "raised": [a.as_dict() for a in self.raised], "widen_g2": self.widen_g2.tolist()}

    def restore(self, snap: dict) -> None:
        """Take the alarms of :meth:`snapshot` back (one of an alarm over the same sensors);
        a listener publishes them again (:attr:`version`)."""
        if list(snap["names"]) != list(self.names) or snap["mag_name"] != self.mag_name:
            raise ValueError(f"the alarm's snapshot watches {snap['names']} and {snap['mag_name']!r}; "
                             f"this one {list(self.names)} and {self.mag_name!r}")
        widen = np.array(snap["widen_g2"], dtype=float)
        if widen.shape != self.widen_g2.shape or not np.all(np.isfinite(widen) & (widen >= 0)):
            raise ValueError(f"the alarm's snapshot widens by {snap['widen_g2']!r}: not one "
                             f"variance >= 0 per accelerometer")
        self.raised = [Alarm.of_dict(d) for d in snap["raised"]]
        self.active = {al.sensor: al for al in map(Alarm.of_dict, snap["active"])}
        self.widen_g2 = widen
        self.version += 1

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
