"""Slips: an encoder that lost counts shows as a lasting shift of the innovations of the
link accelerometers beyond its joint. :class:`SlipDetector` averages each link
accelerometer's normalised innovations on two time scales (``shift_tau_s``,
``shift_slow_tau_s``) and tests them against zero (allowing for the lasting error the
calibration leaves, :attr:`SlipDetector.calibration`); a shift, or a sensor rejected for
longer than a bump lasts, re-acquires: the offsets it sees (and no agreeing sensor sees)
are widened and read again."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from armfusion.fusion.tracking.health import SensorHealth
from armfusion.fusion.tracking.settings import C_REACQUISITIONS, IMU_ACC, StateLayout, TrackerSettings
from armfusion.fusion.tracking.tracker_kernels import add_normalised_innovations, close_slip_block
from armfusion.models.rotations import DEG


class SlipDetector:
    """The shift tests of ``n_links`` link accelerometers (of ``n_accel``), and the
    re-acquisitions. ``sees (S, n)``: sensor s sees joint j."""

    def __init__(self, settings: TrackerSettings, layout: StateLayout, names: tuple[str, ...],
                 n_links: int, n_accel: int, sees: np.ndarray, t_s: float):
        st, Sa, n = settings, n_accel, layout.n_joints
        self.settings, self.layout, self.names = settings, layout, names
        self.n_links, self.sees = n_links, sees
        # averages of the normalised innovations, on each of the detector's time scales
        self._taus = np.array([st.shift_tau_s, st.shift_slow_tau_s])
        self._thr = np.array([st.shift_threshold, st.shift_slow_threshold])
        self.shift = np.zeros((Sa, 2, 3))
        self.shift_t = np.full(Sa, np.nan)
        self._cool = np.full(Sa, -np.inf)
        self._stat = np.zeros(Sa)
        self.calibration = np.zeros((n_links, 3, 3))
        """Per link accelerometer: the covariance of the lasting error the calibration leaves
        in its normalised innovations (set by the observability's consider update)."""
        self._sum = np.zeros((Sa, 3))
        self._n = np.zeros(Sa, dtype=np.int64)
        self._every = np.arange(Sa, dtype=np.int64)
        # the last block's: which link accelerometers were heard, and their tests' weights a
        # and variances var_w per time scale (see close_slip_block)
        self._heard = np.zeros(n_links, dtype=np.bool_)
        self._a = np.zeros((n_links, 2))
        self._var_w = np.ones((n_links, 2))
        self._block_t = float(t_s)
        self._log: dict[int, list[float]] = {}
        self.reacquiring_until = np.full(n, -np.inf)
        """Per joint: until when it is flagged ``reacquiring``."""
        self._eye3 = np.eye(3)

    def listen(self, t: float, u, nu: np.ndarray, Su: np.ndarray, calm: bool,
               reacquire: Callable[[int, float], None]) -> None:
        """The usable accelerometers ``u`` (indices or a slice) gave innovations ``nu (k, 3)``
        with covariances ``Su``. They are averaged over 50 ms, and tested then; only while
        the base behaves as modelled (``calm``: a lurch is common to all sensors)."""
        if calm:  # (compiled: add_normalised_innovations)
            add_normalised_innovations(self._every[u] if type(u) is slice else u, nu, Su, self._sum, self._n)
        else:  # paused: the averages keep what they had, and do not count the pause
            self.shift_t[u] = t
            self._sum[u] = 0.0
            self._n[u] = 0
        if t - self._block_t >= 0.05:
            # the block's means into the averages and their tests, compiled (close_slip_block)
            k = close_slip_block(t, self._sum, self._n, self.n_links, self._taus, self._thr, self.shift_t,
                                 self.shift, self._stat, self._heard, self._a, self._var_w)
            if k >= 0:
                self._block_t = t
                if k:
                    self._detect(t, np.flatnonzero(self._heard), reacquire)

    def _detect(self, t: float, which: np.ndarray, reacquire: Callable[[int, float], None]) -> None:
        """A lasting shift of a link accelerometer's innovations (see ``shift_threshold``),
        on two time scales: a slip shows within a second, a slow drift of the counts over a
        few. The link accelerometers ``which`` were heard in the block just closed: their
        averages, and the statistics of the test without the calibration's lasting error
        (``_stat``), are :func:`~armfusion.fusion.tracking.tracker_kernels.close_slip_block`'s."""
        worst = self._stat[which]
        cal = self.calibration[which]  # (k, 3, 3)
        if cal.any():
            # the sensor's own calibration error lasts: it does not average away, so the
            # test that sets off a re-acquisition allows for it,
            # stat = ema^T (var_w I + C)^-1 ema (per time scale)
            ema, var_w = self.shift[which], self._var_w[which]
            M = cal[:, None] + var_w[:, :, None, None] * self._eye3
            stat = np.einsum("kti,kti->kt", ema, np.linalg.solve(M, ema[..., None])[..., 0])
            stat[~(self._a[which] > 0)] = 0.0
            stat /= self._thr
            worst = stat.max(axis=1)
        hit = worst > 1.0
        if hit.any():
            for s in which[hit & (t >= self._cool[which])]:
                reacquire(int(s), t)
                self.shift[s] = 0.0
                self._cool[s] = t + self.settings.reacquiring_flag_s

    def reacquire(self, i: int, t: float, ukf, health: SensorHealth, locked: np.ndarray) -> None:
        """A sensor rejected for longer than a bump lasts: widen what it sees, read it again."""
        st, L = self.settings, self.layout
        health.counts[i, C_REACQUISITIONS] += 1
        if self.names[i] == IMU_ACC:
            idx = np.r_[L.roll, L.pitch, np.arange(L.accel.start, L.accel.stop)]
            ukf.inflate(idx, np.r_[(2 * DEG) ** 2, (2 * DEG) ** 2, np.full(3, 1.0)])
            return
        joints = self._candidates(i, t, health, locked)
        # a sensor that keeps disagreeing widens further each time (a large slip), up to
        # what an unread joint starts with
        recent = [u for u in self._log.get(i, []) if t - u < 10.0]
        recent.append(t)
        self._log[i] = recent
        sig = min(st.slip_sigma_deg * 2.0 ** (len(recent) - 1), st.unknown_joint_sigma_deg)
        ukf.inflate(joints, (sig * DEG) ** 2)
        self.reacquiring_until[joints] = t + st.reacquiring_flag_s

    def _candidates(self, i: int, t: float, health: SensorHealth, locked: np.ndarray) -> np.ndarray:
        """The joints a disagreeing sensor ``i`` may have slipped: those it sees that no
        agreeing link accelerometer sees too, and that gravity can read now (widening a
        held joint would only throw away what is known of it)."""
        sees = self.sees[i].copy()
        for s in range(self.n_links):
            if s == i or not health.working(s):
                continue
            # agreeing: nowhere near a shift of its own (a slip shows on every sensor beyond
            # the joint, some sooner than others)
            agrees = (not health.rejecting[s] and t >= self._cool[s]
                      and self._stat[s] < 0.25)
            if agrees and t - health.last_t[s] < self.settings.stale_after_s:
                sees &= ~self.sees[s]
        readable = sees & ~locked
        if readable.any():
            return np.flatnonzero(readable)
        fallback = self.sees[i] & ~locked
        return np.flatnonzero(fallback if fallback.any() else self.sees[i])

    def snapshot(self) -> list:
        return [self.shift.tolist(), np.nan_to_num(self.shift_t, nan=-1e300).tolist()]

    def restore(self, snap: list) -> None:
        self.shift = np.array(snap[0], dtype=float)
        st_ = np.array(snap[1], dtype=float)
        self.shift_t = np.where(st_ < -1e299, np.nan, st_)
