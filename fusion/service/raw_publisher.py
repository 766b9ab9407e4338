"""Raw samples out over Zenoh, as ``armfusion drivers --robot R`` reads them.

:class:`RawPublisher` takes batches of raw streams (one :class:`~armfusion.sensors.samples.Stream`
per sensor, the samples read since the last batch) and puts each on
``armfusion/<robot>/raw/<sensor>`` as a :class:`~armfusion.fusion.service.payloads.RawBatch`, with a
per-sensor ``seq``; the publishers block rather than drop when a subscriber falls behind
(``CongestionControl.BLOCK``). A :class:`~armfusion.fusion.service.payloads.Status` of node
``drivers`` goes out on ``armfusion/<robot>/status`` when it starts, about once a second
of wall time, and when it stops, with the samples published per sensor
(``samples.<sensor>``) and the batches.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterable

import zenoh
from armfusion.fusion.service import payloads as pl
from armfusion.sensors.samples import Stream

STATUS_PERIOD_S = 1.0


class RawPublisher:
    """Publishes raw batches of one robot on ``session`` (see the module's docstring)."""

    def __init__(self, session: zenoh.Session, robot: str, *, message: str = ""):
        self.session = session
        self.robot = pl.check_name(robot, "robot")
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._seq: Counter[str] = Counter()
        self._samples: Counter[str] = Counter()
        self._batches = 0
        self._lock = threading.Lock()
        self._status = session.declare_publisher(pl.status_key(self.robot))
        self._next_status = 0.0
        self._message = message

    def _publisher(self, sensor: str) -> zenoh.Publisher:
        pub = self._pubs.get(sensor)
        if pub is None:
            pub = self.session.declare_publisher(pl.raw_key(self.robot, sensor),
                                                 congestion_control=zenoh.CongestionControl.BLOCK)
            self._pubs[sensor] = pub
        return pub

    def wait_for_subscriber(self, sensor: str, timeout_s: float, stop: threading.Event) -> bool:
        """Wait up to ``timeout_s`` until something subscribes to ``sensor``'s key."""
        pub = self._publisher(sensor)
        deadline = time.monotonic() + timeout_s
        while not pub.matching_status.matching:
            if stop.is_set() or time.monotonic() >= deadline:
                return False
            stop.wait(0.02)
        return True

    def publish(self, streams: Iterable[Stream]) -> None:
        """Put each non-empty stream as one batch; a status at most once a second."""
        for s in streams:
            if not len(s):
                continue
            with self._lock:
                seq = self._seq[s.name]
                self._seq[s.name] += 1
            self._publisher(s.name).put(pl.encode(pl.RawBatch(self.robot, s, seq)))
            with self._lock:
                self._samples[s.name] += len(s)
                self._batches += 1
        if time.monotonic() >= self._next_status:
            self.status("running", self._message)

    def status(self, state: str, message: str = "") -> None:
        self._next_status = time.monotonic() + STATUS_PERIOD_S
        with self._lock:
            counters = tuple((f"samples.{k}", v) for k, v in sorted(self._samples.items()))
            counters += (("batches", self._batches),)
        self._status.put(pl.encode(pl.Status(self.robot, "drivers", state, time.time(), message,
                                             counters)))

    @property
    def samples(self) -> dict[str, int]:
        """Samples published, per sensor."""
        with self._lock:
            return dict(self._samples)

    @property
    def batches(self) -> int:
        with self._lock:
            return self._batches

    def close(self, message: str = "") -> None:
        """A last status (``done``) and the publishers undeclared."""
        self.status("done", message)
        for p in self._pubs.values():
            p.undeclare()
        self._status.undeclare()
