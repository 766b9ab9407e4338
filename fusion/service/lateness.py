"""When the fusion node falls behind: its lateness policy (:class:`Lateness`), the watch
that judges its lag and whether it is degraded (:class:`LagWatch`), and what it does while
degraded: fold the waiting instants (:meth:`LagWatch.fold`) and shed the batches that
waited too long (:func:`shed_samples`). See docs/service-node.md, "When the node falls
behind"."""

from __future__ import annotations

import json
import logging
from collections import deque
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.service import payloads as pl

log = logging.getLogger("armfusion.service")


@dataclass(frozen=True)
class Lateness:
    """How the fusion node degrades when it falls behind (see docs/service-node.md, "When the node
    falls behind").

    The node's lag is how far the samples it last took in are behind the sensors' time now,
    in wall time: now, less the usual delivery delay (the median over the streams of the
    least delay of each one's batches in the last ``delay_window_s``: arrival less sample
    time), less the last sample's time. It counts the node's own queue as well as a stall
    of the whole process (whose messages then arrive late together). While the stream is
    live (``max_pace``), beyond
    ``degrade_after_s`` the node is degraded (the status's ``degraded`` 1, its ``lag_ms``,
    and a message saying so) until its lag is back within half of it, or nothing waits, and
    it was last behind more than ``hold_s`` ago. While
    degraded, each pass of the loop takes every message waiting (for at most ``pass_s`` of
    wall time), admits each and queues its samples, then fuses once: the instants more than
    ``degrade_after_s`` older than the sensors' clock are folded, merged into one instant
    per ``fold_period_s`` of sample time, or into ``backlog_updates`` instants when they
    span longer (each sensor's latest sample in a window, at its last instant's time); the
    newer ones are merged one window per ``fold_period_s`` too (the update rate lowered:
    a node short of CPU spends less of it on the tracker); the joint states go out as usual
    (at most ``publish_hz``), so the folded instants have none. The startup's kept samples
    are fused the same way. Every sample still goes through the admission and is counted,
    but those of the batches shed (``shed_after_s``); the folded instants' samples are
    what the tracker does not see one by one.
    """

    degrade_after_s: float = 0.05
    hold_s: float = 1.0
    """Once degraded, the node stays so until it was last behind (its lag over
    ``degrade_after_s``) this long ago: one status period (statuses go out every second), so
    a node that falls behind again and again on a starved machine (its lag back under the
    line between the scheduler's slices) is one degraded period, said once, in every status
    it spans, and folds the while through, instead of flipping at every slice."""
    fold_period_s: float = 0.02
    backlog_updates: int = 10
    """A backlog longer than this many fold periods is folded into this many instants: the
    tracker's work on a backlog of any length is bounded, so a node that can take its
    messages in catches up."""
    pass_s: float = 0.025
    """A pass takes messages for at most half ``degrade_after_s``: the samples taken first
    wait no longer than that before they are fused."""
    max_pace: float = 2.0
    """Live only: while the sensors' newest time ran more than this many times as fast as
    wall time over the arrivals of the last ``pace_window_s`` the node has taken in (a
    replay faster than real time; judged once they span ``pace_min_s``), or the stream's
    arrivals began less than half ``pace_window_s`` ago in wall time (a stream just begun;
    after a silence of ``pace_window_s`` it begins again), the node is not degraded: every
    instant is fused one by one however long it takes (such a stream has no real time to
    be late against)."""
    pace_window_s: float = 4.0
    pace_min_s: float = 0.5
    """The pace is judged once the arrivals the node has taken in span this long: a node
    behind from the stream's start (its startup calibration, a starved CPU) judges it
    before it has taken in half ``pace_window_s`` of them, and degrades."""
    shed_after_s: float = 0.5
    """While degraded and tracking, of the messages that waited longer than this in the
    node's receive channel (arrival to now: ten times ``degrade_after_s``, a backlog the
    folding is not working off: a node that takes its messages in as fast as they come is
    back within ``degrade_after_s`` in a few passes), a pass keeps each sensor's newest
    and sheds the others unread: counted (``shed_batches``, and their samples), never
    admitted, refused nor fused, their batch numbers not counted as missed. A node that
    cannot even take its messages in as fast as they come keeps its lag bounded. (Before
    it tracks, none: the startup calibration gets every sample.)"""
    delay_window_s: float = 60.0
    """The usual delivery delay is the least of this long: a lag that grows slowly (a node
    a little short of CPU for a minute) is not taken for the usual delay."""


