"""``armfusion record OUT.mcap``: record one robot's raw samples and estimates from Zenoh.

Subscribes to ``armfusion/<robot>/raw/*`` and ``armfusion/<robot>/state/*``, checks each
payload (:class:`~armfusion.fusion.service.inbox.Inbox`: a bad one is counted and dropped) and
writes it through :class:`~armfusion.sensors.recording_mcap.McapRecorder`: raw batches as the
recording's streams (``armfusion replay`` of the result publishes them again), joint
states and headings as their records (:mod:`armfusion.fusion.tracking.estimate`: the payload without
its envelope) on ``estimates/joints`` and ``estimates/heading``. The chunk
in progress is flushed at least every ``flush_interval_s`` (1 s), also while nothing
arrives, so a recorder killed with SIGKILL loses at most about that much; on SIGINT or
SIGTERM the file is closed cleanly.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import zenoh
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.inbox import Inbox
from armfusion.fusion.service.node import BoundedReceiver
from armfusion.fusion.tracking.estimate import MCAP_CHANNELS, write_mcap_record
from armfusion.sensors.recording_mcap import McapRecorder

log = logging.getLogger("armfusion.service")


@dataclass(frozen=True)
class RecordReport:
    """What a recorder wrote and what it dropped."""

    path: Path
    samples: dict[str, int]
    estimates: dict[str, int]
    received: int
    dropped: dict[str, int]
    wall_s: float

    def as_dict(self) -> dict:
        return {"path": str(self.path), "samples": self.samples, "estimates": self.estimates,
                "received": self.received, "dropped": self.dropped, "wall_s": round(self.wall_s, 3)}


class Recorder:
    """Subscribes on ``session`` and writes to ``path`` until :meth:`run`'s ``stop`` is set.

    :attr:`ready` is set once the subscriptions are declared; :meth:`counts` may be read
    from another thread while it runs.
    """

    def __init__(self, session: zenoh.Session, path: str | Path, robot: str, *,
                 arm_config: str = "", flush_interval_s: float = 1.0):
        if not 0 < flush_interval_s <= 1.0:
            raise ValueError(f"flush_interval_s must be in (0, 1] s, got {flush_interval_s!r}")
        self.session = session
        self.path = Path(path)
        self.robot = pl.check_name(robot, "robot")
        self.arm_config = arm_config
        self.flush_interval_s = flush_interval_s
        self.ready = threading.Event()
        self._inbox = Inbox("record")
        self._lock = threading.Lock()
        self._samples: Counter[str] = Counter()
        self._estimates: Counter[str] = Counter()
        self._rejected: Counter[str] = Counter()

    def counts(self) -> dict[str, int]:
        """Raw samples written, per sensor."""
        with self._lock:
            return dict(self._samples)

    def run(self, stop: threading.Event) -> RecordReport:
        """Record until ``stop`` is set; the file is complete when this returns."""
        wall0 = time.monotonic()
        receiver = BoundedReceiver()
        subs = [self.session.declare_subscriber(k, receiver)
                for k in (pl.raw_keys(self.robot), f"{pl.ROOT}/{self.robot}/state/*")]
        try:
            with McapRecorder(self.path, arm_config=self.arm_config,
                              flush_interval_s=self.flush_interval_s) as mcap:
                self.ready.set()
                self._loop(mcap, receiver, stop)
        finally:
            receiver.closed.set()
            for s in subs:
                s.undeclare()
        dropped = Counter(self._inbox.dropped) + self._rejected
        if receiver.overflowed:
            dropped["overflow"] += receiver.overflowed
        with self._lock:
            return RecordReport(self.path, dict(self._samples), dict(self._estimates),
                                self._inbox.received, dict(dropped), time.monotonic() - wall0)

    def _loop(self, mcap: McapRecorder, receiver: BoundedReceiver, stop: threading.Event) -> None:
        last_flush = time.monotonic()
        flushed_at = mcap.messages_written
        while not stop.is_set():
            msg = receiver.get(timeout_s=min(0.1, last_flush + self.flush_interval_s - time.monotonic()))
            if msg is not None:
                self._write(mcap, msg)
            if time.monotonic() - last_flush >= self.flush_interval_s:
                if mcap.messages_written != flushed_at:
                    mcap.flush()
                    flushed_at = mcap.messages_written
                last_flush = time.monotonic()
        while (msg := receiver.get_nowait()) is not None:  # what arrived before the stop
            self._write(mcap, msg)

    def _write(self, mcap: McapRecorder, msg) -> None:
        payload = self._inbox.decode(msg.key, msg.data)
        if payload is None:
            return
        try:
            if isinstance(payload, pl.RawBatch):
                mcap.write_stream(payload.stream)
                with self._lock:
                    self._samples[payload.stream.name] += len(payload.stream)
            elif isinstance(payload, pl.JointState | pl.Heading):
                kind = "joints" if isinstance(payload, pl.JointState) else "heading"
                write_mcap_record(mcap, kind, payload.record())
                with self._lock:
                    self._estimates[MCAP_CHANNELS[kind][0]] += 1
        except ValueError as e:  # out of order, before the time origin, a changed stream
            with self._lock:
                self._rejected["rejected"] += 1
            log.warning("record: dropped a payload on %s (rejected): %s", msg.key, str(e)[:200])
