"""The fusion node's tracker and its life: until it tracks, the kept samples and the start
(from the saved state when the first encoder sample says it holds, else a startup
calibration on the first still stretch); then every accepted batch merged in time and fed
to it, its estimates published at most ``publish_hz``, its model-change alarms on the
health key; a startup again on request or to tell ambiguous branches apart; its state saved.

What it says goes on the node's board (:class:`~armfusion.fusion.service.serve_status.NodeBoard`),
which the node's status reads."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service import state_file
from armfusion.fusion.service.admission import Admission
from armfusion.fusion.service.lateness import LagWatch
from armfusion.fusion.service.node import StallWatch
from armfusion.fusion.service.node_start import (
    Began,
    first_start,
    kept_rates_hz,
    parked_prior,
    resolve_again,
    resume_from,
    start_on_still_now,
)
from armfusion.fusion.service.reorder import Reorder
from armfusion.fusion.service.restart import RecentSamples, calibration_reply
from armfusion.fusion.service.serve_endpoints import NodeEndpoints
from armfusion.fusion.service.serve_settings import NodeSettings
from armfusion.fusion.service.serve_status import NodeBoard
from armfusion.fusion.service.startup_buffer import StartupBuffer
from armfusion.fusion.tracking.tracker import ENC, Start, Tracker
from armfusion.models.arm import ArmModel
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.samples import Recording, Stream

log = logging.getLogger("armfusion.service")


@dataclass(frozen=True)
class NodeParts:
    """The parts of the fusion node its tracking reads and writes: the ``board`` its status
    reads, the ``admission`` (the sensors' clock), the ``lag`` watch (folding) and the
    ``stall`` watch (the last estimate's time)."""

    board: NodeBoard
    admission: Admission
    lag: LagWatch
    stall: StallWatch


class NodeTracking:
    """The tracker of the fusion node for ``robot`` on ``arm`` under ``config``, and what it
    keeps for its starts; ``endpoints``: where it publishes, set before the first batch."""

    def __init__(self, arm: ArmModel, robot: str, config: NodeSettings, parts: NodeParts):
        self.arm, self.robot, self.config = arm, robot, config
        self.endpoints: NodeEndpoints | None = None
        self._config_sha = state_file.config_fingerprint(arm)  # what a saved state was tracked with
        self._board, self._admission = parts.board, parts.admission
        self._lag, self._stall = parts.lag, parts.stall
        self._reorder = Reorder(config.max_lag_s)
        self._buffer = StartupBuffer(config.startup_keep_s)
        self._recent = RecentSamples(config.recent_s, stream_models(arm))
        self.tracker: Tracker | None = None
        self._start: Start | None = None  # the startup the tracker runs on (its rival branches)
        self._rates_hz: dict[str, float] = {}
        self._last_enc: tuple[float, np.ndarray] | None = None
        self.last_estimate = None
        self._next_try_t = self._next_resolve_t = self._next_pub_t = -np.inf
        self.startup_t: float | None = None
        self._alarm_version = 0  # the model-change alarms' version last published
        self.sensors: tuple[tuple[str, str], ...] = ()  # each sensor's status, the last estimate's
        self.resumed, self.resume_message = False, ""
        self._saved: dict | None = None
        self._saved_iron: dict | None = None  # the compass's learnt iron, reused by a fresh start
        if config.state_path is not None:
            self._load_saved()

    def _load_saved(self) -> None:
        path = self.config.state_path
        try:
            self._saved = state_file.load_state(path)
            self._saved_iron = state_file.saved_compass_calibration(self._saved, self.robot,
                                                                     self.arm.name, self._config_sha)
            self.resume_message = f"found a saved state in {path}"
        except state_file.StateFileError as e:
            self.resume_message = f"no resume: {e}; a startup calibration on a still arm"
            log.info("serve: %s", self.resume_message)

    @property
    def kept_s(self) -> float:
        """Until the tracker starts, the span of sample time kept for the startup calibration
        (s); 0 once tracking."""
        return self._buffer.span_s

    def forget(self, name: str) -> None:
        """Let go of what is kept of sensor ``name`` (its clock was refuted)."""
        self._buffer.forget(name)
        self._recent.forget(name)
        self._reorder.forget(name)

    def take(self, s: Stream, fuse: bool, now_s: float, arrived_s: float) -> None:
        """An accepted batch ``s`` (arrived at ``arrived_s``, wall time now ``now_s``): kept;
        before the tracker starts, a start tried; after, merged in time and, with ``fuse``,
        what is released fed to the tracker."""
        self._recent.keep(s)
        if self.tracker is None:
            self._buffer.keep(s)
            if self._saved is not None:
                if s.name != ENC:
                    return  # the first encoder sample decides whether the saved state holds
                self._try_resume(float(s.t_s[0]), s.values[0])
                if self.tracker is not None:
                    return
            self._try_start(float(s.t_s[-1]))
            return
        self._board.counts["out_of_order"] += self._reorder.push(s)
        if fuse:
            self.fuse(self._reorder.release(clock_s=self._admission.clock(now_s, arrived_s)))

    def fuse_released(self, fold: bool) -> None:
        """Feed the tracker what the merge releases by the sensors' clock now."""
        self.fuse(self._reorder.release(clock_s=self._admission.clock(time.monotonic())), fold=fold)

    # -- start: a saved state, or a startup calibration on a still arm -------------------------
    def _try_resume(self, t_s: float, encoder_counts: np.ndarray) -> None:
        doc, self._saved = self._saved, None
        c = self.config
        checks = state_file.ResumeChecks(self.robot, max_age_s=c.max_state_age_s,
                                         max_joint_rate_rad_s=c.max_joint_rate_rad_s, max_gap_s=c.max_lag_s,
                                         config_sha256=self._config_sha)
        began = resume_from(doc, self.arm, c.tracker, checks, t_s=t_s, encoder_counts=encoder_counts,
                            state_path=c.state_path)
        if isinstance(began, str):
            self.resume_message = self._board.message = began
            log.warning("serve: %s", began)
            return
        self.resume_message, self.resumed = began.message, True
        self._rates_hz = dict(doc["rates_hz"])
        self._last_enc = (float(doc["t_s"]), np.asarray(doc["encoder_counts"], dtype=np.int64))
        self._begin(began.tracker, self._buffer.merged(), began.message)

    def _try_start(self, t_now: float) -> None:
        c = self.config
        if t_now < self._next_try_t:
            return
        # (the kept samples' span, not a merge of them on every batch: a node that merged its
        # growing buffer per message fell further behind the longer it collected)
        kept_s = self.kept_s
        if kept_s < c.min_data_s:
            self._board.message = (f"collecting {c.min_data_s:g} s of samples for the startup calibration "
                                   f"({kept_s:.1f} s so far)")
            return
        rec = self._buffer.merged()
        self._next_try_t = t_now + c.retry_s
        began = first_start(self.arm, rec, c.tracker, assume_parked=c.assume_parked,
                            saved_iron=self._saved_iron, state_path=c.state_path)
        if isinstance(began, str):
            self._board.message = began
            return
        self._rates_hz = kept_rates_hz(rec)
        self._start = began.start
        self._begin(began.tracker, rec, began.message)

    def _begin(self, tracker: Tracker, rec: Recording, message: str) -> None:
        """Track with ``tracker`` from its time on; ``rec``'s later samples go to it first."""
        self.tracker = tracker
        self._stall.estimated_s = time.monotonic()
        self.startup_t = float(tracker.t_s)
        b = self._board
        b.state, b.message, b.due = "tracking", message, True
        log.info("serve: %s", message)
        for s in rec.streams.values():
            self._reorder.seen(s.name, float(s.t_s[-1]))
            after = s.between(self.startup_t + 1e-9, np.inf)
            if len(after):
                b.counts["out_of_order"] += self._reorder.push(after)
        self._buffer.clear()
        clock_s = self._admission.clock(time.monotonic())
        self.fuse(self._reorder.release(clock_s=clock_s), fold=self._lag.live(time.monotonic()))

    def calibrate(self, arm: ArmModel | None, why: str, carry_pose: bool) -> pl.Calibration:
        """:meth:`FusionNode.calibrate <armfusion.fusion.service.serve.FusionNode.calibrate>`."""
        arm = self.arm if arm is None else arm
        c = self.config
        began = start_on_still_now(arm, self._recent.still_now(c.still_tolerance_s), c.tracker,
                                   prior=parked_prior(arm, c.assume_parked), why=why,
                                   last_estimate=self.last_estimate if carry_pose else None)
        if isinstance(began, str):
            return pl.Calibration(self.robot, False, began)
        self._board.counts["calibrations"] += 1
        if self.tracker is None:
            self._rates_hz = kept_rates_hz(self._recent.recording())
        else:
            began.tracker.set_rates(self._rates_hz)
        self._start = began.start
        if arm is not self.arm:
            self.arm, self._config_sha = arm, state_file.config_fingerprint(arm)
        self._begin(began.tracker, Recording({}), began.message)
        return calibration_reply(self.robot, arm.joint_names, began.start)

    # -- tracking, publishing, saving ------------------------------------------------------------
    def fuse(self, instants, fold: bool = False) -> None:
        """Feed released instants to the tracker; publish at most every publish period.
        ``fold``: the lateness policy's pass: stale instants folded (:meth:`LagWatch.fold
        <armfusion.fusion.service.lateness.LagWatch.fold>`)."""
        tr, b = self.tracker, self._board
        takes = set(tr.sensor_names) | {"imu_temp"}
        if fold:
            instants = self._lag.fold(instants, time.monotonic())
        for t, samples in instants:
            enc = samples.get(ENC)
            if enc is not None and t >= tr.t_s - 1e-9:  # what the tracker fuses, not drops
                self._last_enc = (t, np.asarray(enc, dtype=np.int64))
            e = tr.update_instant(t, {k: v for k, v in samples.items() if k in takes})
            if e is None:
                continue
            self._stall.estimated_s = time.monotonic()
            self.last_estimate = e
            if e.sensors != self.sensors:
                self.sensors, b.due = e.sensors, True
            if t >= self._next_pub_t:
                self.endpoints.estimate(e)
                b.counts["estimates"] += 1
                self._next_pub_t = t + self.config.publish_period_s
            if tr.alarm.version != self._alarm_version:  # an alarm raised, named again or cleared
                self._alarm_version = tr.alarm.version
                self._publish_health()
        if self._start is not None and tr.ambiguity():
            self._try_resolve(tr.t_s)

    def _try_resolve(self, t_now: float) -> None:
        """Joints the startup left ambiguous: on each new still stretch after it, solve again
        (:func:`armfusion.fusion.service.node_start.resolve_again`); when that tells the branches
        apart, track from it."""
        c = self.config
        if t_now < self._next_resolve_t:
            return
        self._next_resolve_t = t_now + c.retry_s
        began = resolve_again(self.arm, c.tracker, self._start, self._recent.still_now(c.still_tolerance_s),
                              set(self.tracker.ambiguity()))
        if isinstance(began, str):
            self._board.message, self._board.due = began, True
        elif isinstance(began, Began):
            began.tracker.set_rates(self._rates_hz)
            self._start = began.start
            self._begin(began.tracker, Recording({}), began.message)

    def _publish_health(self) -> None:
        """The tracker's active model-change alarms on the health key; the status says so too."""
        tr = self.tracker
        self.endpoints.health(tr.t_s, tr.alarm.alarms)
        self._board.counts["alarms"] = len(tr.alarm.raised)
        self._board.due = True

    def save_state(self) -> bool:
        """Write the tracker's state to the config's ``state_path`` (atomically); False before
        it tracks."""
        tr, path = self.tracker, self.config.state_path
        if path is None or tr is None or self._last_enc is None or tr.t_s is None:
            return False
        try:
            snap = tr.snapshot()
        except RuntimeError:  # no encoder sample fused yet
            return False
        t_enc, counts = self._last_enc
        return state_file.save_tracker_state(path, self.robot, self.arm.name, t_enc, counts,
                                             self._rates_hz, snap, self._config_sha)
