"""The innovations the filter keeps for diagnosis: :class:`InnovationLog` (one sensor's,
oldest first), and the ring buffers it is read from (the accelerometers' together, one
row per update; the compass's), with running NIS statistics."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.tracking.tracker_kernels import ring_row_into


# results
@dataclass(frozen=True)
class InnovationLog:
    """One sensor's innovations (oldest first): ``t_s (N,)``, ``innovation (N, k)``,
    ``S (N, k, k)``, ``nis (N,)``, ``accepted (N,)`` (used in the update)."""

    sensor: str
    t_s: np.ndarray
    innovation: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray


class InnovationRing:
    """One sensor's innovations (a ring buffer), with the mean NIS of the healthy ones."""

    def __init__(self, k: int, capacity: int):
        self.cap = max(int(capacity), 1)
        self.t = np.zeros(self.cap)
        self.nu = np.zeros((self.cap, k))
        self.S = np.zeros((self.cap, k, k))
        self.nis = np.zeros(self.cap)
        self.ok = np.zeros(self.cap, bool)
        self.n = 0
        # running NIS statistics (all healthy innovations, accepted or not)
        self.nis_sum = 0.0
        self.nis_count = 0

    def add(self, t, nu, S, nis, ok, count_stats: bool = True):
        i = self.n % self.cap
        self.t[i], self.nu[i], self.S[i], self.nis[i], self.ok[i] = t, nu, S, nis, ok
        self.n += 1
        if count_stats and np.isfinite(nis):
            self.nis_sum += nis
            self.nis_count += 1

    def log(self, name: str) -> InnovationLog:
        m = min(self.n, self.cap)
        idx = (np.arange(self.n - m, self.n)) % self.cap
        return InnovationLog(name, self.t[idx].copy(), self.nu[idx].copy(), self.S[idx].copy(),
                             self.nis[idx].copy(), self.ok[idx].copy())


class AccelRing:
    """Innovations of every accelerometer, one row per update (a ring buffer)."""

    def __init__(self, names: tuple[str, ...], capacity: int):
        Sa = len(names)
        self.names = names
        self.cap = max(int(capacity), 1)
        self.t = np.zeros(self.cap)
        self.nu = np.zeros((self.cap, Sa, 3))
        self.S = np.zeros((self.cap, Sa, 3, 3))
        self.nis = np.zeros((self.cap, Sa))
        self.ok = np.zeros((self.cap, Sa), bool)
        self.present = np.zeros((self.cap, Sa), bool)
        self.n = 0
        self.nis_sum = np.zeros(Sa)
        self.nis_count = np.zeros(Sa, dtype=np.int64)  # rows with only some sensors
        self.nis_whole = 0  # rows with every sensor

    @property
    def counts(self) -> np.ndarray:
        """Healthy innovations counted per sensor."""
        return self.nis_count + self.nis_whole

    def add(self, t, which, nu, S, nis, ok, finite=False):
        """``which (k,)`` sensor indices; ``nu (k, 3)``, ``S (k, 3, 3)``, ``nis``, ``ok (k,)``;
        ``finite``: the caller knows every NIS is finite (each passed its gate)."""
        i = self.n % self.cap
        self.n += 1
        if len(which) == self.present.shape[1]:  # every sensor, in order: whole rows (compiled)
            count = finite or math.isfinite(nis.sum())
            ring_row_into(i, t, nu, S, nis, ok, self.t, self.nu, self.S, self.nis, self.ok, self.present,
                          self.nis_sum, count)
            if count:
                self.nis_whole += 1  # counted for every sensor (see counts)
                return
        else:
            self.t[i] = t
            self.present[i] = False
            self.present[i, which] = True
            self.nu[i, which] = nu
            self.S[i, which] = S
            self.nis[i, which] = nis
            self.ok[i, which] = ok
        good = np.isfinite(nis)
        self.nis_sum[which[good]] += nis[good]
        self.nis_count[which[good]] += 1

    def log(self, name: str) -> InnovationLog:
        j = self.names.index(name)
        m = min(self.n, self.cap)
        idx = (np.arange(self.n - m, self.n)) % self.cap
        idx = idx[self.present[idx, j]]
        return InnovationLog(name, self.t[idx].copy(), self.nu[idx, j].copy(), self.S[idx, j].copy(),
                             self.nis[idx, j].copy(), self.ok[idx, j].copy())
