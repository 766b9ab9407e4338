"""The model-change alarm: a lasting change of the sensor model while the arm is used.

A link accelerometer knocked loose (its mount rotated by a degree or two) or whose bias
jumped leaves a lasting shift in its innovations that the filter cannot absorb into the
joint angles for every pose; a magnetometer that gained hard iron reads off Earth's field
(the compass's ``disturbed``) and never recovers. :class:`ModelChangeAlarm` watches:

- per link accelerometer, the innovations (g, sensor axes) and the predicted specific
  force, averaged in blocks of ``BLOCK_S``; an exponential average of the block means over
  ``TAU_S`` is tested against ``max(THRESHOLD_SIGMA`` x its noise, ``FLOOR_G)``; a test
  that holds for ``HOLD_S`` raises an alarm. The blocks since the shift began name it: a
  constant shift ``b`` (``bias_jump``, size in g) against a shift ``[g]x dtheta`` that
  follows gravity in the sensor's axes (``mount_rotation``, size in degrees), the model
  with the smaller residual winning (a tie, when gravity has not moved in the sensor's
  axes, goes to the mount: it is the commoner accident);
- the compass: disturbed for ``HARD_IRON_AFTER_S`` without a break while the chair is
  in use (``hard_iron``, size: the field magnitude's error, µT).

Each alarm is an :class:`Alarm` (sensor, effect, size with sigma, when it began, when it
was raised). An alarmed accelerometer is down-weighted until :meth:`ModelChangeAlarm.clear`
(recalibrated): its variance per axis is widened by the change's size squared (in g², a
rotation's through ``g x sin``), :meth:`ModelChangeAlarm.widen`. A disturbed compass is
already not fused (the compass's own verdict).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from models.rotations import DEG

BLOCK_S = 0.5
"""Innovations are averaged over blocks this long (s) before the test."""
TAU_S = 6.0
"""The test's exponential average of block means (s)."""
THRESHOLD_SIGMA = 6.0
"""The average's size against its noise (white innovations) that counts as a shift."""
FLOOR_G = 0.012
"""And against this floor (g): what the model leaves in ordinary use, below any alarm."""
HOLD_S = 8.0
"""A shift must hold this long (s) to raise an alarm."""
WINDOW_S = 60.0
"""The naming fit uses at most this much of the shift's history (s)."""
HARD_IRON_AFTER_S = 60.0
"""A compass disturbed this long without a break (s) has gained hard iron."""

