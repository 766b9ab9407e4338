"""``armfusion replay REC``: publish a recording's raw samples over Zenoh, with their timing.

The recording's raw streams are cut into windows of ``batch_s`` of recording time; each
window's samples of one sensor go out as one :class:`~armfusion.fusion.service.payloads.RawBatch`
on ``armfusion/<robot>/raw/<sensor>`` when the wall clock reaches the window's end
(scaled by :attr:`ReplayPacing.speed`; ``speed=None`` publishes as fast as the subscribers take them: the
publishers block rather than drop). A :class:`~armfusion.fusion.service.payloads.Status` goes out
on ``armfusion/<robot>/status`` at the start and at the end, with the samples published
per sensor.

Whether anything hears it is Zenoh's matching status of each publisher (a subscriber whose
key expression matches, anywhere the session reaches). With ``require_subscriber``,
:func:`replay` first waits up to ``wait_for_subscribers_s`` (its :class:`ReplayPacing`) for one and raises
:class:`NoSubscriberError` (nothing published) when no sensor's key has any; every batch
put while its key had no subscriber is counted in :attr:`ReplayReport.unheard`, so a
subscriber that leaves half-way shows too. ``armfusion replay`` exits 1 in both cases. A
subscriber is not yet a receiver (a router's access-control policy may drop the puts):
``armfusion replay`` also reads the fusion node's status (:mod:`armfusion.fusion.service.admitted`)
and exits 1 when it admitted none of the samples.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import zenoh
from armfusion.fusion.service import payloads as pl
from armfusion.sensors.samples import Recording, Stream

log = logging.getLogger("armfusion.service")

DEFAULT_BATCH_S = 0.02


class NoSubscriberError(RuntimeError):
    """Nothing subscribes to the replay's raw keys: publishing would reach nobody."""


@dataclass(frozen=True)
class ReplayReport:
    """What a replay published."""

    robot: str
    samples: dict[str, int]
    batches: int
    wall_s: float
    stopped: bool = False
    unmatched: tuple[str, ...] = field(default=())
    """Sensors whose key had no subscriber when the wait for one ended."""
    unheard: dict[str, int] = field(default_factory=dict)
    """Samples per sensor put while its key had no subscriber (sensors with none left out)."""

    def as_dict(self) -> dict:
        return {"robot": self.robot, "samples": self.samples, "batches": self.batches,
                "wall_s": round(self.wall_s, 3), "stopped": self.stopped,
                "unmatched": list(self.unmatched), "unheard": dict(self.unheard)}


def _windows(streams: dict[str, Stream], t0: float, t1: float, batch_s: float):
    """``(t_end, {sensor: (i0, i1)})`` for each window of ``batch_s`` holding samples."""
    n = max(1, int(np.ceil((t1 - t0) / batch_s + 1e-9)) + 1)
    edges = t0 + batch_s * np.arange(1, n + 1)
    cuts = {k: np.searchsorted(s.t_s, edges, side="left") for k, s in streams.items()}
    start = {k: 0 for k in streams}
    for w in range(n):
        spans = {}
        for k, c in cuts.items():
            i1 = int(c[w]) if w < n - 1 else len(streams[k])
            if i1 > start[k]:
                spans[k] = (start[k], i1)
                start[k] = i1
        if spans:
            yield float(edges[w]), spans


def _wait_for_subscribers(pubs: dict[str, zenoh.Publisher], wait_s: float,
                          stop: threading.Event) -> tuple[str, ...]:
    """Wait up to ``wait_s`` until every publisher has a matching subscriber."""
    deadline = time.monotonic() + wait_s
    while True:
        missing = tuple(k for k, p in pubs.items() if not p.matching_status.matching)
        if not missing or stop.is_set() or time.monotonic() >= deadline:
            return missing
        stop.wait(0.02)


