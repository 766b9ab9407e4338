"""What every armfusion node shares: a stop signal, a bounded receive channel, a stall watch.

A node's shape (the one zenoh-python's examples share): a config from a file with
explicit overrides (:mod:`armfusion.fusion.service.zenoh_config`), a session in a ``with`` block, a
:class:`BoundedReceiver` per subscription, and :func:`stop_on_signals`, which turns
SIGINT and SIGTERM into a :class:`threading.Event` that the node's loop waits on
(:func:`stop_after` sets it after ``--duration``). A node that estimates watches for
stalls (:class:`StallWatch`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import zenoh

log = logging.getLogger("armfusion.service")

DEFAULT_QUEUE_SIZE = 1 << 16
"""Messages a receiver holds before it makes Zenoh wait (a batch is one message): about
36 s of five sensors and the encoders at 200 Hz sent one sample per message. Deep on
purpose: a receiver that makes Zenoh's receive thread wait makes a blocking publisher wait,
and Zenoh closes a link whose publisher waited 5 s, losing what was in flight."""
DEFAULT_MAX_BYTES = 64 << 20
"""Bytes of payloads a receiver holds at most (64 MiB): 65536 real messages of a few hundred
bytes are about 20 MB, but as many payloads of 1 MiB (the largest a node reads) would be
64 GiB; a peer flooding large payloads fills this bound first, and what does not fit waits
and then is dropped like a message a full channel cannot take."""
DEFAULT_BLOCK_S = 1.0
"""How long a full receiver makes Zenoh's receive thread wait before it drops a message.
While it waits, a publisher with ``CongestionControl.BLOCK`` is slowed down instead of
samples being lost."""


@contextlib.contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[threading.Event]:
    """Set ``stop`` on SIGINT or SIGTERM inside the block (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, _frame) -> None:
        log.info("%s: stopping", signal.Signals(signum).name)
        stop.set()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


@contextlib.contextmanager
def stop_after(duration_s: float | None, stop: threading.Event) -> Iterator[threading.Event]:
    """Set ``stop`` once ``duration_s`` has passed inside the block (``None``: never)."""
    if not duration_s:
        yield stop
        return
    timer = threading.Timer(duration_s, stop.set)
    timer.daemon = True
    timer.start()
    try:
        yield stop
    finally:
        timer.cancel()


@dataclass(frozen=True)
class Message:
    key: str
    data: bytes
    arrived_s: float = 0.0
    """When Zenoh handed it over (monotonic): a node that fell behind judges time by it."""


class BoundedReceiver:
    """A subscriber's bounded channel: Zenoh's thread puts, the node's loop takes.

    Bounded in messages (``maxsize``) and in bytes (``max_bytes``; a single message larger
    than that is still taken into an empty channel). When either bound is reached, the
    receive thread waits up to ``block_s`` (back-pressure on a blocking publisher) and then
    drops the message, counted in :attr:`overflowed`.
    """

    def __init__(self, maxsize: int = DEFAULT_QUEUE_SIZE, block_s: float = DEFAULT_BLOCK_S,
                 max_bytes: int = DEFAULT_MAX_BYTES):
        self._queue: queue.Queue[Message] = queue.Queue(maxsize=maxsize)
        self._block_s = block_s
        self._max_bytes = max_bytes
        self._lock = threading.Lock()
        self._room = threading.Condition(self._lock)
        self._bytes = 0
        self._overflowed = 0
        self.closed = threading.Event()

    def __call__(self, sample: zenoh.Sample) -> None:
        """Zenoh's callback: copy the payload out and queue it."""
        if self.closed.is_set():
            return
        msg = Message(str(sample.key_expr), sample.payload.to_bytes(), time.monotonic())
        n = len(msg.data)
        with self._room:
            fits = self._room.wait_for(lambda: self._bytes == 0 or self._bytes + n <= self._max_bytes,
                                       timeout=self._block_s)
            if fits:
                self._bytes += n
        if fits:
            try:
                self._queue.put(msg, timeout=self._block_s)
                return
            except queue.Full:
                self._release(n)
        with self._lock:
            self._overflowed += 1
        log.warning("receive channel full: dropped a message on %s", msg.key[:100])

    def _release(self, n: int) -> None:
        with self._room:
            self._bytes -= n
            self._room.notify_all()

    def get(self, timeout_s: float) -> Message | None:
        """The next message, or ``None`` after ``timeout_s`` without one."""
        try:
            msg = self._queue.get(timeout=max(timeout_s, 0.0))
        except queue.Empty:
            return None
        self._release(len(msg.data))
        return msg

    def get_nowait(self) -> Message | None:
        try:
            msg = self._queue.get_nowait()
        except queue.Empty:
            return None
        self._release(len(msg.data))
        return msg

    @property
    def queued_bytes(self) -> int:
        with self._lock:
            return self._bytes

    @property
    def overflowed(self) -> int:
        with self._lock:
            return self._overflowed


class StallWatch:
    """A node is stalled while it should estimate (``tracking``), raw batches arrive, and no
    estimate came for ``after_s`` (wall time); it is not again once estimates come. The
    node sets :attr:`raw_arrived_s` and :attr:`estimated_s` (monotonic) as they happen."""

    def __init__(self, after_s: float):
        self.after_s = after_s
        self.raw_arrived_s = -math.inf
        self.estimated_s = -math.inf
        self.since_s: float | None = None
        """When the stall in progress began (the last estimate), or ``None``."""
        self.stalls = 0

    def check(self, tracking: bool, now_s: float) -> bool:
        """Look at ``now_s``; True when the node became stalled or stopped being so."""
        quiet_s = now_s - self.estimated_s
        stalled = tracking and quiet_s > self.after_s and now_s - self.raw_arrived_s < self.after_s
        if stalled and self.since_s is None:
            self.since_s = self.estimated_s
            self.stalls += 1
            log.warning("serve: stalled: no estimate for %.1f s while raw batches arrive", quiet_s)
            return True
        if not stalled and self.since_s is not None and quiet_s <= self.after_s:
            self.since_s = None
            log.info("serve: estimates again after a stall")
            return True
        return False
