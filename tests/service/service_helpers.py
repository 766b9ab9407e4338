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

        from armfusion.fusion.service import payloads as pl

        self._lock = threading.Lock()
        self.joints: list = []
        self.status: list = []
        self._subs = [session.declare_subscriber(pl.joints_key(robot), self._put(self.joints)),
                      session.declare_subscriber(pl.status_key(robot), self._put(self.status))]

    def _put(self, into: list):
        from armfusion.fusion.service import payloads as pl

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
    function of its part (a :class:`~armfusion.sensors.samples.Stream`) giving the stream to keep."""
    from armfusion.sensors.samples import Recording

    streams = {}
    for k, s in rec.streams.items():
        part = s.between(t_start_s, t_end_s)
        streams[k] = edits[k](part) if k in edits else part
    return Recording(streams, dict(rec.meta))


def publish_live(session, rec, robot: str = "chair1", batch_s: float = 0.01, stall=None, during=None):
    """Publish ``rec``'s raw streams as live drivers do: every sensor's samples of each
    ``batch_s`` of sample time as one batch, when the wall clock reaches the window's end
    (blocking puts). ``stall = (t_s, length_s)``: every driver stalls at sample time ``t_s``
    for ``length_s`` of wall time, then sends what it read meanwhile as one batch per
    sensor (a driver catching up). ``during(t_s)`` is called after each window, with the
    sample time reached. Returns the samples put."""
    import time

    import numpy as np
    import zenoh
    from armfusion.fusion.service import payloads as pl
    from armfusion.sensors.samples import Stream

    streams = {k: s for k, s in rec.raw().items() if len(s)}
    block = zenoh.CongestionControl.BLOCK
    pubs = {k: session.declare_publisher(pl.raw_key(robot, k), congestion_control=block) for k in streams}
    t0 = min(float(s.t_s[0]) for s in streams.values())
    t_end = max(float(s.t_s[-1]) for s in streams.values())
    edges = list(np.arange(t0 + batch_s, t_end + batch_s, batch_s))
    if stall is not None:  # the window of the stall's length becomes one
        t_stall, length_s = stall
        edges = [e for e in edges if not t_stall < e < t_stall + length_s] + [t_stall + length_s]
        edges.sort()
    seq = dict.fromkeys(streams, 0)
    done = dict.fromkeys(streams, 0)
    put = 0
    wall0 = time.monotonic()
    for edge in edges:
        delay = wall0 + (edge - t0) - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        for k, s in streams.items():
            i1 = int(np.searchsorted(s.t_s, edge, side="right"))
            if i1 > done[k]:
                part = Stream(k, s.kind, s.t_s[done[k]:i1], s.values[done[k]:i1], s.channels)
                pubs[k].put(pl.encode(pl.RawBatch(robot, part, seq[k])))
                seq[k] += 1
                put += i1 - done[k]
                done[k] = i1
        if during is not None:
            during(edge)
    for p in pubs.values():
        p.undeclare()
    return put
