"""``armfusion serve``: the fusion node. Startup calibration on the first still window,
then the tracker, sample by sample; publishes the joint state, the heading and a status.

Raw batches arrive per sensor on ``armfusion/<robot>/raw/*``. Each is checked twice before
anything else sees it: as a payload (:class:`~armfusion.fusion.service.inbox.Inbox`) and against the
arm's sensors and the sensors' own clock (:class:`~armfusion.fusion.service.admission.Admission`);
what fails is dropped and counted by reason (``dropped.<reason>`` in the status), and only
accepted samples count as ``samples``.

Until the tracker starts, the samples are kept; once ``min_data_s`` of them are in, every
``retry_s`` the node looks for the first still stretch in them and runs the startup
calibration there (:func:`armfusion.fusion.tracking.tracker.start_from_recording`); the samples after
it are then fed to the tracker, and from then on every sample as it comes, merged in time
across the sensors (:mod:`armfusion.fusion.service.reorder`). While tracking, no estimate for
``stall_after_s`` while raw batches arrive is a stall (``stalled`` 1 in the status, and said
in its message, until estimates come again).

Estimates go out on ``state/joints`` and ``state/heading`` (an estimate's two records,
:mod:`armfusion.fusion.tracking.estimate`) at most ``publish_hz`` per second of sample time, a status
on ``status`` every second (and at once when a sensor's status changes), and the node holds
a liveliness token on ``armfusion/<robot>/status`` while it runs. Every joint state and
status carries each sensor's status (``ok``, ``stale``…): a sensor that stops is ``stale``
after ``stale_after_s`` (0.25 s) of sample time, while the others go on.

A queryable on ``armfusion/<robot>/calibrate`` re-runs the startup calibration on request
on the latest still stretch of the last ``recent_s`` of samples (the arm still now), and
restarts the tracker from it; it refuses, saying why, while the arm moves or before there
is a still stretch (:meth:`FusionNode.calibrate`).

With a planned maneuver (``maneuver``, :mod:`armfusion.fusion.service.maneuver`), the node publishes
the plan on ``armfusion/<robot>/maneuver`` for the arm's controller, keeps the samples between
its ``maneuver/start`` and ``maneuver/done`` requests and runs the sensor fit on them in a
child process; it never moves the arm, and it tracks with the config the fit writes only
when asked (``maneuver/apply``, :func:`armfusion.fusion.service.maneuver.apply_fitted_config`).

With a ``state_path``, the node saves its state there (:mod:`armfusion.fusion.service.state_file`)
every ``save_period_s`` of wall time and when it stops, and at start resumes from it
without a new startup calibration when the encoders kept counting; otherwise it says why
and calibrates on a still arm as usual.

The names above (``min_data_s``, ``publish_hz``, ``state_path``…) are the fields of the node's
:class:`~armfusion.fusion.service.serve_settings.NodeSettings`, where their defaults are.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter

import numpy as np
import zenoh
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.admission import Admission
from armfusion.fusion.service.inbox import Inbox
from armfusion.fusion.service.lateness import LagWatch, shed_samples
from armfusion.fusion.service.maneuver import (
    ManeuverEndpoint,
    ServedManeuver,
    apply_fitted_config,
    joints_note,
)
from armfusion.fusion.service.node import BoundedReceiver, StallWatch
from armfusion.fusion.service.serve_endpoints import NodeEndpoints
from armfusion.fusion.service.serve_settings import NodeSettings
from armfusion.fusion.service.serve_status import NodeBoard, NodeCounts, ServeReport, status_message
from armfusion.fusion.service.serve_tracking import NodeParts, NodeTracking
from armfusion.fusion.tracking.tracker import Tracker, warm_up
from armfusion.models.arm import ArmModel

log = logging.getLogger("armfusion.service")


class FusionNode:
    """Subscribes to a robot's raw samples on ``session``, calibrates, tracks, publishes.

    ``settings``: how it runs (:class:`~armfusion.fusion.service.serve_settings.NodeSettings`:
    its saved state, what it keeps, its admission, stall and lateness; ``None``: the defaults).
    ``maneuver``: a planned calibration maneuver it serves (:mod:`armfusion.fusion.service.maneuver`),
    or ``None``.

    The node takes its messages in (each checked as a payload, then by the admission),
    judges its lag (:mod:`~armfusion.fusion.service.lateness`) and says its status
    (:mod:`~armfusion.fusion.service.serve_status`) on its keys
    (:mod:`~armfusion.fusion.service.serve_endpoints`); its tracker, its starts and its saved
    state are its tracking's (:mod:`~armfusion.fusion.service.serve_tracking`).
    """

    def __init__(self, session: zenoh.Session, arm: ArmModel, robot: str,
                 settings: NodeSettings | None = None, *, maneuver: ServedManeuver | None = None):
        self.session = session
        self.settings = settings = NodeSettings() if settings is None else settings
        self.robot = pl.check_name(robot, "robot")
        self.state_path = settings.state_path
        self.lateness = settings.lateness
        self.ready = threading.Event()
        self._board = NodeBoard()
        self._admission, self._lag = Admission(arm, settings.admission), LagWatch(self.lateness)
        self._maneuver, self._inbox = maneuver, Inbox("serve")
        self._stall = StallWatch(settings.stall_after_s)
        self.tracking = NodeTracking(arm, self.robot, settings,
                                     NodeParts(self._board, self._admission, self._lag, self._stall))
        self._arrived: dict[str, float] = {}  # sensor -> when its last batch arrived (monotonic)
        self._silent: frozenset[str] = frozenset()

    @property
    def arm(self) -> ArmModel:
        """The config tracked with (a calibration applied replaces it)."""
        return self.tracking.arm

    @property
    def tracker(self) -> Tracker | None:
        return self.tracking.tracker

    def report_samples(self) -> int:
        """Raw samples accepted so far (may be read from another thread)."""
        return self._board.counts["samples"]

    def refused(self) -> dict[str, int]:
        """Raw batches the admission refused so far, by reason (a copy; any thread)."""
        return dict(self._admission.rejected.copy())

    @property
    def startup_kept_s(self) -> float:
        """Until the tracker starts, the span of sample time kept for the startup calibration
        (s; at most 1.25 × ``startup_keep_s``); 0 once tracking."""
        return self.tracking.kept_s

    def calibrate(self, arm: ArmModel | None = None, why: str = "calibrated on request",
                  carry_pose: bool = False) -> pl.Calibration:
        """Re-run the startup calibration on the latest still stretch and restart the tracker
        from it; or refuse, saying why (the arm moves, no still stretch yet, no samples).
        ``arm``: a new config of the same arm (a sensor calibration's) to track with from then
        on; ``why``: how the status's message begins; ``carry_pose``: the running tracker's
        last pose and sigma go to the startup as a saved pose (checked against the still data)
        and seed the joints it cannot read (the arm has not moved: it is still)."""
        return self.tracking.calibrate(arm, why, carry_pose)

    def save_state(self) -> bool:
        """Write the tracker's state to ``state_path`` (atomically); False before it tracks."""
        return self.tracking.save_state()

    def run(self, stop: threading.Event) -> ServeReport:
        """Serve until ``stop`` is set."""
        # the compiled kernels ready before any sample is taken in (compiled once after an
        # install: seconds the node would otherwise spend while the samples queue up)
        try:
            log.info("serve: tracker kernels ready in %.1f s", warm_up(self.arm, self.settings.tracker))
        except (ValueError, KeyError, RuntimeError) as e:  # (a speed-up only: they compile on first use)
            log.warning("serve: could not warm the tracker's kernels up (%s); they compile on first use", e)
        # a deep channel: while the node catches up (after its startup calibration, or on a
        # busy machine) Zenoh's receive thread must not block for long, or a blocking
        # publisher waits and Zenoh closes the link after 5 s (block/wait_before_close),
        # losing what was in flight
        receiver = BoundedReceiver(maxsize=self.settings.queue_size)
        self.tracking.endpoints = endpoints = NodeEndpoints(self.session, self.robot, receiver)
        served = None if self._maneuver is None else ManeuverEndpoint(
            self.session, self._maneuver,
            lambda: apply_fitted_config(self._maneuver, self.arm,
                                        lambda arm, why: self.calibrate(arm, why, carry_pose=True)),
            lambda: joints_note(self.tracking.last_estimate, self._maneuver.plan))
        self._board.state = "calibrating"
        self.ready.set()
        try:
            self._loop(stop, receiver, served)
            while (msg := receiver.get_nowait()) is not None:
                self._on_message_guarded(msg)
            self._board.state = "stopping"
            if self.state_path is not None:
                self.save_state()
            self._publish_status(receiver)
        finally:
            receiver.closed.set()
            endpoints.close_queries("the fusion node is stopping")
            if served is not None:
                served.close()
            endpoints.close()
        t = self.tracking
        return self._counts(receiver).report(self.robot, self._board.state, t.startup_t, self._board.message,
                                             t.resumed, t.resume_message)

    def _loop(self, stop: threading.Event, receiver: BoundedReceiver,
              served: ManeuverEndpoint | None) -> None:
        """The node's loop until ``stop``: a message (or, degraded, all waiting), the
        requests, the maneuver, the stall and silence watches, the status, the saved state."""
        next_status = next_save = last_status = 0.0
        board = self._board
        while not stop.is_set():
            msg = receiver.get(timeout_s=0.1)
            if msg is not None:
                self._take(msg, receiver)
            elif self._lag.nothing_waits(time.monotonic()):  # whatever it was behind, it has taken in
                board.due = True
            while (query := self.tracking.endpoints.next_query()) is not None:
                self._answer(query)
            if served is not None and served.serve():
                board.due = True
            now = time.monotonic()
            if self._stall.check(self.tracker is not None, now):
                board.due = True
            silent = frozenset(k for k, t in self._arrived.items() if now - t > self.settings.silent_after_s)
            if silent != self._silent:
                self._silent, board.due = silent, True
            # every second, and at once (at most 10 a second) when a sensor's status changes;
            # at once whenever the node has become degraded (however soon it catches up)
            if now >= next_status or (board.due and now >= last_status + 0.1) or self._lag.news:
                self._publish_status(receiver)
                last_status, next_status = now, now + 1.0
            if self.state_path is not None and now >= next_save:
                self.save_state()
                next_save = now + self.settings.save_period_s

    def _counts(self, receiver: BoundedReceiver) -> NodeCounts:
        dropped = Counter(self._inbox.dropped) + self._admission.rejected
        if receiver.overflowed:
            dropped["overflow"] += receiver.overflowed
        return NodeCounts(self._board.counts, self._admission, self._stall, self._lag, dict(dropped))

    def _take(self, msg, receiver: BoundedReceiver) -> None:
        """One message, or, when the node is degraded, every message waiting: the lateness
        policy (:class:`~armfusion.fusion.service.lateness.Lateness`)."""
        if not self._lag.degraded:
            self._on_message_guarded(msg)
            self._judge_lag()
            return
        now = time.monotonic()
        until = now + self.lateness.pass_s
        # (while it tracks: the startup calibration gets every sample it keeps)
        shed_before = now - self.lateness.shed_after_s if self.tracker is not None else -np.inf
        stale: dict[str, object] = {}  # key -> the newest message that waited too long
        while msg is not None:
            if msg.arrived_s and msg.arrived_s < shed_before:
                self._shed(stale.get(msg.key))
                stale[msg.key] = msg
            else:
                for m in stale.values():  # (older than this one: they go first)
                    self._on_message_guarded(m, fuse=False)
                stale.clear()
                self._on_message_guarded(msg, fuse=False)
            msg = receiver.get_nowait() if time.monotonic() < until else None
        for m in stale.values():
            self._on_message_guarded(m, fuse=False)
        if self.tracker is not None:
            try:
                self.tracking.fuse_released(fold=True)
            except Exception as e:  # noqa: BLE001 - as _on_message_guarded
                self._board.counts["errors"] += 1
                log.exception("serve: error while catching up: %s: %s", type(e).__name__, str(e)[:200])
        self._judge_lag()

    def _shed(self, msg) -> None:
        """Shed ``msg`` unread but for its count of samples (``Lateness.shed_after_s``);
        ``None``: nothing."""
        if msg is None:
            return
        self._board.counts["shed_batches"] += 1
        self._admission.shed(msg.key.rpartition("/")[2])
        self._board.counts["shed_samples"] += shed_samples(msg.data)

    def _judge_lag(self) -> None:
        if self._lag.judge(time.monotonic()):
            self._board.due = True

    def _on_message_guarded(self, msg, fuse: bool = True) -> None:
        """:meth:`_on_message`, and the last line of defence: whatever slipped past the checks
        is counted (``errors``), logged with its traceback, and the node goes on."""
        try:
            self._on_message(msg, fuse)
        except Exception as e:  # noqa: BLE001 - nothing a peer sends may stop the node
            self._board.counts["errors"] += 1
            self._board.due = True
            log.exception("serve: error on a message on %s: %s: %s", msg.key[:100], type(e).__name__,
                          str(e)[:200])

    def _on_message(self, msg, fuse: bool = True) -> None:
        batch = self._inbox.decode(msg.key, msg.data)
        if not isinstance(batch, pl.RawBatch):
            return
        s = batch.stream
        now = time.monotonic()
        arrived = msg.arrived_s or now  # (earlier than now when the node is behind)
        self._stall.raw_arrived_s = now
        verdict = self._admission.check(batch, now, arrived)
        if not verdict.ok:
            return
        if verdict.reset:  # what was kept of this stream was on a clock the others refute
            self._lag.forget(s.name)
            self.tracking.forget(s.name)
            if self._maneuver is not None:
                self._maneuver.clock_reset(s.name)
        self._board.counts["samples"] += len(s)
        self._arrived[s.name] = now
        self._lag.taken(s.name, arrived, float(s.t_s[-1]))
        if self._maneuver is not None:
            self._maneuver.keep(s)
        self.tracking.take(s, fuse, now, arrived)

    def _answer(self, query) -> None:
        """A ``calibrate`` request answered (:meth:`calibrate`)."""
        try:
            result = self.calibrate()
        except Exception as e:  # noqa: BLE001 - a request must get a reply and never stop the node
            log.exception("serve: calibration on request failed")
            result = pl.Calibration(self.robot, False, f"calibration failed: {type(e).__name__}: {e}")
        self.tracking.endpoints.reply(query, result)

    def _publish_status(self, receiver: BoundedReceiver) -> None:
        board = self._board
        board.due = self._lag.news = False
        sensors = dict(self.tracking.sensors)
        sensors.update(dict.fromkeys(self._silent & set(sensors), "stale"))
        quiet_s = (time.monotonic() - max(self._arrived.values())
                   if self._silent and self._silent >= set(sensors) else None)
        message = status_message(board.message, maneuver=self._maneuver, tracker=self.tracker, lag=self._lag,
                                 every_sensor_quiet_s=quiet_s, stall=self._stall)
        counters = self._counts(receiver).status_counters()
        self.tracking.endpoints.status(pl.Status(self.robot, "serve", board.state, time.time(), message,
                                                 tuple(counters.items()), tuple(sensors.items())))
