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
when asked (``maneuver/apply``, :meth:`FusionNode._apply_calibration`).

With a ``state_path``, the node saves its state there (:mod:`armfusion.fusion.service.state_file`)
every ``save_period_s`` of wall time and when it stops, and at start resumes from it
without a new startup calibration when the encoders kept counting; otherwise it says why
and calibrates on a still arm as usual.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service import state_file
from armfusion.fusion.service.admission import Admission, AdmissionSettings
from armfusion.fusion.service.inbox import Inbox
from armfusion.fusion.service.maneuver import ManeuverEndpoint, ServedManeuver, same_arm_problem
from armfusion.fusion.service.node import DEFAULT_QUEUE_SIZE, BoundedReceiver, StallWatch
from armfusion.fusion.service.reorder import Reorder
from armfusion.fusion.service.restart import (
    RecentSamples,
    ambiguity_note,
    calibration_reply,
    solve_ambiguity_again,
)
from armfusion.fusion.service.startup_buffer import StartupBuffer
from armfusion.fusion.startup.solve import StartupPrior
from armfusion.fusion.tracking.tracker import (
    ENC,
    NoStillWindowError,
    Start,
    Tracker,
    TrackerSettings,
    start_from_recording,
    warm_up,
)
from armfusion.models.arm import ArmModel
from armfusion.models.arm_config import ConfigError
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.samples import Recording

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
    resumed: bool = False
    resume_message: str = ""
    calibrations: int = 0
    missed_batches: int = 0
    seq_resets: int = 0
    encoder_rebases: int = 0
    stalls: int = 0
    errors: int = 0
    refused_samples: dict[str, int] | None = None
    """The samples of the raw batches the admission refused, by reason (``dropped`` counts
    payloads and batches)."""
    degraded_periods: int = 0
    folded_instants: int = 0
    lag_max_ms: int = 0
    shed_batches: int = 0
    shed_samples: int = 0

    def as_dict(self) -> dict:
        return {"robot": self.robot, "state": self.state, "samples": self.samples,
                "estimates": self.estimates, "out_of_order": self.out_of_order,
                "dropped": self.dropped, "startup_t_s": self.startup_t_s, "message": self.message,
                "resumed": self.resumed, "resume_message": self.resume_message,
                "calibrations": self.calibrations, "missed_batches": self.missed_batches,
                "seq_resets": self.seq_resets, "encoder_rebases": self.encoder_rebases,
                "stalls": self.stalls, "errors": self.errors,
                "refused_samples": dict(self.refused_samples or {}),
                "degraded_periods": self.degraded_periods, "folded_instants": self.folded_instants,
                "lag_max_ms": self.lag_max_ms, "shed_batches": self.shed_batches,
                "shed_samples": self.shed_samples}


@dataclass(frozen=True)
class Lateness:
    """How the fusion node degrades when it falls behind (see docs/service-node.md, "When the node
    falls behind").

    The node's lag is how far the samples it last took in are behind the sensors' time now,
    in wall time: now, less the usual delivery delay (the median over the streams of the
    least delay of each one's batches in the last ``delay_window_s``: arrival less sample
    time), less the last sample's time. It counts the node's own queue as well as a stall
    of the whole process (whose messages then arrive late together). While the stream is
    live (``max_pace``), beyond
    ``degrade_after_s`` the node is degraded (the status's ``degraded`` 1, its ``lag_ms``,
    and a message saying so) until its lag is back within half of it, or nothing waits. While
    degraded, each pass of the loop takes every message waiting (for at most ``pass_s`` of
    wall time), admits each and queues its samples, then fuses once: the instants more than
    ``degrade_after_s`` older than the sensors' clock are folded, merged into one instant
    per ``fold_period_s`` of sample time, or into ``backlog_updates`` instants when they
    span longer (each sensor's latest sample in a window, at its last instant's time); the
    newer ones are merged one window per ``fold_period_s`` too (the update rate lowered:
    a node short of CPU spends less of it on the tracker); the joint states go out as usual
    (at most ``publish_hz``), so the folded instants have none. The startup's kept samples
    are fused the same way. Every sample still goes through the admission and is counted,
    but those of the batches shed (``shed_after_s``); the folded instants' samples are
    what the tracker does not see one by one.
    """

    degrade_after_s: float = 0.05
    fold_period_s: float = 0.02
    backlog_updates: int = 10
    """A backlog longer than this many fold periods is folded into this many instants: the
    tracker's work on a backlog of any length is bounded, so a node that can take its
    messages in catches up."""
    pass_s: float = 0.025
    """A pass takes messages for at most half ``degrade_after_s``: the samples taken first
    wait no longer than that before they are fused."""
    max_pace: float = 2.0
    """Live only: while the sensors' newest time ran more than this many times as fast as
    wall time over the arrivals of the last ``pace_window_s`` the node has taken in (a
    replay faster than real time; judged once they span ``pace_min_s``), or the stream's
    arrivals began less than half ``pace_window_s`` ago in wall time (a stream just begun;
    after a silence of ``pace_window_s`` it begins again), the node is not degraded: every
    instant is fused one by one however long it takes (such a stream has no real time to
    be late against)."""
    pace_window_s: float = 4.0
    pace_min_s: float = 0.5
    """The pace is judged once the arrivals the node has taken in span this long: a node
    behind from the stream's start (its startup calibration, a starved CPU) judges it
    before it has taken in half ``pace_window_s`` of them, and degrades."""
    shed_after_s: float = 0.5
    """While degraded and tracking, of the messages that waited longer than this in the
    node's receive channel (arrival to now: ten times ``degrade_after_s``, a backlog the
    folding is not working off: a node that takes its messages in as fast as they come is
    back within ``degrade_after_s`` in a few passes), a pass keeps each sensor's newest
    and sheds the others unread: counted (``shed_batches``, and their samples), never
    admitted, refused nor fused, their batch numbers not counted as missed. A node that
    cannot even take its messages in as fast as they come keeps its lag bounded. (Before
    it tracks, none: the startup calibration gets every sample.)"""
    delay_window_s: float = 60.0
    """The usual delivery delay is the least of this long: a lag that grows slowly (a node
    a little short of CPU for a minute) is not taken for the usual delay."""