EFFECTS = ("mount_rotation", "bias_jump", "hard_iron")


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

    def as_dict(self) -> dict:
        return {"sensor": self.sensor, "effect": self.effect, "size": round(self.size, 6),
                "sigma": round(self.sigma, 6), "unit": self.unit, "since_s": self.since_s,
                "raised_s": self.raised_s}


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` for each row of ``v (N, 3)``: ``(N, 3, 3)``."""
    z = np.zeros(len(v))
    x, y, w = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], 1)


def name_shift(nu_g: np.ndarray, g_pred: np.ndarray, var_g2: np.ndarray) -> tuple[str, float, float]:
    """Which effect explains block-mean innovations ``nu_g (N, 3)`` seen with predicted
    specific forces ``g_pred (N, 3)`` (both g, sensor axes; ``var_g2 (N,)`` each block's
    noise variance per axis): ``(effect, size, sigma)``; a bias in g, a rotation in deg."""
    N = len(nu_g)
    w = 1.0 / var_g2
    # bias: nu = b
    b = (w[:, None] * nu_g).sum(0) / w.sum()
    rss_b = float((w * np.square(nu_g - b).sum(1)).sum())
    # mount: nu = [g]x dtheta  (a sensor turned by -dtheta sees f + f x (-dtheta)... as a
    # small rotation either way; the size is what is reported)
    H = _skew(g_pred)  # (N, 3, 3)
    A = np.einsum("n,nji,njk->ik", w, H, H) + 1e-9 * np.eye(3)
    y = np.einsum("n,nji,nj->i", w, H, nu_g)
    th = np.linalg.solve(A, y)
    rss_m = float((w * np.square(nu_g - H @ th).sum(1)).sum())
    # sigma from the fit's residual scatter (blocks are not white: inflate by the
    # residual's own variance factor when it exceeds the noise's)
    dof = max(3 * N - 3, 1)
    if rss_m <= rss_b * 1.05:
        s2 = max(rss_m / dof, 1.0)
        cov = s2 * np.linalg.inv(A)
        size = float(np.linalg.norm(th))
        u = th / max(size, 1e-12)
        return "mount_rotation", size / DEG, math.sqrt(max(float(u @ cov @ u), 0.0)) / DEG
    s2 = max(rss_b / dof, 1.0)
    size = float(np.linalg.norm(b))
    return "bias_jump", size, math.sqrt(s2 / w.sum())


class ModelChangeAlarm:
    """The alarm over the link accelerometers ``names`` and the compass (``mag_name``)."""

    def __init__(self, names: tuple[str, ...], mag_name: str | None, t_s: float):
        n = len(names)
        self.names, self.mag_name = names, mag_name
        self._sum_nu = np.zeros((n, 3))
        self._sum_g = np.zeros((n, 3))
        self._sum_var = np.zeros(n)
        self._n = np.zeros(n, dtype=np.int64)
        self._block_t = float(t_s)
        self._ema = np.zeros((n, 3))
        self._ema_t = np.full(n, np.nan)
        self._over_since = np.full(n, np.nan)
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
    def listen(self, t: float, nu: np.ndarray, Su: np.ndarray, z_pred: np.ndarray, calm: bool) -> None:
        """Every link accelerometer's innovation ``nu (n, 3)`` (g), covariances ``Su (n, 3, 3)``
        and predicted readings ``z_pred (n, 3)`` at ``t``; only while ``calm`` (the base as
        modelled) are they counted."""
        if calm:
            self._sum_nu += nu
            self._sum_g += z_pred
            self._sum_var += np.trace(Su, axis1=1, axis2=2) / 3.0
            self._n += 1
        if t - self._block_t >= BLOCK_S:
            if self._n.any():
                self._block(t)
            self._sum_nu[:] = 0.0
            self._sum_g[:] = 0.0
            self._sum_var[:] = 0.0
            self._n[:] = 0
            self._block_t = t

    def _block(self, t: float) -> None:
        have = np.flatnonzero(self._n > 0)
        n_ = self._n[have].astype(float)
        nu = self._sum_nu[have] / n_[:, None]
        g = self._sum_g[have] / n_[:, None]
        var = self._sum_var[have] / n_ / n_  # per axis, of a block mean of white samples
        last = self._ema_t[have]
        dt = np.where(np.isnan(last), BLOCK_S, t - last)
        a = np.minimum(1.0, dt / TAU_S)
        self._ema_t[have] = t
        self._ema[have] += a[:, None] * (nu - self._ema[have])
        sd = np.sqrt(var * a / (2.0 - a))
        over = np.linalg.norm(self._ema[have], axis=1) > np.maximum(THRESHOLD_SIGMA * sd, FLOOR_G)
        cap = self._hist.shape[1]
        for j, s in enumerate(have.tolist()):
            row = self._hist_n[s] % cap
            self._hist[s, row, 0] = t
            self._hist[s, row, 1:4] = nu[j]
            self._hist[s, row, 4:7] = g[j]
            self._hist_var[s, row] = var[j]
            self._hist_n[s] += 1
            name = self.names[s]
            if not over[j]:
                self._over_since[s] = np.nan
                continue
            if np.isnan(self._over_since[s]):
                self._over_since[s] = t
            if name not in self.active and t - self._over_since[s] >= HOLD_S:
                self._raise_accel(s, t)

    def _raise_accel(self, s: int, t: float) -> None:
        since = float(self._over_since[s]) - TAU_S  # the average takes about tau to cross
        m = min(int(self._hist_n[s]), self._hist.shape[1])
        h, v = self._hist[s, :m], self._hist_var[s, :m]
        keep = h[:, 0] >= since
        if keep.sum() < 4:
            keep[:] = True
        effect, size, sigma = name_shift(h[keep, 1:4], h[keep, 4:7], v[keep])
        alarm = Alarm(self.names[s], effect, size, sigma, "deg" if effect == "mount_rotation" else "g",
                      round(since, 3), round(t, 3))
        self.active[alarm.sensor] = alarm
        self.raised.append(alarm)
        size_g = size * DEG if effect == "mount_rotation" else size  # a rotation's force, g
        self.widen_g2[s] = (2.0 * size_g) ** 2
        self._ema[s] = 0.0

    def widen(self, sel: np.ndarray, var: np.ndarray) -> None:
        """Add each alarmed accelerometer's widening to the update's variances ``var`` (the
        accelerometers ``sel`` first, three rows each), in place."""
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
            alarm = Alarm(self.mag_name, "hard_iron", float(np.median(e)), float(np.std(e)), "uT",
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
                self._over_since[s] = np.nan
                self._hist_n[s] = 0
            elif name == self.mag_name:
                self._mag_since = None

    @property
    def alarms(self) -> tuple[Alarm, ...]:
        """The active alarms, by the time each was raised."""
        return tuple(sorted(self.active.values(), key=lambda a: a.raised_s))
