"""What a node does with what it receives: :class:`Inbox` decodes each payload
(:func:`armfusion.fusion.service.payloads.decode`) and counts and drops what is bad, with one log line
per reason per second at most (:class:`DropLog`), never an exception into the node."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter

from armfusion.fusion.service.payloads import Payload, PayloadError, decode

log = logging.getLogger("armfusion.service")


class DropLog:
    """One warning line per reason per ``period_s`` at most, saying how many were not logged
    since: a peer flooding bad payloads cannot flood the log. Thread-safe."""

    def __init__(self, period_s: float = 1.0):
        self.period_s = period_s
        self._lock = threading.Lock()
        self._last: dict[str, tuple[float, int]] = {}

    def warn(self, reason: str, message: str, *args) -> None:
        now = time.monotonic()
        with self._lock:
            last, quiet = self._last.get(reason, (-math.inf, 0))
            if now - last < self.period_s:
                self._last[reason] = (last, quiet + 1)
                return
            self._last[reason] = (now, 0)
        more = f" ({quiet} more since the last line)" if quiet else ""
        log.warning(message + "%s", *args, more)


class Inbox:
    """Decodes what a node receives, counting and dropping what is bad (with one log line per
    reason per second at most, :class:`DropLog`).

    Safe to call from Zenoh's receive threads: the counters take a lock.
    """

    def __init__(self, node: str):
        self.node = node
        self._lock = threading.Lock()
        self._received = 0
        self._dropped: Counter[str] = Counter()
        self._log = DropLog()

    def decode(self, key: str, data: bytes) -> Payload | None:
        """The payload, or ``None`` (counted, logged) when it is not a valid one."""
        with self._lock:
            self._received += 1
        try:
            return decode(key, data)
        except PayloadError as e:
            reason, message = e.reason, str(e)
        except Exception as e:  # noqa: BLE001 - a bad payload must never stop the node
            reason, message = "malformed", f"{type(e).__name__}: {e}"
        with self._lock:
            self._dropped[reason] += 1
        self._log.warn(reason, "%s: dropped a payload on %s (%s): %s", self.node, str(key)[:100], reason,
                       message[:200])
        return None

    @property
    def received(self) -> int:
        with self._lock:
            return self._received

    @property
    def dropped(self) -> dict[str, int]:
        """Dropped payloads by reason: ``oversized``, ``malformed``, ``unknown_version``, ``bad_key``."""
        with self._lock:
            return dict(self._dropped)
