"""``armfusion serve``: the fusion node. Startup calibration on the first still window,
then the tracker, sample by sample; publishes the joint state, the heading and a status.

Raw batches arrive per sensor on ``armfusion/<robot>/raw/*``. Until the tracker starts,
they are kept; once ``min_data_s`` of samples are in, every ``retry_s`` the node looks
for the first still stretch in them and runs the startup calibration there
(:func:`fusion.tracker.start_from_recording`); the samples after it are then fed to the
tracker, and from then on every sample as it comes.

The sensors' batches come in separately, so a small reorder stage merges them in time
before the tracker (which drops a sample older than the last): a sample is released when
every sensor heard from in the last ``max_lag_s`` has sent something at least as late, or
when it is ``max_lag_s`` older than the newest sample (a silent sensor does not stall the
others). Estimates go out on ``state/joints`` and ``state/heading`` at most
``publish_hz`` per second of sample time, a status on ``status`` every second, and the
node holds a liveliness token on ``armfusion/<robot>/status`` while it runs.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np
import zenoh

from fusion.service import payloads as pl
from fusion.service.node import BoundedReceiver
from fusion.tracker import NoStillWindowError, Tracker, TrackerSettings, start_from_recording
from models.arm import ArmModel
from sensors.samples import Recording, Stream

log = logging.getLogger("armfusion.service")


@dataclass(frozen=True)
class ServeReport:
    robot: str
    state: str
    samples: int
    estimates: int
    out_of_order: int
    dropped: dict[str, int]
    startup_t_s: float | None
    message: str

    def as_dict(self) -> dict:
        return {"robot": self.robot, "state": self.state, "samples": self.samples,
                "estimates": self.estimates, "out_of_order": self.out_of_order,
                "dropped": self.dropped, "startup_t_s": self.startup_t_s, "message": self.message}


class _Reorder:
    """Per-sensor queues of ``(t_s, counts)``, released merged in time (see the module)."""

    def __init__(self, max_lag_s: float):
        self.max_lag_s = max_lag_s
        self._t: dict[str, list[np.ndarray]] = {}
        self._v: dict[str, list[np.ndarray]] = {}
        self._last: dict[str, float] = {}
        self._released = -np.inf

    def push(self, s: Stream) -> int:
        """Queue a batch; returns how many of its samples were already too late (dropped)."""
        late = int(np.sum(s.t_s <= self._released))
        keep = s.t_s > self._released
        self._t.setdefault(s.name, []).append(s.t_s[keep])
        self._v.setdefault(s.name, []).append(s.values[keep])
        self._last[s.name] = max(self._last.get(s.name, -np.inf), float(s.t_s[-1]))
        return late

    def seen(self, name: str, t_s: float) -> None:
        """Note that ``name`` has sent everything up to ``t_s`` (before any push of it)."""
        self._last[name] = max(self._last.get(name, -np.inf), t_s)

    def release(self, flush: bool = False) -> list[tuple[float, dict[str, np.ndarray]]]:
        """The instants that are safe to fuse, in time order: ``(t_s, {sensor: counts})``."""
        if not self._last:
            return []
        newest = max(self._last.values())
        alive = [t for t in self._last.values() if t >= newest - self.max_lag_s]
        mark = newest if flush else max(min(alive), newest - self.max_lag_s)
        ts, names, rows = [], [], []
        for k in list(self._t):
            t = np.concatenate(self._t[k]) if self._t[k] else np.empty(0)
            v = np.concatenate(self._v[k]) if self._v[k] else np.empty((0, 0))
            n = int(np.searchsorted(t, mark, side="right"))
            self._t[k], self._v[k] = [t[n:]], [v[n:]]
            ts.append(t[:n])
            names.extend([k] * n)
            rows.extend(v[:n])
        if not names:
            return []
        t_all = np.concatenate(ts)
        order = np.argsort(t_all, kind="stable")
        out: list[tuple[float, dict[str, np.ndarray]]] = []
        for i in order.tolist():
            t = float(t_all[i])
            if not out or out[-1][0] != t:
                out.append((t, {}))
            out[-1][1][names[i]] = rows[i]
        self._released = max(self._released, float(t_all[order[-1]]))
        return out


class FusionNode:
    """Subscribes to a robot's raw samples on ``session``, calibrates, tracks, publishes."""

    def __init__(self, session: zenoh.Session, arm: ArmModel, robot: str, *,
                 settings: TrackerSettings | None = None, publish_hz: float = 50.0,
                 min_data_s: float = 2.0, retry_s: float = 0.5, max_lag_s: float = 0.1):
        self.session = session
        self.arm = arm
        self.robot = pl.check_name(robot, "robot")
        self.settings = settings
        self.publish_period_s = 1.0 / publish_hz
        self.min_data_s = min_data_s
        self.retry_s = retry_s
        self.ready = threading.Event()
        self._reorder = _Reorder(max_lag_s)
        self._inbox = pl.Inbox("serve")
        self._buffer: dict[str, list[Stream]] = {}
        self._tracker: Tracker | None = None
        self._next_try_t = -np.inf
        self._next_pub_t = -np.inf
        self._startup_t: float | None = None
        self._counts: Counter[str] = Counter()
        self._state = "starting"
        self._message = "waiting for samples"

    @property
    def tracker(self) -> Tracker | None:
        return self._tracker

    def report_samples(self) -> int:
        """Raw samples received so far (may be read from another thread)."""
        return self._counts["samples"]

    def run(self, stop: threading.Event) -> ServeReport:
        """Serve until ``stop`` is set."""
        receiver = BoundedReceiver()
        pub_joints = self.session.declare_publisher(pl.joints_key(self.robot))
        pub_heading = self.session.declare_publisher(pl.heading_key(self.robot))
        pub_status = self.session.declare_publisher(pl.status_key(self.robot))
        token = self.session.liveliness().declare_token(pl.status_key(self.robot))
        sub = self.session.declare_subscriber(pl.raw_keys(self.robot), receiver)
        self._pubs = (pub_joints, pub_heading)
        self._state = "calibrating"
        self.ready.set()
        next_status = 0.0
        try:
            while not stop.is_set():
                msg = receiver.get(timeout_s=0.1)
                if msg is not None:
                    self._on_message(msg)
                if time.monotonic() >= next_status:
                    self._publish_status(pub_status, receiver)
                    next_status = time.monotonic() + 1.0
            while (msg := receiver.get_nowait()) is not None:
                self._on_message(msg)
            self._state = "stopping"
            self._publish_status(pub_status, receiver)
        finally:
            receiver.closed.set()
            sub.undeclare()
            token.undeclare()
            for p in (pub_joints, pub_heading, pub_status):
                p.undeclare()
        return ServeReport(self.robot, self._state, self._counts["samples"], self._counts["estimates"],
                           self._counts["out_of_order"], self._dropped(receiver), self._startup_t,
                           self._message)

    def _dropped(self, receiver: BoundedReceiver) -> dict[str, int]:
        d = Counter(self._inbox.dropped)
        if receiver.overflowed:
            d["overflow"] += receiver.overflowed
        return dict(d)

    def _on_message(self, msg) -> None:
        batch = self._inbox.decode(msg.key, msg.data)
        if not isinstance(batch, pl.RawBatch):
            return
        s = batch.stream
        self._counts["samples"] += len(s)
        if self._tracker is None:
            self._buffer.setdefault(s.name, []).append(s)
            self._try_start(float(s.t_s[-1]))
            return
        self._counts["out_of_order"] += self._reorder.push(s)
        self._fuse(self._reorder.release())

    def _recording(self) -> Recording:
        streams = {}
        for k, parts in self._buffer.items():
            t = np.concatenate([p.t_s for p in parts])
            v = np.concatenate([p.values for p in parts])
            keep = np.concatenate([[True], np.diff(t) > 0])  # a repeated batch is ignored
            streams[k] = Stream(k, parts[0].kind, t[keep], v[keep], parts[0].channels)
        return Recording(streams)

    def _try_start(self, t_now: float) -> None:
        if t_now < self._next_try_t:
            return
        rec = self._recording()
        if rec.duration_s < self.min_data_s:
            return
        self._next_try_t = t_now + self.retry_s
        try:
            tracker, start = start_from_recording(self.arm, rec, self.settings)
        except NoStillWindowError as e:
            self._message = f"waiting for a still arm: {e}"
            return
        except (ValueError, KeyError) as e:
            self._message = f"startup calibration failed: {e}"
            log.warning("serve: %s", self._message)
            return
        self._tracker = tracker
        self._startup_t = float(tracker.t_s)
        self._state = "tracking"
        self._message = (f"startup calibration on the still stretch {start.t_start_s:.2f}"
                         f"-{start.t_end_s:.2f} s; tracking")
        log.info("serve: %s", self._message)
        for s in rec.streams.values():
            self._reorder.seen(s.name, float(s.t_s[-1]))
            after = s.between(self._startup_t + 1e-9, np.inf)
            if len(after):
                self._reorder.push(after)
        self._buffer.clear()
        self._fuse(self._reorder.release())

    def _fuse(self, instants) -> None:
        """Feed released instants to the tracker; publish at most every publish period."""
        tr = self._tracker
        takes = set(tr.sensor_names) | {"imu_temp"}
        for t, samples in instants:
            e = tr.update_instant(t, {k: v for k, v in samples.items() if k in takes})
            if e is not None and t >= self._next_pub_t:
                self._publish(e)
                self._next_pub_t = t + self.publish_period_s

    def _publish(self, e) -> None:
        pub_joints, pub_heading = self._pubs
        pub_joints.put(pl.encode(pl.JointState(
            self.robot, e.t_s, tuple(e.joint_names), tuple(float(x) for x in e.q_rad),
            tuple(float(x) for x in e.sigma_rad), tuple(e.flags))))
        pub_heading.put(pl.encode(pl.Heading(self.robot, e.t_s, float(e.heading_rad),
                                             float(e.heading_sigma_rad), bool(e.magnetic_disturbance))))
        self._counts["estimates"] += 1

    def _publish_status(self, pub, receiver: BoundedReceiver) -> None:
        counters = {"samples": self._counts["samples"], "estimates": self._counts["estimates"],
                    "out_of_order": self._counts["out_of_order"]}
        counters.update({f"dropped.{k}": v for k, v in self._dropped(receiver).items()})
        pub.put(pl.encode(pl.Status(self.robot, "serve", self._state, time.time(), self._message,
                                    tuple(counters.items()))))
