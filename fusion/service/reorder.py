"""The fusion node's merging of its sensors' batches in time.

The sensors' batches come in separately and a little out of step, while the tracker takes
instants in time order (it drops a sample older than the last). :class:`Reorder` queues each
sensor's samples and releases merged instants once every sensor heard from in the last
``max_lag_s`` has sent something at least as late, or once they are ``max_lag_s`` older than
the newest sample (a silent sensor does not stall the others). Given the sensors' clock
(:meth:`armfusion.fusion.service.admission.Admission.clock`), the newest sample is taken no later
than it: one stream whose stamps run ahead of the others (within what the admission lets
through) waits in its queue instead of making the others' samples late. :func:`merge_batches` makes one
recording of kept batches, for the startup calibration.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np
from armfusion.sensors.samples import Recording, Stream


class Reorder:
    """Per-sensor queues of ``(t_s, counts)``, released merged in time (see the module).

    Plain Python queues: a driver sends one or a few samples per batch, for which NumPy's
    per-call overhead would cost more than the work."""

    def __init__(self, max_lag_s: float):
        self.max_lag_s = max_lag_s
        self._q: dict[str, deque[tuple[float, np.ndarray]]] = {}
        self._last: dict[str, float] = {}
        self._released = -np.inf

    def push(self, s: Stream) -> int:
        """Queue a batch; returns how many of its samples were already too late (dropped)."""
        q = self._q.setdefault(s.name, deque())
        released, late = self._released, 0
        times = s.t_s.tolist()
        for t, v in zip(times, s.values, strict=True):
            if t <= released:
                late += 1
            elif not q or t > q[-1][0]:
                q.append((t, v))
            else:  # earlier than what is queued (a batch overtook another): keep the queue in order
                bisect.insort(q, (t, v), key=lambda item: item[0])
        if times[-1] > self._last.get(s.name, -np.inf):
            self._last[s.name] = times[-1]
        return late

    def forget(self, name: str) -> None:
        """Drop what is queued of ``name`` and its newest time (its clock was refuted)."""
        self._q.pop(name, None)
        self._last.pop(name, None)

    def seen(self, name: str, t_s: float) -> None:
        """Note that ``name`` has sent everything up to ``t_s`` (before any push of it)."""
        self._last[name] = max(self._last.get(name, -np.inf), t_s)

    def release(self, flush: bool = False, clock_s: float | None = None
                ) -> list[tuple[float, dict[str, np.ndarray]]]:
        """The instants that are safe to fuse, in time order: ``(t_s, {sensor: counts})``;
        ``clock_s``: the sensors' time now (see the module), ``flush``: everything queued."""
        if not self._last:
            return []
        newest = max(self._last.values())
        if clock_s is not None and not flush:
            newest = min(newest, clock_s)
        alive = [t for t in self._last.values() if t >= newest - self.max_lag_s]
        mark = newest if flush else max(min(alive), newest - self.max_lag_s)
        if mark <= self._released:  # nothing queued is that old (push drops what is)
            return []
        items: list[tuple[float, str, np.ndarray]] = []
        for k, q in self._q.items():
            while q and q[0][0] <= mark:
                t, v = q.popleft()
                items.append((t, k, v))
        if not items:
            return []
        items.sort(key=lambda item: item[0])  # stable: a sensor's samples keep their order
        out: list[tuple[float, dict[str, np.ndarray]]] = []
        for t, k, v in items:
            if not out or out[-1][0] != t:
                out.append((t, {}))
            out[-1][1][k] = v
        self._released = max(self._released, items[-1][0])
        return out


def merge_batches(parts: dict[str, list[Stream]], t_from_s: float = -np.inf) -> Recording:
    """One recording of the batches in ``parts`` (from ``t_from_s`` on), in time order; a
    repeated sample is ignored. (The admission keeps the batches' times within a bounded
    window and their channels the config's; this stays in order whatever comes.)"""
    streams = {}
    for k, ps in parts.items():
        if not ps:
            continue
        t = np.concatenate([p.t_s for p in ps])
        v = np.concatenate([p.values for p in ps])
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        keep = np.concatenate([[True], np.diff(t) > 0]) & (t >= t_from_s)
        if np.any(keep):
            streams[k] = Stream(k, ps[0].kind, t[keep], v[keep], ps[0].channels)
    return Recording(streams)
