"""The tracking filter, :class:`Tracker`: a small object with a frozen settings struct
(:class:`armfusion.fusion.tracking.settings.TrackerSettings`), a few lifecycle verbs (``initialise``,
``update`` / ``update_instant`` / ``step``, ``run``, ``state`` / ``resume``,
``snapshot`` / ``restore``) and results by value (:attr:`Tracker.estimate`), composed of
parts that own their state:
:class:`~armfusion.fusion.tracking.health.SensorHealth` (counters, verdicts, statuses),
:class:`~armfusion.fusion.tracking.slips.SlipDetector` (slips and re-acquisition),
:class:`~armfusion.fusion.tracking.observability.Observability` (hold, consider sensitivity, joint
flags), :class:`~armfusion.fusion.tracking.compass.Compass` (the heading),
:class:`~armfusion.fusion.tracking.process.StillDetector` and :class:`~armfusion.fusion.tracking.process.ProcessModel`,
:class:`~armfusion.fusion.tracking.measurement.Measurements`, the two
:class:`~armfusion.fusion.tracking.differentiator.CausalDifferentiator` and
:class:`~armfusion.fusion.tracking.initial.Ambiguity`. The model it runs is described in
:mod:`armfusion.fusion.tracking.tracker` and docs/tracking.md.

Its rooms: :class:`armfusion.fusion.tracking.setup.TrackerSetup` (what it is made of for an arm, and a
start's first state and fresh parts), :class:`armfusion.fusion.tracking.readout.TrackerReadout` (what it
holds and reports, read only; the reports themselves in :mod:`armfusion.fusion.tracking.report` and
:mod:`armfusion.fusion.tracking.combos`), :class:`armfusion.fusion.tracking.fuse.InstantUpdate` (an instant's
predict and update); this class keeps the lifecycle and the one filter path.

One filter path, live and over a recording alike: each instant's readings go through
:meth:`Tracker.step` (the differentiators take them, the mean pose's kinematic frame
is made, compiled, with the offsets and gyro bias of the moment, the filter predicts and
fuses). :meth:`Tracker.update_instant` feeds it one instant's raw samples;
:meth:`Tracker.run` (:func:`armfusion.fusion.tracking.run.run_recording`) a whole recording, with the
conversion to SI units and the saturation checks done for many instants at once, and the
differentiators' fits and the frames for a block of instants in one compiled call each
(:func:`armfusion.fusion.tracking.run.prepare_block`, given to ``step`` as its ``prepared`` pieces).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np
from armfusion.fusion.startup.solve import StartupResult
from armfusion.fusion.tracking.alarm import ModelChangeAlarm
from armfusion.fusion.tracking.combos import JointTiltCombinations
from armfusion.fusion.tracking.compass import Compass
from armfusion.fusion.tracking.estimate import Estimate
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.fuse import InstantUpdate, UpdateParts
from armfusion.fusion.tracking.initial import (
    ImuStill,
    restored_startup,
)
from armfusion.fusion.tracking.live import admit_instant
from armfusion.fusion.tracking.measurement import AccelReadings
from armfusion.fusion.tracking.readout import TrackerReadout
from armfusion.fusion.tracking.report import ReportedParts, Reports
from armfusion.fusion.tracking.settings import (
    ENC,
    F_AMBIGUOUS,
    GYRO,
    MAG,
    TrackerSettings,
)
from armfusion.fusion.tracking.snapshot import SNAPSHOT_FORMAT, TrackerState
from armfusion.fusion.tracking.ukf import BatchedUKF
from armfusion.fusion.tracking.update import InstantReadings, MagReading
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG
from armfusion.sensors.samples import Recording


class Tracker(TrackerReadout):
    """The joint-angle and heading tracker, driven sample by sample (or a whole recording).

    Lifecycle: ``Tracker(arm, settings)`` -> :meth:`initialise` (from a startup result) ->
    :meth:`update` for every raw sample as it arrives (or :meth:`update_instant` for all
    samples of one instant, or :meth:`run` for a recording) -> :attr:`estimate` (by value).
    :meth:`snapshot` / :meth:`restore` carry the state across a restart of the process.
    """

    SNAPSHOT_FORMAT = SNAPSHOT_FORMAT

    def __init__(self, arm: ArmModel, settings: TrackerSettings | None = None,
                 rates_hz: Mapping[str, float] | float = 100.0, correction=None):
        """The arm's tracker, not started (:class:`armfusion.fusion.tracking.setup.TrackerSetup` has the
        arguments)."""
        super().__init__(arm, settings, rates_hz, correction)

    # -- lifecycle -----------------------------------------------------------------------
    def initialise(self, startup: StartupResult, t_s: float, encoder_counts: np.ndarray | None = None,
                   imu: ImuStill | None = None, prior_q_rad: np.ndarray | None = None,
                   prior_sigma_rad: np.ndarray | None = None) -> None:
        """Seed the filter from the startup calibration (its joint angles and covariance).

        ``encoder_counts`` are the counts while the startup window was still (default: the
        first encoder sample that arrives). A joint the startup could not read starts at
        ``prior_q_rad`` (the pose saved at the last clean shutdown; default the ready pose)
        with ``unknown_joint_sigma_deg`` (or ``prior_sigma_rad``, where a running tracker knew
        it better), and is ``converging`` until read; without a saved
        pose, the sigma it reports covers every angle inside its limits until gravity reads
        it (the filter's own stays as said: a prior that wide would not linearise). ``imu`` (from
        :func:`armfusion.fusion.tracking.imu_still.imu_still_from_recording`) gives the gyro bias, heading and
        field reference.
        """
        n = self.arm.n_joints
        p = self.start_parts(startup, imu or ImuStill(np.zeros(3), 0.5 * DEG, None, None, None), t_s,
                             prior_q_rad, prior_sigma_rad)
        self._x0, self._P0, self._q_startup, self.ambiguity_ = p.x0, p.P0, p.q_startup, p.ambiguity
        self._ukf = None  # created when the first encoder sample fixes the offsets
        self._q_enc = np.zeros(n)
        self._enc0 = None if encoder_counts is None else np.asarray(encoder_counts, float)
        if self._enc0 is not None:
            self.start_filter(self._enc0 / self.counts_per_rad)
        self._t = float(t_s)
        self.compass, self.enc_rates, self.gyro_rates = p.compass, p.enc_rates, p.gyro_rates
        self.health, self.slips, self._alarm, self.still = p.health, p.slips, p.alarm, p.still
        self._omega = None  # last gyro, base axes, rad/s
        self.observability.reset()
        if p.unread_var is not None:
            self.observability.set_unread(p.unread_var)
        self._flags = p.flags
        self._combos = JointTiltCombinations(self.arm, self.layout, self.settings, self.observability)
        self._reports = Reports(self.arm, self.settings, self.layout, self.accel_streams, self._unmodelled_g,
                                self.sensor_index.get(MAG), self.gyro_scale_sigma,
                                ReportedParts(self.health, self.compass, self.observability, self.ambiguity_,
                                              self._combos))
        self._update = InstantUpdate(UpdateParts(
            self.settings, self.layout, n, self.measurements, self.process, self.observability, self.still,
            self.intensity, self.compass, self.health, self.slips, self._alarm, self.sensor_index.get(MAG),
            self.R_0I if self._has_imu else None, self._P0), len(self.link_names), self._reacquire)
        self._flags_t = -np.inf
        self._frame_cache = None

    def start_filter(self, q_enc: np.ndarray) -> None:
        """Start the filter at the first encoder sample's angles ``q_enc`` (rad), which fix
        the offsets (the startup's encoder counts where :meth:`initialise` was given them);
        nothing when it runs already."""
        if self._ukf is not None:
            return
        if self._enc0 is not None:
            q_enc = self._enc0 / self.counts_per_rad
        L = self.layout
        self._q_enc = np.array(q_enc, dtype=float)
        if self.ambiguity_.q_enc is None:
            self.ambiguity_.q_enc = self._q_enc.copy()  # the candidates hold at these encoder angles
        x = self._x0.copy()
        x[L.offset] = self._q_startup - q_enc
        self._ukf = BatchedUKF(x, self._P0, self._points, angle_states=(L.yaw,))

    @property
    def alarm(self) -> ModelChangeAlarm:
        """The recalibration alarm (:class:`armfusion.fusion.tracking.alarm.ModelChangeAlarm`); another
        may stand in for it (a benchmark's that does nothing)."""
        return self._alarm

    @alarm.setter
    def alarm(self, alarm: ModelChangeAlarm) -> None:
        self._alarm = alarm
        self._update.parts = replace(self._update.parts, alarm=alarm)

    # -- the one filter path ------------------------------------------------------------------
    def update(self, stream: str, t_s: float, values) -> Estimate | None:
        """Fuse one raw sample (counts, as the device gave them) of ``stream`` at ``t_s``.

        Returns the estimate after it, or None if the sample was dropped (out of order,
        not finite, saturated, or before the first encoder sample).
        """
        return self.update_instant(t_s, {stream: values})

    def update_instant(self, t_s: float, samples: Mapping[str, np.ndarray]) -> Estimate | None:
        """Fuse every sample of one instant together (one stacked update): raw counts by
        stream, as the devices gave them: admitted (:func:`armfusion.fusion.tracking.live.admit_instant`), then
        :meth:`step`."""
        self._check()
        t = float(t_s)
        readings = admit_instant(self, t, samples)
        if readings is None or not self.step(t, readings):
            return None
        return self.estimate

    def step(self, t: float, readings: InstantReadings, prepared: tuple | None = None) -> bool:
        """One instant's admitted readings through the filter (the one path, live and over a
        recording): the encoders' angles, the gyro, the accelerometers and the compass,
        any of them None when it has no sample here. False before the first encoder sample.

        The differentiators take the encoders and the gyro, and the kinematic frame is made
        with the filter's offsets and gyro bias now (:meth:`_frame_now`); or, over a
        recording, ``prepared`` = ``(encoder fit at t (3, n) or None, frame or None)`` from
        :func:`armfusion.fusion.tracking.run.prepare_block`, which pushed the samples and made the frames of a block of
        instants at once, with the offsets and gyro bias of the block's start. Then
        predict, stack, innovate, gate, correct (:meth:`_step`)."""
        q_enc, gyro, acc, mag = readings
        health = self.health
        if q_enc is not None:
            health.mark_used(self.sensor_index[ENC], t)
            if self._ukf is None:
                self.start_filter(q_enc)
            if prepared is None:
                self.enc_rates.push(t, q_enc)
            self._frame_cache = None
        if self._ukf is None:
            return False
        if gyro is not None:
            if prepared is None:
                self.gyro_rates.push(t, gyro)
            health.mark_used(self.sensor_index[GYRO], t)
        if prepared is None:
            # (the compass's heading residual is computed through the frame too: a
            # magnetometer read at an instant of its own needs one)
            frame = self._frame_now(t, gyro) if acc is not None or mag is not None else None
            e = self.enc_rates.at(t)
        else:
            e, frame = prepared
        self._step(t, gyro, acc, mag, frame, self._q_enc if e is None else e[0])
        return True

    def _frame_now(self, t: float, gyro: np.ndarray | None) -> Frames | None:
        """The mean pose's kinematics at ``t``, with the filter's offsets and gyro bias now,
        the gyro's reading at ``t`` (else its last) and its derivative at its last sample
        (kept for further samples of the same instant: the product of exponentials carries
        any change of the offsets since, exactly, and into the motion term to first order).
        Compiled (:mod:`armfusion.fusion.tracking.frame_kernels`); :func:`armfusion.fusion.tracking.run.prepare_block`
        is the same for a block of instants."""
        if self._frame_cache is not None and self._frame_cache[0] == t:
            return self._frame_cache[1]
        e = self.enc_rates.at(t)
        if e is None:
            return None
        L = self.layout
        x = self._ukf.x
        w = self._omega if gyro is None else gyro
        om = None if w is None else self.process.rate(w, x)
        g = self.gyro_rates.latest
        omd = None if g is None else g[1]
        fields = self.frame_constants.fields(e, x[L.offset], om, omd, self.settings.motion_compensation)
        frame = self.measurements.with_noise(Frames.of(fields))
        self._frame_cache = (t, frame)
        return frame

    def _step(self, t: float, gyro: np.ndarray | None, acc: AccelReadings | None, mag: MagReading | None,
              frame: Frames | None, q_enc: np.ndarray) -> None:
        """Predict to ``t`` (the gyro's rate over the interval), the base's stillness and
        motion averages, the compass's averaged reading, then the update
        (:class:`armfusion.fusion.tracking.fuse.InstantUpdate`), the attitude folded back into Euler
        angles, the flags when due."""
        ukf, up = self._ukf, self._update
        self._q_enc = q_enc
        dt = t - self._t
        anchor = (up.predict(ukf, dt, self._omega, gyro, self._gyro_newer_weight, self.attitude_index)
                  if dt > 0 else None)
        if gyro is not None:
            self._omega = gyro
        self._t = t
        if frame is None:
            acc = None
        up.averages(ukf, dt, gyro, acc)
        if mag is not None:
            mag = up.compass_reading(ukf, t, mag, frame, self._omega, q_enc)
        if acc is not None or mag is not None:
            up.fuse(ukf, t, acc, mag, frame, self._omega, q_enc, self._link_read_horizon_s)
        if dt > 0 and anchor is not None:  # back to Euler angles about the anchor (a reset)
            ukf.recentre(self.process.fold_attitude(ukf.mean, anchor))
        if t - self._flags_t >= self.settings.observability_period_s or self.health.changed:
            self._update_flags(t)

    def _reacquire(self, i: int, t: float) -> None:
        self.alarm.reacquired(t, self._ukf.mean[self.layout.offset])
        self.slips.reacquire(i, t, self._ukf, self.health, self.observability.locked)

    def _update_flags(self, t: float) -> None:
        """Sensor statuses and joint flags, every ``observability_period_s`` and at once
        when a sensor's health changes."""
        self._flags_t = t
        codes = self.health.update_statuses(t)
        if self._ukf is None:
            return
        n = self.arm.n_joints
        self._flags = self.observability.joint_flags(
            t, codes, self._ukf.covariance, self._q_enc + self._ukf.mean[:n], self.ambiguity_.joints,
            self.slips.reacquiring_until)

    # -- a whole recording -------------------------------------------------------------------
    def run(self, rec: Recording, t_stop_s: float | None = None, truth: bool = True,
            block: int = 256, progress: Callable[[float], None] | None = None):
        """Fuse every sample of ``rec`` after the current time (up to ``t_stop_s``), through
        the same path as :meth:`update_instant`: a :class:`armfusion.fusion.tracking.run.TrackRun`
        (:func:`armfusion.fusion.tracking.run.run_recording` has the details)."""
        from armfusion.fusion.tracking.run import run_recording

        self._check()
        return run_recording(self, rec, t_stop_s, truth, block, progress)

    # -- restart -----------------------------------------------------------------------------
    def state(self) -> TrackerState:
        """What the started tracker knows now, by value (:class:`armfusion.fusion.tracking.snapshot.TrackerState`)."""
        self._check_filter()
        ukf = self._ukf
        return TrackerState(
            t_s=self._t, x=ukf.x.copy(), P=ukf.P.copy(), q_enc=self._q_enc.copy(),
            omega=None if self._omega is None else np.array(self._omega, dtype=float),
            encoder_fit=self.enc_rates.snapshot(), gyro_fit=self.gyro_rates.snapshot(),
            compass=self.compass.snapshot(), counters=self.health.counts.copy(),
            still=self.still.snapshot(),
            intensity=None if self.intensity is None else self.intensity.snapshot(),
            shift=self.slips.snapshot(), consider=self.observability.snapshot(),
            ambiguous=self.ambiguity_.snapshot(), alarm=self.alarm.snapshot())

    def resume(self, state: TrackerState) -> None:
        """Start from ``state`` (:meth:`state`, maybe of another process) instead of
        :meth:`initialise`."""
        L = self.layout
        x = np.array(state.x, dtype=float)
        self.initialise(restored_startup(self.arm), float(state.t_s),
                        imu=ImuStill(x[L.bias], 1e-3, None, None, Compass.field_from(state.compass)))
        self._q_enc = np.array(state.q_enc, dtype=float)
        self._ukf = BatchedUKF(x, np.array(state.P, dtype=float), self._points, angle_states=(L.yaw,))
        self._omega = None if state.omega is None else np.array(state.omega, dtype=float)
        self.enc_rates.restore(state.encoder_fit)
        self.gyro_rates.restore(state.gyro_fit)
        self.compass.restore(state.compass)
        self.health.counts = np.array(state.counters, dtype=np.int64)
        if state.still is not None:
            self.still.restore(state.still)
        if self.intensity is not None and state.intensity is not None:
            self.intensity.restore(state.intensity)
        if state.shift is not None:
            self.slips.restore(state.shift)
        if self.ambiguity_.restore(state.ambiguous, self.arm.n_joints):  # rival branches still open
            self._flags = np.where(self.ambiguity_.joints, F_AMBIGUOUS, self._flags).astype(np.int8)
        # the calibration's pull on the offsets so far
        self.observability.restore(state.consider, float(state.t_s))
        if state.alarm is not None:  # (raised before the restart: still raised, still down-weighted)
            self.alarm.restore(state.alarm)

    def snapshot(self) -> dict:
        """The tracker's state as a JSON-ready dict (:meth:`TrackerState.to_dict`): enough to
        resume after a restart of the process without a new startup calibration, provided the
        encoders kept counting."""
        return self.state().to_dict(self.arm.name, self.state_names)

    def restore(self, snap: Mapping) -> None:
        """Resume from :meth:`snapshot` (replaces :meth:`initialise`)."""
        self.resume(TrackerState.from_dict(snap, self.arm.name, self.state_names))