class LagWatch:
    """The fusion node's lag behind the sensors and whether it is degraded, judged from the
    accepted batches' arrivals and times under the policy ``lateness`` (:class:`Lateness`).

    ``degraded``, ``lag_s`` (the last judged), ``lag_max_s``, ``periods`` (how many times it
    became degraded), ``folded`` (instants merged into another) and ``news`` (it became
    degraded since the owner last cleared it) are read by the node's status."""

    def __init__(self, lateness: Lateness):
        self.lateness = lateness
        self.degraded = False
        self.news = False
        self.lag_s = 0.0
        self.lag_max_s = 0.0
        self.periods = 0
        self.folded = 0
        self._pace_marks: deque[tuple[float, float, float]] = deque()  # see _mark_pace
        self._pace_arrived_s = -np.inf
        self._run_began_s = -np.inf  # the first arrival after a silence of pace_window_s (or ever)
        self._delays: dict[str, deque[tuple[float, float]]] = {}  # see _note_delay
        self._taken_t: float | None = None  # the last sample time of the last batch accepted
        self._behind_s = -np.inf  # wall time the lag was last judged over degrade_after_s

    def taken(self, name: str, arrived_s: float, t_s: float) -> None:
        """Note a batch of sensor ``name`` accepted, arrived at ``arrived_s``, its last sample
        at ``t_s``."""
        self._taken_t = t_s
        self._mark_pace(arrived_s, t_s)
        self._note_delay(name, arrived_s, t_s)

    def forget(self, name: str) -> None:
        """Let go of sensor ``name``'s delivery delays (its clock was reset)."""
        self._delays.pop(name, None)

    def nothing_waits(self, now_s: float) -> bool:
        """Nothing waits in the node's channel at wall time ``now_s``: whatever it was behind,
        it has taken in; no longer degraded once it was last behind ``hold_s`` ago. True when
        that changed."""
        self.lag_s = 0.0
        if not self.degraded or now_s - self._behind_s < self.lateness.hold_s:
            return False
        self.degraded = False
        log.info("serve: caught up (nothing waiting); no longer degraded")
        return True

    def sensors_now(self, now_s: float) -> float | None:
        """The sensors' time at wall time ``now_s`` as their delivery says it: ``now_s``
        less the usual delivery delay (the median over the streams of the least delay,
        arrival less last sample's time, of each one's batches in the last
        ``delay_window_s``); ``None`` before any."""
        lows = sorted(d[0][1] for d in self._delays.values() if d)
        return None if not lows else now_s - lows[(len(lows) - 1) // 2]

    def _note_delay(self, name: str, arrived_s: float, t_s: float) -> None:
        """Note an accepted batch's delivery delay (a sliding minimum per stream)."""
        d = self._delays.setdefault(name, deque())
        delay = arrived_s - t_s
        while d and d[-1][1] >= delay:
            d.pop()
        d.append((arrived_s, delay))
        while d[0][0] < arrived_s - self.lateness.delay_window_s:
            d.popleft()

    def judge(self, now_s: float) -> bool:
        """The node's lag at wall time ``now_s`` (how far the samples it last took are behind
        the sensors' time now), and whether it is degraded; True when that changed."""
        lt = self.lateness
        sensors_now = self.sensors_now(now_s)
        if sensors_now is None or self._taken_t is None:
            return False
        lag = max(sensors_now - self._taken_t, 0.0)
        self.lag_s, self.lag_max_s = lag, max(self.lag_max_s, lag)
        was = self.degraded
        if not self.live(now_s):
            self.degraded = False
        elif lag > lt.degrade_after_s:
            self.degraded, self._behind_s = True, now_s
        elif lag <= 0.5 * lt.degrade_after_s and now_s - self._behind_s >= lt.hold_s:
            self.degraded = False
        if self.degraded == was:
            return False
        if self.degraded:
            self.news = True
            self.periods += 1
            log.warning("serve: degraded: %.0f ms behind the sensors; folding the backlog", 1e3 * lag)
        else:
            log.info("serve: caught up (%.0f ms behind); no longer degraded", 1e3 * lag)
        return True

    def live(self, now_s: float) -> bool:
        """Whether the stream is live: its arrivals began at least half ``pace_window_s``
        ago (wall time ``now_s``, whatever the node has taken in of them since), and the
        sensors' time ran at about wall time (at most the lateness policy's ``max_pace``
        times as fast) over the arrivals of the last ``pace_window_s`` the node has taken
        in, once they span ``pace_min_s``."""
        lt = self.lateness
        marks = self._pace_marks
        if not marks:
            return False
        wall = self._pace_arrived_s - marks[0][0]
        return (now_s - self._run_began_s >= 0.5 * lt.pace_window_s and wall >= lt.pace_min_s
                and marks[-1][2] - marks[0][1] <= lt.max_pace * wall)

    def _mark_pace(self, arrived_s: float, t_s: float) -> None:
        """Note an accepted batch's last time ``t_s``, arrived at ``arrived_s``: per 0.1 s of
        arrivals, its first arrival, its first batch's time and the newest time; those of the
        last ``pace_window_s`` kept. (A silence its time did not run through is not judged a
        paused source: at arrival it cannot be told from a node that was itself stopped.)"""
        marks = self._pace_marks
        if arrived_s - self._pace_arrived_s > self.lateness.pace_window_s:
            self._run_began_s = arrived_s
        self._pace_arrived_s = max(self._pace_arrived_s, arrived_s)
        if marks and arrived_s < marks[-1][0] + 0.1:
            if t_s > marks[-1][2]:
                marks[-1] = (*marks[-1][:2], t_s)
            return
        marks.append((arrived_s, t_s, t_s))
        while marks[0][0] < arrived_s - self.lateness.pace_window_s:
            marks.popleft()

    def fold(self, instants, now_s: float):
        """``instants`` merged, each sensor's latest sample in a window at its last instant's
        time: those older than the sensors' clock at wall time ``now_s`` by more than the
        lateness policy's ``degrade_after_s`` one window per ``fold_period_s`` of sample time,
        or ``backlog_updates`` windows when they span longer; the newer ones one window per
        ``fold_period_s`` (the update rate lowered while the node is behind)."""
        if not instants:
            return instants
        lt = self.lateness
        clock = self.sensors_now(now_s)
        stale_before = -np.inf if clock is None else clock - lt.degrade_after_s
        n_stale = next((i for i, (t, _) in enumerate(instants) if t >= stale_before), len(instants))
        # the longer the backlog, the longer a window: at most backlog_updates of them
        period = lt.fold_period_s if not n_stale else max(
            lt.fold_period_s, (stale_before - instants[0][0]) / lt.backlog_updates)
        return self._merged(instants[:n_stale], period) + self._merged(instants[n_stale:], lt.fold_period_s)

    def _merged(self, instants, period_s: float) -> list[tuple[float, dict[str, np.ndarray]]]:
        """``instants`` merged into windows of ``period_s`` from the first (see :meth:`fold`);
        the instants merged into another are counted in ``folded``."""
        out: list[tuple[float, dict[str, np.ndarray]]] = []
        window_end, merged, t_last = -np.inf, None, None
        for t, samples in instants:
            if merged is not None and t > window_end:
                out.append((t_last, merged))
                merged = None
            if merged is None:
                merged, window_end = {}, t + period_s - 1e-9
            merged.update(samples)
            t_last = t
        if merged is not None:
            out.append((t_last, merged))
        self.folded += len(instants) - len(out)
        return out


def shed_samples(data: bytes) -> int:
    """How many samples a raw batch's payload ``data`` holds, read for its count alone (the
    batch shed unread, :class:`Lateness`, ``shed_after_s``): 0 for what the decoder would not
    read either."""
    if len(data) > pl.MAX_PAYLOAD_BYTES:
        return 0
    try:  # (the JSON parser's C alone: no check, no array, no sample handled in Python)
        values = json.loads(data).get("values")
    except (ValueError, AttributeError, RecursionError):
        return 0
    return len(values) if isinstance(values, list) else 0
