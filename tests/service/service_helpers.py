"""Helpers of the service tests: a consumer of what the fusion node publishes, a poll with
a deadline, and a recording cut and edited (a sensor stopped, encoders reset)."""

from __future__ import annotations

import socket


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Collected:
    """Every joint state and status of one robot a session receives, decoded, in order."""

    def __init__(self, session, robot: str = "chair1"):
        import threading

        from fusion.service import payloads as pl

        self._lock = threading.Lock()
        self.joints: list = []
        self.status: list = []
        self._subs = [session.declare_subscriber(pl.joints_key(robot), self._put(self.joints)),
                      session.declare_subscriber(pl.status_key(robot), self._put(self.status))]

    def _put(self, into: list):
        from fusion.service import payloads as pl

        def callback(sample) -> None:
            p = pl.decode(str(sample.key_expr), sample.payload.to_bytes())
            with self._lock:
                into.append(p)
        return callback

    def snapshot(self) -> tuple[list, list]:
        with self._lock:
            return list(self.joints), list(self.status)


def wait_for(pred, timeout_s: float) -> bool:
    """Poll ``pred`` every 20 ms until it holds or ``timeout_s`` passes (a deadline, not a timing check)."""
    import time

    deadline = time.monotonic() + timeout_s
    while not pred() and time.monotonic() < deadline:
        time.sleep(0.02)
    return bool(pred())


def cut(rec, t_start_s: float, t_end_s: float, **edits):
    """The recording's streams between the two times; ``edits`` map a stream's name to a
    function of its part (a :class:`~sensors.samples.Stream`) giving the stream to keep."""
    from sensors.samples import Recording

    streams = {}
    for k, s in rec.streams.items():
        part = s.between(t_start_s, t_end_s)
        streams[k] = edits[k](part) if k in edits else part
    return Recording(streams, dict(rec.meta))