@dataclass(frozen=True)
class ReplayPacing:
    """How a replay publishes: ``speed`` times the recording's pace (``None``: as fast as the
    subscribers take the samples), in windows of ``batch_s`` of recording time; first waiting
    up to ``wait_for_subscribers_s`` for a subscriber on every raw key (the sensors named in
    :attr:`ReplayReport.unmatched` had none by then); with ``require_subscriber``, raising
    :class:`NoSubscriberError`, publishing nothing, when no raw key has a subscriber after that
    wait."""

    speed: float | None = 1.0
    batch_s: float = DEFAULT_BATCH_S
    wait_for_subscribers_s: float = 0.0
    require_subscriber: bool = False

    def __post_init__(self) -> None:
        if self.speed is not None and not self.speed > 0:
            raise ValueError(f"speed must be > 0 (or None for as fast as possible), got {self.speed!r}")
        if not self.batch_s > 0:
            raise ValueError(f"batch_s must be > 0, got {self.batch_s!r}")


def replay(session: zenoh.Session, rec: Recording, robot: str, pacing: ReplayPacing | None = None, *,
           stop: threading.Event | None = None, on_start: Callable[[], None] | None = None) -> ReplayReport:
    """Publish the raw streams of ``rec`` as robot ``robot``, paced by ``pacing`` (``None``:
    at the recording's pace, not waiting for subscribers); see the module's docstring.
    ``stop``: ends the replay early when set. ``on_start``: called once, as the publishing
    starts (after the wait), e.g. :meth:`armfusion.fusion.service.admitted.AdmissionWatch.start`.
    """
    pacing = ReplayPacing() if pacing is None else pacing
    speed, batch_s = pacing.speed, pacing.batch_s
    wait_for_subscribers_s = pacing.wait_for_subscribers_s
    stop = stop or threading.Event()
    streams = {k: s for k, s in rec.raw().items() if len(s)}
    if not streams:
        raise ValueError("the recording has no raw samples to replay")
    t0, t1 = min(s.t_s[0] for s in streams.values()), max(s.t_s[-1] for s in streams.values())
    status_pub = session.declare_publisher(pl.status_key(robot))
    pubs = {k: session.declare_publisher(pl.raw_key(robot, k),
                                         congestion_control=zenoh.CongestionControl.BLOCK)
            for k in streams}
    unmatched = _wait_for_subscribers(pubs, wait_for_subscribers_s, stop) if wait_for_subscribers_s else ()
    if pacing.require_subscriber and all(not p.matching_status.matching for p in pubs.values()):
        for p in (*pubs.values(), status_pub):
            p.undeclare()
        raise NoSubscriberError(
            f"nothing subscribes to {pl.raw_keys(robot)} (waited {wait_for_subscribers_s:g} s): is "
            "`armfusion serve` or `record` running, for this robot, and connected to this node? "
            "Nothing was published")
    samples = {k: 0 for k in streams}
    unheard = {k: 0 for k in streams}
    seq = {k: 0 for k in streams}
    batches = 0

    def status(state: str, message: str) -> None:
        counters = tuple((f"samples.{k}", v) for k, v in samples.items()) + (("batches", batches),)
        status_pub.put(pl.encode(pl.Status(robot, "replay", state, time.time(), message, counters)))

    status("running", f"replaying {t1 - t0:.2f} s of {len(streams)} sensors")
    if on_start is not None:
        on_start()
    wall0 = time.monotonic()
    for t_end, spans in _windows(streams, t0, t1, batch_s):
        if speed is not None:
            delay = wall0 + (t_end - t0) / speed - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
        if stop.is_set():
            break
        for k, (i0, i1) in spans.items():
            s = streams[k]
            part = Stream(s.name, s.kind, s.t_s[i0:i1], s.values[i0:i1], s.channels)
            if not pubs[k].matching_status.matching:
                unheard[k] += i1 - i0
            pubs[k].put(pl.encode(pl.RawBatch(robot, part, seq[k])))
            seq[k] += 1
            samples[k] += i1 - i0
            batches += 1
    wall = time.monotonic() - wall0
    stopped = stop.is_set()
    status("done", "stopped" if stopped else f"published {sum(samples.values())} samples in {wall:.2f} s")
    for p in pubs.values():
        p.undeclare()
    status_pub.undeclare()
    return ReplayReport(robot, samples, batches, wall, stopped, unmatched,
                        {k: n for k, n in unheard.items() if n})