class FusionNode:
    """Subscribes to a robot's raw samples on ``session``, calibrates, tracks, publishes.

    ``state_path``: the saved state (see :mod:`armfusion.fusion.service.state_file`), written every
    ``save_period_s`` of wall time and at stop, and resumed from at start when it is no
    older than ``max_state_age_s`` and the encoders moved no faster than
    ``max_joint_rate_rad_s`` in between. ``recent_s``: how much of the latest samples the
    node keeps for a calibration on request. ``startup_keep_s``: until the tracker starts, how
    much of the latest samples the node keeps for its startup calibration (older batches are
    let go: a node waiting for a still arm holds, and searches on each retry, at most that
    much, however long it waits). ``silent_after_s``: a sensor none of whose
    batches arrived for that long (wall time) is ``stale`` in the status, also when every
    sensor stops and the tracker, which judges staleness in sample time, hears nothing.
    ``admission``: the bounds every raw batch is checked against
    (:mod:`armfusion.fusion.service.admission`). ``stall_after_s``: while tracking, no estimate for
    that long (wall time) while raw batches arrive is a stall, reported in the status.
    ``lateness``: when the node is degraded and what it does then (:class:`Lateness`).
    """

    def __init__(self, session: zenoh.Session, arm: ArmModel, robot: str, *,
                 settings: TrackerSettings | None = None, publish_hz: float = 50.0,
                 min_data_s: float = 2.0, retry_s: float = 0.5, max_lag_s: float = 0.1,
                 state_path: Path | str | None = None, save_period_s: float = 1.0,
                 max_state_age_s: float = 60.0, max_joint_rate_rad_s: float = 1.5,
                 recent_s: float = 5.0, still_tolerance_s: float = 0.3, silent_after_s: float = 0.5,
                 startup_keep_s: float = 60.0,
                 queue_size: int = DEFAULT_QUEUE_SIZE, admission: AdmissionSettings | None = None,
                 stall_after_s: float = 1.0, assume_parked: bool = False,
                 maneuver: ServedManeuver | None = None, lateness: Lateness | None = None):
        self.session = session
        # the ready pose as evidence for the startup's branches only when the caller says the
        # arm is parked there (serve --assume-parked); by default nothing but the data chooses
        self.assume_parked = assume_parked
        self.arm = arm
        self._config_sha = state_file.config_fingerprint(arm)  # what a saved state was tracked with
        self.robot = pl.check_name(robot, "robot")
        self.settings = settings
        self.publish_period_s = 1.0 / publish_hz
        self.min_data_s = min_data_s
        self.retry_s = retry_s
        self.state_path = None if state_path is None else Path(state_path)
        self.save_period_s = save_period_s
        self.max_state_age_s = max_state_age_s
        self.max_joint_rate_rad_s = max_joint_rate_rad_s
        self.recent_s = recent_s
        if not startup_keep_s >= 2.0 * min_data_s:
            raise ValueError(f"startup_keep_s must be at least twice min_data_s ({2.0 * min_data_s:g} s), "
                             f"not {startup_keep_s!r}")
        self.startup_keep_s = startup_keep_s
        self.still_tolerance_s = still_tolerance_s
        self.silent_after_s = silent_after_s
        self.queue_size = queue_size
        self.stall_after_s = stall_after_s
        self._admission = Admission(arm, admission)
        self.lateness = lateness or Lateness()
        self._degraded = False
        self._degraded_news = False  # became degraded since the last status
        self._lag_s = 0.0
        self._lag_max_s = 0.0
        self._pace_marks: deque[tuple[float, float, float]] = deque()  # see _mark_pace
        self._pace_arrived_s = -np.inf
        self._run_began_s = -np.inf  # the first arrival after a silence of pace_window_s (or ever)
        self._delays: dict[str, deque[tuple[float, float]]] = {}  # see _note_delay
        self._taken_t: float | None = None  # the last sample time of the last batch accepted
        self._maneuver = maneuver
        self._last_estimate = None
        self._stall = StallWatch(stall_after_s)
        self.ready = threading.Event()
        self._max_lag_s = max_lag_s
        self._reorder = Reorder(max_lag_s)
        self._inbox = Inbox("serve")
        self._buffer = StartupBuffer(startup_keep_s)
        self._recent = RecentSamples(recent_s, stream_models(arm))
        self._queries: queue.Queue = queue.Queue()
        self._tracker: Tracker | None = None
        self._rates_hz: dict[str, float] = {}
        self._last_enc: tuple[float, np.ndarray] | None = None
        self._next_try_t = -np.inf
        self._start: Start | None = None  # the startup the tracker runs on (its rival branches)
        self._next_resolve_t = -np.inf
        self._next_pub_t = -np.inf
        self._startup_t: float | None = None
        self._counts: Counter[str] = Counter()
        self._alarm_version = 0  # the model-change alarms' version last published
        self._sensors: tuple[tuple[str, str], ...] = ()
        self._arrived: dict[str, float] = {}  # sensor -> when its last batch arrived (monotonic)
        self._silent: frozenset[str] = frozenset()
        self._status_due = False
        self._state = "starting"
        self._message = "waiting for samples"
        self._resumed = False
        self._saved: dict | None = None
        self._saved_iron: dict | None = None  # the compass's learnt iron, reused by a fresh start
        self._resume_message = ""
        if self.state_path is not None:
            try:
                self._saved = state_file.load_state(self.state_path)
                self._saved_iron = state_file.saved_compass_calibration(self._saved, self.robot,
                                                                         self.arm.name, self._config_sha)
                self._resume_message = f"found a saved state in {self.state_path}"
            except state_file.StateFileError as e:
                self._resume_message = f"no resume: {e}; a startup calibration on a still arm"
                log.info("serve: %s", self._resume_message)

    @property
    def tracker(self) -> Tracker | None:
        return self._tracker

    def report_samples(self) -> int:
        """Raw samples accepted so far (may be read from another thread)."""
        return self._counts["samples"]

    def refused(self) -> dict[str, int]:
        """Raw batches the admission refused so far, by reason (a copy; any thread)."""
        return dict(self._admission.rejected.copy())

    def run(self, stop: threading.Event) -> ServeReport:
        """Serve until ``stop`` is set."""
        # a deep channel: while the node catches up (after its startup calibration, or on a
        # busy machine) Zenoh's receive thread must not block for long, or a blocking
        # publisher waits and Zenoh closes the link after 5 s (block/wait_before_close),
        # losing what was in flight
        # the compiled kernels ready before any sample is taken in (compiled once after an
        # install: seconds the node would otherwise spend while the samples queue up)
        try:
            log.info("serve: tracker kernels ready in %.1f s", warm_up(self.arm, self.settings))
        except (ValueError, KeyError, RuntimeError) as e:  # (a speed-up only: they compile on first use)
            log.warning("serve: could not warm the tracker's kernels up (%s); they compile on first use", e)
        receiver = BoundedReceiver(maxsize=self.queue_size)
        pub_joints = self.session.declare_publisher(pl.joints_key(self.robot))
        pub_heading = self.session.declare_publisher(pl.heading_key(self.robot))
        pub_status = self.session.declare_publisher(pl.status_key(self.robot))
        self._pub_health = pub_health = self.session.declare_publisher(pl.health_key(self.robot))
        token = self.session.liveliness().declare_token(pl.status_key(self.robot))
        sub = self.session.declare_subscriber(pl.raw_keys(self.robot), receiver)
        queryable = self.session.declare_queryable(pl.calibrate_key(self.robot), self._queries.put)
        served = None if self._maneuver is None else ManeuverEndpoint(
            self.session, self._maneuver, self._apply_calibration, self._joints_note)
        self._pubs = (pub_joints, pub_heading)
        self._state = "calibrating"
        self.ready.set()
        next_status = next_save = last_status = 0.0
        try:
            while not stop.is_set():
                msg = receiver.get(timeout_s=0.1)
                if msg is not None:
                    self._take(msg, receiver)
                elif self._degraded:  # nothing waiting: whatever it was behind, it has taken in
                    self._degraded, self._lag_s, self._status_due = False, 0.0, True
                    log.info("serve: caught up (nothing waiting); no longer degraded")
                while (query := self._next_query()) is not None:
                    self._answer(query)
                if served is not None and served.serve():
                    self._status_due = True
                now = time.monotonic()
                if self._stall.check(self._tracker is not None, now):
                    self._status_due = True
                silent = frozenset(k for k, t in self._arrived.items() if now - t > self.silent_after_s)
                if silent != self._silent:
                    self._silent, self._status_due = silent, True
                # every second, and at once (at most 10 a second) when a sensor's status changes;
                # at once whenever the node has become degraded (however soon it catches up)
                if now >= next_status or (self._status_due and now >= last_status + 0.1) \
                        or self._degraded_news:
                    self._publish_status(pub_status, receiver)
                    last_status, next_status = now, now + 1.0
                if self.state_path is not None and now >= next_save:
                    self.save_state()
                    next_save = now + self.save_period_s
            while (msg := receiver.get_nowait()) is not None:
                self._on_message_guarded(msg)
            self._state = "stopping"
            if self.state_path is not None:
                self.save_state()
            self._publish_status(pub_status, receiver)
        finally:
            receiver.closed.set()
            queryable.undeclare()
            while (query := self._next_query()) is not None:
                self._reply(query, pl.Calibration(self.robot, False, "the fusion node is stopping"))
            if served is not None:
                served.close()
            sub.undeclare()
            token.undeclare()
            for p in (pub_joints, pub_heading, pub_status, pub_health):
                p.undeclare()
        adm = self._admission
        return ServeReport(self.robot, self._state, self._counts["samples"], self._counts["estimates"],
                           self._counts["out_of_order"], self._dropped(receiver), self._startup_t,
                           self._message, self._resumed, self._resume_message,
                           self._counts["calibrations"], adm.missed_batches, adm.seq_resets,
                           adm.encoder_rebases, self._stall.stalls, self._counts["errors"],
                           dict(adm.rejected_samples), self._counts["degraded_periods"],
                           self._counts["folded_instants"], int(round(1e3 * self._lag_max_s)),
                           self._counts["shed_batches"], self._counts["shed_samples"])

    def _dropped(self, receiver: BoundedReceiver) -> dict[str, int]:
        d = Counter(self._inbox.dropped) + self._admission.rejected
        if receiver.overflowed:
            d["overflow"] += receiver.overflowed
        return dict(d)

    def _take(self, msg, receiver: BoundedReceiver) -> None:
        """One message, or, when the node is degraded, every message waiting: the lateness
        policy (:class:`Lateness`)."""
        if not self._degraded:
            self._on_message_guarded(msg)
            self._judge_lag()
            return
        now = time.monotonic()
        until = now + self.lateness.pass_s
        # (while it tracks: the startup calibration gets every sample it keeps)
        shed_before = now - self.lateness.shed_after_s if self._tracker is not None else -np.inf
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
        if self._tracker is not None:
            try:
                self._fuse(self._reorder.release(clock_s=self._admission.clock(time.monotonic())),
                           fold=True)
            except Exception as e:  # noqa: BLE001 - as _on_message_guarded
                self._counts["errors"] += 1
                log.exception("serve: error while catching up: %s: %s", type(e).__name__, str(e)[:200])
        self._judge_lag()

    def _shed(self, msg) -> None:
        """Shed ``msg`` unread but for its count of samples (:class:`Lateness`,
        ``shed_after_s``); ``None``: nothing."""
        if msg is None:
            return
        self._counts["shed_batches"] += 1
        self._admission.shed(msg.key.rpartition("/")[2])
        if len(msg.data) > pl.MAX_PAYLOAD_BYTES:  # (what the decoder would not read either)
            return
        try:  # (the JSON parser's C alone: no check, no array, no sample handled in Python)
            values = json.loads(msg.data).get("values")
        except (ValueError, AttributeError, RecursionError):
            return
        self._counts["shed_samples"] += len(values) if isinstance(values, list) else 0

    def _sensors_now(self, now_s: float) -> float | None:
        """The sensors' time at wall time ``now_s`` as their delivery says it: ``now_s``
        less the usual delivery delay (the median over the streams of the least delay,
        arrival less last sample's time, of each one's batches in the last
        ``delay_window_s``); ``None`` before any."""
        lows = sorted(d[0][1] for d in self._delays.values() if d)
        return None if not lows else now_s - lows[(len(lows) - 1) // 2]

    def _note_delay(self, name: str, arrived_s: float, t_s: float) -> None:
        """Note an accepted batch's delivery delay (a sliding minimum per stream)."""
        d = self._delays.setdefault(name, deque())
        delay = arrived_s - t_s
        while d and d[-1][1] >= delay:
            d.pop()
        d.append((arrived_s, delay))
        while d[0][0] < arrived_s - self.lateness.delay_window_s:
            d.popleft()

    def _judge_lag(self) -> None:
        """The node's lag (how far the samples it last took are behind the sensors' time now),
        and whether it is degraded (see :class:`Lateness`)."""
        lt = self.lateness
        now = time.monotonic()
        sensors_now = self._sensors_now(now)
        if sensors_now is None or self._taken_t is None:
            return
        lag = max(sensors_now - self._taken_t, 0.0)
        self._lag_s, self._lag_max_s = lag, max(self._lag_max_s, lag)
        was = self._degraded
        if not self._live(now):
            self._degraded = False
        elif lag > lt.degrade_after_s:
            self._degraded = True
        elif lag <= 0.5 * lt.degrade_after_s:
            self._degraded = False
        if self._degraded != was:
            self._status_due = True
            if self._degraded:
                self._degraded_news = True
                self._counts["degraded_periods"] += 1
                log.warning("serve: degraded: %.0f ms behind the sensors; folding the backlog", 1e3 * lag)
            else:
                log.info("serve: caught up (%.0f ms behind); no longer degraded", 1e3 * lag)

    def _live(self, now_s: float | None = None) -> bool:
        """Whether the stream is live: its arrivals began at least half ``pace_window_s``
        ago (wall time ``now_s``, whatever the node has taken in of them since), and the
        sensors' time ran at about wall time (at most the lateness policy's ``max_pace``
        times as fast) over the arrivals of the last ``pace_window_s`` the node has taken
        in, once they span ``pace_min_s``."""
        lt = self.lateness
        marks = self._pace_marks
        if not marks:
            return False
        now_s = time.monotonic() if now_s is None else now_s
        wall = self._pace_arrived_s - marks[0][0]
        return (now_s - self._run_began_s >= 0.5 * lt.pace_window_s and wall >= lt.pace_min_s
                and marks[-1][2] - marks[0][1] <= lt.max_pace * wall)

    def _mark_pace(self, arrived_s: float, t_s: float) -> None:
        """Note an accepted batch's last time ``t_s``, arrived at ``arrived_s``: per 0.1 s of
        arrivals, its first arrival, its first batch's time and the newest time; those of the
        last ``pace_window_s`` kept. (A silence its time did not run through is not judged a
        paused source: at arrival it cannot be told from a node that was itself stopped.)"""
        marks = self._pace_marks
        if arrived_s - self._pace_arrived_s > self.lateness.pace_window_s:
            self._run_began_s = arrived_s
        self._pace_arrived_s = max(self._pace_arrived_s, arrived_s)
        if marks and arrived_s < marks[-1][0] + 0.1:
            if t_s > marks[-1][2]:
                marks[-1] = (*marks[-1][:2], t_s)
            return
        marks.append((arrived_s, t_s, t_s))
        while marks[0][0] < arrived_s - self.lateness.pace_window_s:
            marks.popleft()

    def _on_message_guarded(self, msg, fuse: bool = True) -> None:
        """:meth:`_on_message`, and the last line of defence: whatever slipped past the checks
        is counted (``errors``), logged with its traceback, and the node goes on."""
        try:
            self._on_message(msg, fuse)
        except Exception as e:  # noqa: BLE001 - nothing a peer sends may stop the node
            self._counts["errors"] += 1
            self._status_due = True
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
            self._delays.pop(s.name, None)
            self._buffer.forget(s.name)
            self._recent.forget(s.name)
            self._reorder.forget(s.name)
            if self._maneuver is not None:
                self._maneuver.clock_reset(s.name)
        self._counts["samples"] += len(s)
        self._arrived[s.name] = now
        self._taken_t = float(s.t_s[-1])
        self._mark_pace(arrived, self._taken_t)
        self._note_delay(s.name, arrived, self._taken_t)
        self._recent.keep(s)
        if self._maneuver is not None:
            self._maneuver.keep(s)
        if self._tracker is None:
            self._buffer.keep(s)
            if self._saved is not None:
                if s.name != ENC:
                    return  # the first encoder sample decides whether the saved state holds
                self._try_resume(float(s.t_s[0]), s.values[0])
                if self._tracker is not None:
                    return
            self._try_start(float(s.t_s[-1]))
            return
        self._counts["out_of_order"] += self._reorder.push(s)
        if fuse:
            self._fuse(self._reorder.release(clock_s=self._admission.clock(now, arrived)))

    # -- start: a saved state, or a startup calibration on a still arm -------------------------
    def _try_resume(self, t_s: float, encoder_counts: np.ndarray) -> None:
        doc, self._saved = self._saved, None
        tracker, problem = state_file.resumed_tracker(
            doc, self.arm, self.settings, robot=self.robot, t_s=t_s, encoder_counts=encoder_counts,
            max_age_s=self.max_state_age_s, max_joint_rate_rad_s=self.max_joint_rate_rad_s,
            max_gap_s=self._max_lag_s, config_sha256=self._config_sha)
        if problem is not None:
            self._resume_message = (f"saved state in {self.state_path} not used: {problem}; "
                                    "a startup calibration on a still arm")
            self._message = self._resume_message
            log.warning("serve: %s", self._resume_message)
            return
        moved = np.abs(np.asarray(encoder_counts, float) - np.asarray(doc["encoder_counts"], float))
        moved_deg = float(np.degrees(np.max(moved / self.arm.counts_per_rad)))
        self._resume_message = (f"resumed from the state saved in {self.state_path} "
                                f"{time.time() - float(doc['saved_wall_s']):.1f} s ago at t = "
                                f"{float(doc['t_s']):.3f} s; the encoders moved up to {moved_deg:.2f}° "
                                "since: no startup calibration needed")
        self._resumed = True
        self._rates_hz = dict(doc["rates_hz"])
        self._last_enc = (float(doc["t_s"]), np.asarray(doc["encoder_counts"], dtype=np.int64))
        self._begin(tracker, self._buffer.merged(), self._resume_message)

    @property
    def startup_kept_s(self) -> float:
        """Until the tracker starts, the span of sample time kept for the startup calibration
        (s; at most 1.25 × ``startup_keep_s``); 0 once tracking."""
        return self._buffer.span_s

    def _try_start(self, t_now: float) -> None:
        if t_now < self._next_try_t:
            return
        # (the kept samples' span, not a merge of them on every batch: a node that merged its
        # growing buffer per message fell further behind the longer it collected)
        kept_s = self.startup_kept_s
        if kept_s < self.min_data_s:
            self._message = (f"collecting {self.min_data_s:g} s of samples for the startup calibration "
                             f"({kept_s:.1f} s so far)")
            return
        rec = self._buffer.merged()
        self._next_try_t = t_now + self.retry_s
        try:
            # (the unlock-move search is for a person asking: calibrate on request shows it)
            tracker, start = start_from_recording(self.arm, rec, self.settings, propose_unlock=False,
                                                  prior=self._parked_prior())
        except NoStillWindowError as e:
            self._message = f"waiting for a still arm: {e}"
            return
        except (ValueError, KeyError) as e:
            self._message = f"startup calibration failed: {e}"
            log.warning("serve: %s", self._message)
            return
        self._rates_hz = {k: (v.rate_hz or 100.0) for k, v in rec.raw().items()}
        self._start = start
        assumed = ("; its branches rest on an assumption: the arm parked at its ready pose "
                   "(--assume-parked)" if self.assume_parked else "")
        compass = ""
        try:
            if tracker.compass.restore_iron(self._saved_iron):
                compass = f"; the compass's iron as learnt before, from {self.state_path}"
        except ValueError as e:
            compass = f"; the saved compass calibration not used: {e}"
        self._begin(tracker, rec, f"startup calibration on the still stretch {start.t_start_s:.2f}"
                                  f"-{start.t_end_s:.2f} s; tracking" + assumed + ambiguity_note(start)
                    + compass)

    def _begin(self, tracker: Tracker, rec: Recording, message: str) -> None:
        """Track with ``tracker`` from its time on; ``rec``'s later samples go to it first."""
        self._tracker = tracker
        self._stall.estimated_s = time.monotonic()
        self._startup_t = float(tracker.t_s)
        self._state = "tracking"
        self._message = message
        self._status_due = True
        log.info("serve: %s", message)
        for s in rec.streams.values():
            self._reorder.seen(s.name, float(s.t_s[-1]))
            after = s.between(self._startup_t + 1e-9, np.inf)
            if len(after):
                self._counts["out_of_order"] += self._reorder.push(after)
        self._buffer.clear()
        now = time.monotonic()
        self._fuse(self._reorder.release(clock_s=self._admission.clock(now)), fold=self._live())

    # -- calibration on request ------------------------------------------------------------------
    def _next_query(self):
        try:
            return self._queries.get_nowait()
        except queue.Empty:
            return None

    def _answer(self, query) -> None:
        try:
            result = self.calibrate()
        except Exception as e:  # noqa: BLE001 - a request must get a reply and never stop the node
            log.exception("serve: calibration on request failed")
            result = pl.Calibration(self.robot, False, f"calibration failed: {type(e).__name__}: {e}")
        self._reply(query, result)

    def _reply(self, query, result: pl.Calibration) -> None:
        try:
            query.reply(pl.calibrate_key(self.robot), pl.encode(result))
        finally:
            query.drop()

    def calibrate(self, arm: ArmModel | None = None, why: str = "calibrated on request",
                  carry_pose: bool = False) -> pl.Calibration:
        """Re-run the startup calibration on the latest still stretch and restart the tracker
        from it; or refuse, saying why (the arm moves, no still stretch yet, no samples).
        ``arm``: a new config of the same arm (a sensor calibration's) to track with from then
        on; ``why``: how the status's message begins; ``carry_pose``: the running tracker's
        last pose and sigma go to the startup as a saved pose (checked against the still data)
        and seed the joints it cannot read (the arm has not moved: it is still)."""
        arm = self.arm if arm is None else arm
        e = self._last_estimate if carry_pose else None
        pose = {} if e is None else {"prior_q_rad": np.asarray(e.q_rad, float),
                                     "prior_sigma_rad": np.asarray(e.sigma_rad, float)}

        def refuse(why: str) -> pl.Calibration:
            return pl.Calibration(self.robot, False, why)

        still = self._recent.still_now(self.still_tolerance_s)
        if isinstance(still, str):
            return refuse(still)
        _, window = still
        try:
            tracker, start = start_from_recording(arm, window, self.settings,
                                                  prior=self._parked_prior(arm), **pose)
        except NoStillWindowError as e:
            return refuse(f"the arm moves: {e}")
        except (ValueError, KeyError) as e:
            return refuse(f"the startup calibration failed: {e}")
        self._counts["calibrations"] += 1
        if self._tracker is None:
            self._rates_hz = {k: (v.rate_hz or 100.0) for k, v in self._recent.recording().raw().items()}
        else:
            tracker.set_rates(self._rates_hz)
        self._start = start
        if arm is not self.arm:
            self.arm, self._config_sha = arm, state_file.config_fingerprint(arm)
        message = (f"{why} on the still stretch {start.t_start_s:.2f}-{start.t_end_s:.2f} s"
                   f"; tracking from it: {start.startup.summary or ''}").rstrip(": ")
        self._begin(tracker, Recording({}), message)
        return calibration_reply(self.robot, arm.joint_names, start)

    # -- the planned maneuver ---------------------------------------------------------------------
    def _apply_calibration(self) -> pl.Maneuver:
        """``maneuver/apply``: track from now on with the config the maneuver's fit wrote, from a
        startup calibration on the still arm (:meth:`calibrate`); or refuse, saying why."""
        m = self._maneuver
        if m.state != "calibrated":
            return m.payload(False, f"refused: no calibration to apply (the maneuver is {m.state})")
        try:
            arm = load_arm(m.config_written)
        except (ConfigError, OSError, ValueError) as e:
            return m.payload(False, f"refused: {m.config_written} does not load: {str(e)[:200]}")
        differs = same_arm_problem(self.arm, arm)
        if differs:
            return m.payload(False, f"refused: {m.config_written} is not this arm's config: {differs}")
        what = f"the calibration of {Path(m.config_written).name} applied"
        result = self.calibrate(arm, what, carry_pose=True)
        if not result.ok:
            return m.payload(False, f"refused: {result.message}")
        return m.applied(f"{what}; the startup with it: {result.message}")

    def _joints_note(self) -> str:
        """What the controller must know of the arm's pose before it plays the plan."""
        e = self._last_estimate
        if e is None:
            return ("the node has no joint estimate yet: the controller must take the arm to the plan's "
                    "first pose by its own means")
        unknown = [f"{j} ({f})" for j, f in zip(e.joint_names, e.flags, strict=True) if f != "ok"]
        if unknown:
            return (f"not known to the tracker now: {', '.join(unknown)}: the controller must not rely on "
                    "their estimates to reach the plan's first pose")
        d = np.degrees(np.abs(np.asarray(e.q_rad) - self._maneuver.plan.poses_rad[0]))
        j = int(np.argmax(d))
        return f"the plan's first pose is {d[j]:.1f}° away ({e.joint_names[j]}) from the estimate now"

    # -- tracking, publishing, saving ------------------------------------------------------------
    def _fold(self, instants):
        """``instants`` merged, each sensor's latest sample in a window at its last instant's
        time: those older than the sensors' clock by more than the lateness policy's
        ``degrade_after_s`` one window per ``fold_period_s`` of sample time, or
        ``backlog_updates`` windows when they span longer; the newer ones one window per
        ``fold_period_s`` (the update rate lowered while the node is behind)."""
        if not instants:
            return instants
        lt = self.lateness
        clock = self._sensors_now(time.monotonic())
        stale_before = -np.inf if clock is None else clock - lt.degrade_after_s
        n_stale = next((i for i, (t, _) in enumerate(instants) if t >= stale_before), len(instants))
        # the longer the backlog, the longer a window: at most backlog_updates of them
        period = lt.fold_period_s if not n_stale else max(
            lt.fold_period_s, (stale_before - instants[0][0]) / lt.backlog_updates)
        return self._merged(instants[:n_stale], period) + self._merged(instants[n_stale:], lt.fold_period_s)

    def _merged(self, instants, period_s: float) -> list[tuple[float, dict[str, np.ndarray]]]:
        """``instants`` merged into windows of ``period_s`` from the first (see :meth:`_fold`);
        the instants merged into another are counted in ``folded_instants``."""
        out: list[tuple[float, dict[str, np.ndarray]]] = []
        window_end, merged, t_last = -np.inf, None, None
        for t, samples in instants:
            if merged is not None and t > window_end:
                out.append((t_last, merged))
                merged = None
            if merged is None:
                merged, window_end = {}, t + period_s - 1e-9
            merged.update(samples)
            t_last = t
        if merged is not None:
            out.append((t_last, merged))
        self._counts["folded_instants"] += len(instants) - len(out)
        return out

    def _fuse(self, instants, fold: bool = False) -> None:
        """Feed released instants to the tracker; publish at most every publish period.
        ``fold``: the lateness policy's pass (:class:`Lateness`): stale instants folded."""
        tr = self._tracker
        takes = set(tr.sensor_names) | {"imu_temp"}
        if fold:
            instants = self._fold(instants)
        for t, samples in instants:
            enc = samples.get(ENC)
            if enc is not None and t >= tr.t_s - 1e-9:  # what the tracker fuses, not drops
                self._last_enc = (t, np.asarray(enc, dtype=np.int64))
            e = tr.update_instant(t, {k: v for k, v in samples.items() if k in takes})
            if e is None:
                continue
            self._stall.estimated_s = time.monotonic()
            self._last_estimate = e
            if e.sensors != self._sensors:
                self._sensors = e.sensors
                self._status_due = True
            if t >= self._next_pub_t:
                self._publish(e)
                self._next_pub_t = t + self.publish_period_s
            if tr.alarm.version != self._alarm_version:  # an alarm raised, named again or cleared
                self._alarm_version = tr.alarm.version
                self._publish_health()
        if self._start is not None and tr.ambiguity():
            self._try_resolve(tr.t_s)

    def _parked_prior(self, arm: ArmModel | None = None):
        return StartupPrior.assume_parked(arm or self.arm) if self.assume_parked else None

    def _try_resolve(self, t_now: float) -> None:
        """Joints the startup left ambiguous: on each new still stretch after it, solve again
        (:func:`armfusion.fusion.service.restart.solve_ambiguity_again`); when that tells the branches
        apart, track from it. Nothing here moves the arm: the status names the move that would
        help."""
        if t_now < self._next_resolve_t:
            return
        self._next_resolve_t = t_now + self.retry_s
        start = self._start
        still = self._recent.still_now(self.still_tolerance_s)
        if isinstance(still, str) or start.geometric is None or start.encoder_rad is None:
            return
        again = solve_ambiguity_again(self.arm, self.settings, start, still, set(self._tracker.ambiguity()))
        if again is None:
            return
        seg = again.segment
        if again.tracker is None:
            self._message = (f"{', '.join(again.still_ambiguous)} still ambiguous after the still stretch "
                             f"{seg.t_start_s:.2f}-{seg.t_end_s:.2f} s" + ambiguity_note(start))
            self._status_due = True
            return
        again.tracker.set_rates(self._rates_hz)
        self._start = again.start
        self._begin(again.tracker, Recording({}), (
            f"the branches of {', '.join(again.resolved)} told apart on the still stretch "
            f"{seg.t_start_s:.2f}-{seg.t_end_s:.2f} s (the startup's candidates carried through the "
            "encoder counts); tracking from it" + ambiguity_note(again.start)))

    def _publish(self, e) -> None:
        pub_joints, pub_heading = self._pubs
        pub_joints.put(pl.encode(pl.JointState.of(self.robot, e)))
        pub_heading.put(pl.encode(pl.Heading.of(self.robot, e)))
        self._counts["estimates"] += 1

    def _publish_health(self) -> None:
        """The tracker's active model-change alarms on the health key; the status says so too."""
        tr = self._tracker
        self._pub_health.put(pl.encode(pl.Health.of(self.robot, tr.t_s, tr.alarm.alarms)))
        self._counts["alarms"] = len(tr.alarm.raised)
        self._status_due = True

    def _publish_status(self, pub, receiver: BoundedReceiver) -> None:
        self._status_due = self._degraded_news = False
        adm = self._admission
        counters = {"samples": self._counts["samples"], "estimates": self._counts["estimates"],
                    "out_of_order": self._counts["out_of_order"],
                    "missed_batches": adm.missed_batches, "seq_resets": adm.seq_resets,
                    "encoder_rebases": adm.encoder_rebases,
                    "stalled": int(self._stall.since_s is not None), "stalls": self._stall.stalls,
                    "errors": self._counts["errors"],
                    "calibrations": self._counts["calibrations"],
                    "model_alarms": self._counts["alarms"],
                    "degraded": int(self._degraded), "lag_ms": int(round(1e3 * self._lag_s)),
                    "degraded_periods": self._counts["degraded_periods"],
                    "folded_instants": self._counts["folded_instants"],
                    "shed_batches": self._counts["shed_batches"]}
        counters.update({f"dropped.{k}": v for k, v in self._dropped(receiver).items()})
        sensors = dict(self._sensors)
        sensors.update(dict.fromkeys(self._silent & set(sensors), "stale"))
        message = self._message
        if self._maneuver is not None and self._maneuver.state in ("recording", "fitting", "failed"):
            message = f"maneuver {self._maneuver.state}: {self._maneuver.message}; {message}"
        if self._tracker is not None and self._tracker.t_s is not None:
            # a sensor the gate rejects (or the screen leaves out) more than its share, and why
            warnings = self._tracker.sensor_warnings()
            if warnings:
                message = "; ".join(warnings) + f"; {message}"
        if self._tracker is not None and self._tracker.alarm.active:
            message = "model changed: " + "; ".join(a.line() for a in self._tracker.alarm.alarms) + \
                f"; {message}"
        if self._degraded:
            message = (f"degraded: {1e3 * self._lag_s:.0f} ms behind the sensors; folding the backlog "
                       f"({1.0 / self.lateness.fold_period_s:.0f} instants a second of it); {message}")
        if self._silent and self._silent >= set(sensors):
            quiet_s = time.monotonic() - max(self._arrived.values())
            message = f"no samples for {quiet_s:.1f} s: every sensor stale; {message}"
        if self._stall.since_s is not None:
            message = (f"stalled: no estimate for {time.monotonic() - self._stall.since_s:.1f} s while raw "
                       f"batches arrived; {message}")
        pub.put(pl.encode(pl.Status(self.robot, "serve", self._state, time.time(), message,
                                    tuple(counters.items()), tuple(sensors.items()))))

    def save_state(self) -> bool:
        """Write the tracker's state to ``state_path`` (atomically); False before it tracks."""
        tr = self._tracker
        if self.state_path is None or tr is None or self._last_enc is None or tr.t_s is None:
            return False
        try:
            snap = tr.snapshot()
        except RuntimeError:  # no encoder sample fused yet
            return False
        t_enc, counts = self._last_enc
        return state_file.save_tracker_state(self.state_path, self.robot, self.arm.name, t_enc, counts,
                                             self._rates_hz, snap, self._config_sha)
