"""Each sensor's health, as the tracker judges it sample by sample: the counters
(:data:`armfusion.fusion.tracking.settings.COUNTERS`), the accelerometers' stuck, implausible (dead)
and gate verdicts, the innovations kept for diagnosis, and the statuses
(:data:`armfusion.fusion.tracking.settings.SENSOR_STATUS`) reported with every estimate.

A handful of sensors: plain Python is faster here than array calls.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from armfusion.fusion.tracking.innovations import AccelRing
from armfusion.fusion.tracking.measurement import Stack
from armfusion.fusion.tracking.settings import (
    C_IMPLAUSIBLE,
    C_NAN,
    C_OUT_OF_ORDER,
    C_REJECTED,
    C_SAMPLES,
    C_SATURATED,
    C_STUCK,
    C_USED,
    COUNTERS,
    S_ABSENT,
    S_DEAD,
    S_REJECTING,
    S_STALE,
    S_STUCK,
    SENSOR_STATUS,
    STATUS_CODE,
    G,
    TrackerSettings,
)
from armfusion.fusion.tracking.tracker_kernels import screen_accelerometers

PLAUSIBLE_BASE_SIGMAS = 4.0
"""A reading's magnitude may differ from the prediction's by this many sigmas of the base's
own acceleration (a 3-D Gaussian's magnitude exceeds four sigmas about once in 1,000)."""


class SensorHealth:
    """The health of the sensors ``names`` (the accelerometers first, ``n_accel`` of them)."""

    def __init__(self, names: tuple[str, ...], n_accel: int, settings: TrackerSettings):
        S, Sa = len(names), n_accel
        self.names, self.n_accel, self.settings = names, Sa, settings
        self.plausible_g = max(settings.plausible_tolerance_g,
                               PLAUSIBLE_BASE_SIGMAS * settings.base_accel_sigma_mps2 / G)
        """How far a reading's magnitude may be from the prediction's before it is implausible
        (g): :attr:`TrackerSettings.plausible_tolerance_g`, or four sigmas of the base's own
        acceleration where that is more (a hand's 3 m/s², where a chair's 0.7 keeps the
        setting's 0.35 g): a base that accelerates more than the filter predicts changes
        every reading's magnitude, and that is motion, not a dead sensor."""
        self.seen = np.zeros(S, bool)
        self.last_t = np.full(S, -np.inf)
        self.counts = np.zeros((S, len(COUNTERS)), dtype=np.int64)
        self.rejecting = [False] * S  # per-sensor verdicts as plain lists (read one by one)
        # per accelerometer: last counts, identical run, prediction when it began, stuck,
        # implausible since, rejecting since
        self._acc = [[None, 0, None, False, None, None] for _ in range(Sa)]
        self._last_counts = np.full((Sa, 3), np.nan)  # per accelerometer: its last counts (NaN: none)
        self._dirty = [False] * Sa  # a sensor whose health bookkeeping is not at rest
        self.stuck = [False] * Sa
        self.dead = [False] * Sa
        self.ring = AccelRing(names[:Sa], settings.innovation_capacity)
        self.status_codes = np.full(S, STATUS_CODE["absent"], dtype=np.int8)
        """Replaced (never written in place) when the statuses are updated."""
        self.changed = True
        """A sensor's health changed since the statuses were last updated."""

    def out_of_order(self, index: dict[str, int], samples) -> None:
        """Count ``samples`` (by stream) as out of order."""
        for s in samples:
            if s in index:
                self.counts[index[s], C_OUT_OF_ORDER] += 1

    def admit(self, t: float, index: dict[str, int], samples, limits: dict, physical) -> dict:
        """The raw ``samples`` (by stream; ``index`` their sensors) that are finite and not
        saturated (``limits``: per stream the counts' range), as ``(counts, physical(s,
        counts))``; the others counted (``nan``, ``saturated``). ``imu_temp`` is left out."""
        counts, phys = self.counts, {}
        for s, v in samples.items():
            if s == "imu_temp":
                continue
            i = index[s]
            counts[i, C_SAMPLES] += 1
            c = np.asarray(v, dtype=float).reshape(-1)
            cl = c.tolist()  # a handful of numbers: plain floats are cheaper to check
            if not all(map(math.isfinite, cl)):
                counts[i, C_NAN] += 1
                continue
            lo, hi = limits[s]
            if lo is not None and (min(cl) <= lo or max(cl) >= hi):
                counts[i, C_SATURATED] += 1
                self.seen[i], self.last_t[i] = True, t
                continue
            phys[s] = (c, physical(s, c[None])[0])
        return phys

    def heard(self, i, t: float) -> None:
        """Sensor(s) ``i`` spoke at ``t`` (whether or not their samples are then used)."""
        self.seen[i], self.last_t[i] = True, t

    def mark_used(self, i: int, t: float) -> None:
        self.seen[i], self.last_t[i] = True, t
        self.counts[i, C_USED] += 1

    def accel(self, t: float, stack: Stack, inn, gate_l: list | None, rows: np.ndarray,
              reacquire: Callable[[int, float], None]) -> tuple[np.ndarray, object, np.ndarray, np.ndarray]:
        """Stuck, implausible (dead) and gate verdicts for the accelerometers of the stacked
        measurement ``stack`` (their indices, counts, readings in g and variances) and its
        update ``inn``; returns which may enter the update and the usable ones' sensors,
        normalised innovations' inputs ``(u, nu, Su)`` (``u`` None when none is usable).
        ``gate_l``: ``inn.gate_ok`` as a list, when the caller has it; ``rows``: each
        accelerometer's three rows; ``reacquire(sensor, t)``: a sensor rejected for longer
        than a bump lasts."""
        sel, counts, f, var, full = stack.index, stack.counts, stack.f_g, stack.var_a, stack.selection.full
        k = len(sel)
        ix = slice(0, k) if full else sel  # plain slices where every sensor spoke
        if gate_l is None:
            gate_l = inn.gate_ok.tolist()
        # identical counts in a row (stuck?) and |f| against |prediction| (dead?), compiled
        same, implausible = np.empty(k, dtype=np.bool_), np.empty(k, dtype=np.bool_)
        flagged = screen_accelerometers(sel, counts, f, inn.z_pred, self._last_counts, self.plausible_g,
                                        same, implausible)
        gate_ok = inn.gate_ok[:k]
        self.seen[ix] = True
        self.last_t[ix] = t
        if not (flagged or any(self._dirty)) and all(gate_l[:k]):
            # the usual case: every sensor healthy and consistent
            self.counts[ix, C_USED] += 1
            ok = usable = gate_ok
            all_usable = True
        else:
            ok, usable = self._slow(t, sel, inn.z_pred[: 3 * k].reshape(k, 3), inn, var, same, implausible,
                                    reacquire)
            all_usable = bool(usable.all())
        u = nu = Su = None
        if all_usable or usable.any():
            which, Sb = inn.blocks[3]  # accelerometer groups come first, in order
            if all_usable:
                Su = Sb[:k]
                nu = inn.innovation[: 3 * k].reshape(k, 3)
                self.ring.add(t, sel, nu, Su, inn.nis[:k], ok, finite=ok is gate_ok)
                u = ix
            else:
                ui = np.flatnonzero(usable)
                nu = inn.innovation[rows[ui]]
                Su = Sb[ui]
                u = sel[ui]
                self.ring.add(t, u, nu, Su, inn.nis[ui], ok[ui])
        return ok, u, nu, Su

    def _slow(self, t, sel, zp, inn, var, same, implausible, reacquire):
        """The sensor by sensor path: a stuck, implausible or rejected sample somewhere."""
        st = self.settings
        k = len(sel)
        zl = zp.tolist()
        gate = inn.gate_ok[:k].tolist()
        sd = np.sqrt(var).tolist()
        ok = np.zeros(k, dtype=bool)
        usable = np.zeros(k, dtype=bool)
        H = self._acc
        for i, s in enumerate(sel.tolist()):
            h = H[s]
            # implausible: far from the predicted magnitude (a dead or disconnected sensor)
            if implausible[i]:
                self.counts[s, C_IMPLAUSIBLE] += 1
                if h[4] is None:
                    h[4] = t
                dead = t - h[4] >= st.dead_after_s
                if dead != self.dead[s]:
                    self.dead[s] = dead
                    self.changed = True
                h[1], h[2] = 0, None
                self._dirty[s] = True
                continue
            # stuck: identical counts in a row while the prediction moved
            if same[i]:
                h[1] += 1
                if h[2] is None:
                    h[2] = zl[i]
                moved = max(abs(a - b) / e for a, b, e in zip(zl[i], h[2], sd[i], strict=True)) > 6.0
                if h[1] + 1 >= st.stuck_samples and moved:
                    h[3] = True
            else:
                h[1], h[2], h[3] = 0, None, False
            if h[3] != self.stuck[s]:
                self.stuck[s] = h[3]
                self.changed = True
            if h[3]:
                self.counts[s, C_STUCK] += 1
                continue
            h[4] = None
            if self.dead[s]:
                self.dead[s] = False
                self.changed = True
            usable[i] = True
            if gate[i]:
                ok[i] = True
                self.counts[s, C_USED] += 1
                self.rejecting[s] = False
                h[5] = None
            else:
                self.counts[s, C_REJECTED] += 1
                self.rejecting[s] = True
                if h[5] is None:
                    h[5] = t
                elif t - h[5] >= st.reacquire_after_s:
                    reacquire(s, t)
                    h[5] = None
            self._dirty[s] = (h[1] > 0 or h[2] is not None or h[3] or h[4] is not None
                              or h[5] is not None or self.dead[s] or self.rejecting[s])
        return ok, usable

    def working(self, s: int) -> bool:
        """Sensor ``s`` has spoken and is neither dead nor stuck."""
        return bool(self.seen[s]) and not self.dead[s] and not self.stuck[s]

    def update_statuses(self, t: float) -> list[int]:
        """Every sensor's status code at ``t`` (the most severe condition wins)."""
        self.changed = False
        stale_s = self.settings.stale_after_s
        Sa = self.n_accel
        codes = []
        for i in range(len(self.names)):
            if not self.seen[i]:
                c = S_ABSENT
            elif i < Sa and self.dead[i]:
                c = S_DEAD
            elif i < Sa and self.stuck[i]:
                c = S_STUCK
            elif t - self.last_t[i] > stale_s:
                c = S_STALE
            elif self.rejecting[i]:
                c = S_REJECTING
            else:
                c = 0
            codes.append(c)
        self.status_codes = np.array(codes, dtype=np.int8)
        return codes

    def nis_stats(self) -> dict[str, tuple[float, int, int]]:
        """Per accelerometer: (mean NIS, count, degrees of freedom) over its healthy samples."""
        r = self.ring
        cnt = r.counts
        return {s: (float(r.nis_sum[i] / cnt[i]) if cnt[i] else float("nan"), int(cnt[i]), 3)
                for i, s in enumerate(self.names[:self.n_accel])}

    def named_statuses(self) -> tuple[tuple[str, str], ...]:
        """Each sensor's status by name."""
        codes = self.status_codes.tolist()
        return tuple((s, SENSOR_STATUS[c]) for s, c in zip(self.names, codes, strict=True))

    def counters(self) -> dict[str, dict[str, int]]:
        return {s: {c: int(self.counts[i, k]) for k, c in enumerate(COUNTERS)}
                for i, s in enumerate(self.names)}


def sensor_warnings(counters: dict[str, dict[str, int]], nis: dict[str, tuple[float, int, int]],
                    floors_g: dict[str, float], floors_said: dict[str, str], settings: TrackerSettings
                    ) -> list[str]:
    """One line per accelerometer its gate rejected, or its screen left out as implausible,
    more often than ``settings.warn_rejected_share`` of its samples: how often, against what
    the gate expects, its mean NIS, its unmodelled-error floor (and where that came from), and
    what to look at. ``counters``, ``nis``: the tracker's (:meth:`Tracker.counters`,
    :meth:`Tracker.nis_stats`); ``floors_g``: each accelerometer's floor in g."""
    out = []
    for s, floor in floors_g.items():
        c = counters.get(s)
        if not c or not c["samples"]:
            continue
        n = c["samples"]
        rejected, implausible = c["rejected"] / n, c["implausible"] / n
        mean, count, dof = nis.get(s, (float("nan"), 0, 3))
        where = floors_said.get(s)
        floor_said = f"{floor:g} g" + (f", its class's ({where})" if where else ", as the config gives it")
        if rejected > settings.warn_rejected_share:
            nis_said = f"mean NIS {mean:.1f} against {dof}" if count else "no NIS kept"
            out.append(
                f"{s}: the gate rejected {100 * rejected:.0f} % of its samples (a sensor its model fits: "
                f"{100 * settings.gate_significance:.1f} %): its readings sit further from the prediction "
                f"than its noise and unmodelled error ({floor_said}) allow ({nis_said}); something of it "
                "is not modelled (a scale, a mount, a delay, a base that moves): `calibrate sensors`, or "
                f"state its error (calibration.accel_unmodelled_g_per_sensor.{s})")
        if implausible > settings.warn_rejected_share:
            out.append(
                f"{s}: {100 * implausible:.0f} % of its samples left out as implausible (their magnitude "
                "far from the predicted one): a dead or disconnected sensor, wrong units, or an estimate "
                "of the base's motion gone wrong")
    return out
