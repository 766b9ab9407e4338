"""Whether a publisher's raw samples reach the fusion node and are admitted, from its status.

Zenoh's matching status says only that a subscriber's interest reached the publisher. Under
an access-control policy a router may forward that interest and still drop the puts
(config/deploy/chair.json5 lets the user ``drivers`` alone put raw samples): the publisher
sees a subscriber, sends, and nothing arrives. So a publisher of raw samples (``armfusion
replay``, ``drivers --robot``) also reads the fusion node's status on
``armfusion/<robot>/status`` (node ``serve``, once a second): its ``samples`` counter, the raw
samples it admitted, and its ``dropped.<reason>`` counters.

:class:`AdmissionWatch` takes the fusion node's counters when the first batch goes out
(:meth:`AdmissionWatch.start`) and decides:

- ``admitted``: a status heard since shows ``samples`` above that;
- ``refused``: ``timeout_s`` after the first batch, statuses came and none shows more samples:
  the message says whether the node dropped batches meanwhile (by reason: the admission
  refused them) or nothing reached it (a router's policy dropped the puts, or they went
  elsewhere);
- ``unknown``: no fusion node of this robot is heard (no status, no liveliness token), e.g.
  only a recorder listens: nothing to judge by.

The node's counters are totals over every publisher of the robot: samples another publisher
sends at the same time count as admitted too.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import zenoh
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.inbox import Inbox

FUSION_NODE = "serve"
STATUS_PERIOD_S = 1.0
"""The fusion node publishes its status once a second (fusion/service/serve.py)."""
TOKEN_HISTORY_S = 0.3
"""How long the liveliness tokens already declared take to arrive, at most, on loopback."""


@dataclass(frozen=True)
class Admission:
    """The watch's verdict (see the module's docstring)."""

    state: str
    message: str
    admitted: int = 0
    """Samples the fusion node admitted since the first batch, by the status that decided
    (its counter's increase: a lower bound of what it admits by the end)."""
    dropped: dict[str, int] = field(default_factory=dict)
    """Its dropped counters' increase since, by reason."""

    def as_dict(self) -> dict:
        return {"state": self.state, "message": self.message, "admitted": self.admitted,
                "dropped": dict(self.dropped)}


@dataclass(frozen=True)
class _Counters:
    arrived_s: float
    samples: int
    dropped: dict[str, int]


class AdmissionWatch:
    """Reads the fusion node's status of ``robot`` on ``session`` (see the module's docstring)."""

    def __init__(self, session: zenoh.Session, robot: str, timeout_s: float):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.robot = pl.check_name(robot, "robot")
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        self._inbox = Inbox("admission watch")
        self._latest: _Counters | None = None
        self._alive = False
        self._created_s = time.monotonic()
        self._start: tuple[float, _Counters] | None = None
        self._verdict: Admission | None = None
        key = pl.status_key(self.robot)
        self._subs = [session.declare_subscriber(key, self._on_status),
                      session.liveliness().declare_subscriber(key, self._on_token, history=True)]

    def _on_status(self, sample: zenoh.Sample) -> None:
        status = self._inbox.decode(str(sample.key_expr), sample.payload.to_bytes())
        if not isinstance(status, pl.Status) or status.node != FUSION_NODE:
            return
        counters = dict(status.counters)
        dropped = {k.removeprefix("dropped."): v for k, v in counters.items() if k.startswith("dropped.")}
        with self._lock:
            self._latest = _Counters(time.monotonic(), int(counters.get("samples", 0)), dropped)

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._alive = sample.kind == zenoh.SampleKind.PUT

    def wait_for_node(self, stop: threading.Event, timeout_s: float = 1.5 * STATUS_PERIOD_S) -> bool:
        """Wait until the fusion node's status is heard (True), up to ``timeout_s`` while its
        liveliness token says it lives; False at once when none does."""
        deadline = time.monotonic() + timeout_s
        while not stop.is_set():
            now = time.monotonic()
            with self._lock:
                heard, alive = self._latest is not None, self._alive
            if heard:
                return True
            if now >= deadline or (not alive and now >= self._created_s + TOKEN_HISTORY_S):
                return False
            stop.wait(0.02)
        return False

    def start(self) -> None:
        """The first batch goes out now: the fusion node's counters so far are the baseline
        (none heard: it starts from zero)."""
        with self._lock:
            if self._start is None:
                self._start = (time.monotonic(), self._latest or _Counters(0.0, 0, {}))

    @property
    def started(self) -> bool:
        with self._lock:
            return self._start is not None

    def check(self) -> Admission | None:
        """The verdict once there is one (it then stays), else ``None``."""
        with self._lock:
            if self._verdict is not None or self._start is None:
                return self._verdict
            t0, base = self._start
            latest = self._latest
            since = latest if latest is not None and latest.arrived_s > t0 else None
            if since is not None and since.samples > base.samples:
                self._verdict = Admission("admitted", f"the fusion node of {self.robot} admits the samples "
                                          f"({since.samples - base.samples} by its first status since "
                                          "the first batch)",
                                          since.samples - base.samples, _increase(since, base))
            elif time.monotonic() - t0 >= self.timeout_s:
                self._verdict = self._not_admitted(since, base)
            return self._verdict

    def _not_admitted(self, since: _Counters | None, base: _Counters) -> Admission:
        within = f"within {self.timeout_s:g} s of the first batch"
        if since is None:
            return Admission("unknown", f"no status from the fusion node of {self.robot} {within}: "
                             "whether anything was admitted is unknown")
        dropped = _increase(since, base)
        if dropped:
            return Admission("refused", f"the fusion node of {self.robot} admitted none of the samples "
                             f"sent {within}; it dropped batches meanwhile: "
                             + ", ".join(f"{k} {v}" for k, v in sorted(dropped.items()))
                             + " (see docs/reference/service.md, What the fusion node refuses)", 0, dropped)
        return Admission("refused", f"the fusion node of {self.robot} admitted none of the samples "
                         f"sent {within}, and none reached it: a router on the way dropped them (an "
                         "access-control policy that does not let this node's user publish raw samples? "
                         "Zenoh's matching status said a subscriber listens even so)")

    def finish(self, stop: threading.Event | None = None) -> Admission:
        """The verdict, waiting for it (up to the timeout after the first batch) while a fusion
        node is heard; ``unknown`` at once when none is, or nothing was sent."""
        stop = stop or threading.Event()
        if not self.started:
            return Admission("unknown", "nothing was sent")
        while (verdict := self.check()) is None:
            with self._lock:
                known = self._alive or self._latest is not None
            if not known or stop.is_set():
                return Admission("unknown", f"no fusion node of {self.robot} heard (no status, no "
                                 "liveliness token): whether anything was admitted is unknown")
            stop.wait(0.05)
        return verdict

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def _increase(now: _Counters, base: _Counters) -> dict[str, int]:
    return {k: v - base.dropped.get(k, 0) for k, v in now.dropped.items() if v > base.dropped.get(k, 0)}
