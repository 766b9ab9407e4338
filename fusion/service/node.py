"""What every armfusion node shares: a stop signal, a bounded receive channel.

A node's shape (the one zenoh-python's examples share): a config from a file with
explicit overrides (:mod:`fusion.service.zenoh_config`), a session in a ``with`` block, a
:class:`BoundedReceiver` per subscription, and :func:`stop_on_signals`, which turns
SIGINT and SIGTERM into a :class:`threading.Event` that the node's loop waits on.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import zenoh

log = logging.getLogger("armfusion.service")

DEFAULT_QUEUE_SIZE = 1 << 16
"""Messages a receiver holds before it makes Zenoh wait (a batch is one message): about
36 s of five sensors and the encoders at 200 Hz sent one sample per message. Deep on
purpose: a receiver that makes Zenoh's receive thread wait makes a blocking publisher wait,
and Zenoh closes a link whose publisher waited 5 s, losing what was in flight."""
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


@dataclass(frozen=True)
class Message:
    key: str
    data: bytes


class BoundedReceiver:
    """A subscriber's bounded channel: Zenoh's thread puts, the node's loop takes.

    When the channel is full, the receive thread waits up to ``block_s`` (back-pressure
    on a blocking publisher) and then drops the message, counted in :attr:`overflowed`.
    """

    def __init__(self, maxsize: int = DEFAULT_QUEUE_SIZE, block_s: float = DEFAULT_BLOCK_S):
        self._queue: queue.Queue[Message] = queue.Queue(maxsize=maxsize)
        self._block_s = block_s
        self._lock = threading.Lock()
        self._overflowed = 0
        self.closed = threading.Event()

    def __call__(self, sample: zenoh.Sample) -> None:
        """Zenoh's callback: copy the payload out and queue it."""
        if self.closed.is_set():
            return
        msg = Message(str(sample.key_expr), sample.payload.to_bytes())
        try:
            self._queue.put(msg, timeout=self._block_s)
        except queue.Full:
            with self._lock:
                self._overflowed += 1
            log.warning("receive channel full: dropped a message on %s", msg.key)

    def get(self, timeout_s: float) -> Message | None:
        """The next message, or ``None`` after ``timeout_s`` without one."""
        try:
            return self._queue.get(timeout=max(timeout_s, 0.0))
        except queue.Empty:
            return None

    def get_nowait(self) -> Message | None:
        try:
            return self._queue.get_nowait()
        except queue.Empty:
            return None

    @property
    def overflowed(self) -> int:
        with self._lock:
            return self._overflowed
