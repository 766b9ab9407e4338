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
from armfusion.fusion.startup.combinations import Combination, observable_combinations
from armfusion.fusion.startup.solve import TILT_NAMES, StartupResult
from armfusion.fusion.tracking import calibrated, fixed_base
from armfusion.fusion.tracking.alarm import ModelChangeAlarm
from armfusion.fusion.tracking.compass import CALIBRATING, GYRO_ONLY, STATUS_CODE, Compass
from armfusion.fusion.tracking.differentiator import CausalDifferentiator
from armfusion.fusion.tracking.estimate import HEADING_STATUS, Estimate
from armfusion.fusion.tracking.frame_kernels import FrameConstants
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.health import SensorHealth, sensor_warnings
from armfusion.fusion.tracking.initial import (
    Ambiguity,
    ImuStill,
    initial_state,
    limits_cover_var,
    read_by_startup,
    restored_startup,
)
from armfusion.fusion.tracking.innovations import InnovationLog
from armfusion.fusion.tracking.live import admit_instant
from armfusion.fusion.tracking.measurement import AccelReadings, Measurements
from armfusion.fusion.tracking.observability import Observability
from armfusion.fusion.tracking.process import (
    MotionIntensity,
    ProcessModel,
    StillDetector,
    attitude_sigma_rad,
    gyro_newer_weight,
)
from armfusion.fusion.tracking.settings import (
    C_REJECTED,
    C_USED,
    ENC,
    F_AMBIGUOUS,
    F_CONVERGING,
    F_GIMBAL,
    F_UNOBSERVED,
    FLAG_CODE,
    GYRO,
    IMU_ACC,
    JOINT_FLAGS,
    MAG,
    S_ABSENT,
    S_DEAD,
    S_STALE,
    G,
    NotInitialisedError,
    StateLayout,
    TrackerSettings,
)
from armfusion.fusion.tracking.slips import SlipDetector
from armfusion.fusion.tracking.snapshot import SNAPSHOT_FORMAT, TrackerState
from armfusion.fusion.tracking.ukf import BatchedUKF, Innovation, SigmaPoints
from armfusion.fusion.tracking.update import InstantReadings, MagReading, UpdateResult
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, up_from_tilt
from armfusion.sensors.samples import Recording


class Tracker:
    """The joint-angle and heading tracker, driven sample by sample (or a whole recording).

    Lifecycle: ``Tracker(arm, settings)`` -> :meth:`initialise` (from a startup result) ->
    :meth:`update` for every raw sample as it arrives (or :meth:`update_instant` for all
    samples of one instant, or :meth:`run` for a recording) -> :attr:`estimate` (by value).
    :meth:`snapshot` / :meth:`restore` carry the state across a restart of the process.
    """

    SNAPSHOT_FORMAT = SNAPSHOT_FORMAT

    def __init__(self, arm: ArmModel, settings: TrackerSettings | None = None,
                 rates_hz: Mapping[str, float] | float = 100.0, correction=None):
        """``correction`` (a :class:`armfusion.fusion.identification.identify.StartupCorrection`, default: made from the
        config's effects when it has any) undoes the calibrated accelerometer errors (affine:
        mount, axes, scale, bias) on every sample, and maps the controller's joint angles to
        the geometric ones (zero offsets, sag, play) in the kinematics."""
        self.model = model = calibrated.config_model(arm)
        arm = calibrated.with_lever_arms(arm, model)
        self.arm = arm
        if correction is None and arm.effects:
            from armfusion.fusion.identification.identify import startup_correction

            correction = startup_correction(arm, include_joint_offsets=True)
        self.correction = correction
        self.readings = calibrated.Readings(arm, model, correction)
        self._joint_effects = calibrated.joint_effects(correction)
        # the base's own motion as the config describes it (a chair's by default)
        self.settings = st = (settings or TrackerSettings()).for_base(arm.base_motion)
        if arm.fixed_base is not None:  # bolted down: no base motion at all
            self.settings = st = st.bolted()
        n = arm.n_joints
        self._has_imu = arm.imu is not None
        # the gyro's scale about the vertical: a state where it is not known exactly (a turn's
        # heading is off by the same fraction each time; the compass shows by how much); for a
        # base that turns about every axis, every axis's scale error as the tilt's noise instead
        self.gyro_scale_sigma = (calibrated.heading_scale_sigma(arm, model, st.gyro_scale_sigma,
                                                                any_axis=st.base_turns_about_any)
                                 if self._has_imu else 0.0)
        self.layout = L = StateLayout(n, velocity=st.base_speed_sigma_mps is not None,
                                      gyro_scale=self.gyro_scale_sigma > 0.0 and not st.base_turns_about_any,
                                      jerk=(st.base_speed_sigma_mps is None and st.base_jerk_sigma_mps3 > 0
                                            and st.motion_compensation),
                                      pivot=(st.base_pivot_sigma_m is not None and self._has_imu
                                             and st.motion_compensation))
        self.state_names = L.names(arm.joint_names)
        self.link_names = tuple(s.name for s in arm.link_accelerometers)
        self.accel_names = self.link_names + ((arm.imu.name,) if self._has_imu else ())
        self.accel_streams = self.link_names + ((IMU_ACC,) if self._has_imu else ())
        self.sensor_names = self.accel_streams + ((GYRO, MAG) if self._has_imu else ()) + (ENC,)
        self.sensor_index = {s: i for i, s in enumerate(self.sensor_names)}
        """Each stream's index in :attr:`sensor_names`."""
        links = np.array([arm.sensor(nm).link for nm in self.accel_names], dtype=int)
        self._links = links  # (the accelerometers' links and the IMU's index: for the kernels' tests)
        self._imu_acc_index = self.sensor_index.get(IMU_ACC, -1)
        self._links_list = [int(k) for k in links[: len(self.link_names)]]
        self.R_0I = arm.imu.R_LS if self._has_imu else np.eye(3)  # the IMU's axes in the base's
        scale, scale_sigma = calibrated.encoder_scales(arm, model)
        self.counts_per_rad = arm.counts_per_rad * (1.0 + scale)
        """Per joint, the encoder's counts per radian (the config's, its calibrated scale error applied)."""
        # each accelerometer turned to its stamp by its calibrated time offset and its part's
        # delay, and the compass by its part's delay, with the base's turn rate
        delays_s = calibrated.part_delays_s(arm, self.accel_streams + (MAG,))
        time_offset_s, time_var_s2 = calibrated.stamp_offsets(model, self.accel_names, delays_s[:-1])
        self._mag_delay_s = float(delays_s[-1]) if self._has_imu else 0.0
        unmodelled_g = calibrated.accel_floors_g(arm, self.link_names, self._has_imu)
        self._unmodelled_g = unmodelled_g
        self._sees = links[:, None] > np.arange(n)[None, :]  # (S, n): sensor s sees joint j
        self.measurements = Measurements(st, L, self.sensor_names, self.accel_streams, links,
                                         self.sensor_index.get(IMU_ACC, -1), unmodelled_g, time_offset_s,
                                         time_var_s2)
        self.observability = Observability(st, L, self.link_names, self.accel_streams, self._sees, correction,
                                           calibrated.spread_maps(correction), unmodelled_g, scale_sigma,
                                           self.R_0I if self._has_imu else None)
        if arm.fixed_base is not None:  # its tilt's floor, which no averaging lowers
            self.observability.tilt_floor_var = fixed_base.floor_var_rad2(unmodelled_g[:len(self.link_names)])
        self.process = ProcessModel(st, L, arm.joint_names)
        if st.base_turns_about_any:
            self.process.set_scale_noise(self.gyro_scale_sigma)
        # a base whose speed is bounded (a hand): how vigorously it moves, from the IMU
        self.intensity = MotionIntensity(st) if L.vel is not None and self._has_imu else None
        self.process.intensity = self.intensity
        self.set_rates(rates_hz)
        self._points = SigmaPoints(L.size, st.alpha, st.beta, st.kappa)
        self._ukf: BatchedUKF | None = None
        self._t: float | None = None
        self.attitude_index = np.array([L.roll, L.pitch, L.yaw])
        """The attitude's (roll, pitch, yaw) indices in the state."""
        self.nees_index = np.r_[np.arange(n), L.roll, L.pitch, L.yaw]
        """The joints' and the attitude's indices in the state (what a NEES is taken over)."""
        self._min_list = arm.min_rad.tolist()
        self._max_list = arm.max_rad.tolist()
        self.frame_constants = FrameConstants(arm, self.accel_names, self._joint_effects, G)
        """What the compiled kinematic frames are made with (:mod:`armfusion.fusion.tracking.frame_kernels`)."""

    def set_rates(self, rates_hz: Mapping[str, float] | float) -> None:
        """Sample rates (Hz) per stream, which set each sensor's noise (datasheet rms at rate)."""
        if isinstance(rates_hz, Mapping):
            rates = {s: float(rates_hz.get(s, 100.0)) for s in self.sensor_names}
        else:
            rates = dict.fromkeys(self.sensor_names, float(rates_hz))
        self.readings.set_rates(rates)
        models = self.readings.models
        self.measurements.set_rates(models, rates)
        m = self.measurements
        self.observability.set_rates(m.accel_sigma_g, m.accel_rate_hz)
        st, nl = self.settings, len(self.link_names)
        self._link_read_horizon_s = np.maximum(st.observability_period_s,
                                               st.observability_read_periods / m.accel_rate_hz[:nl])
        self.count_limits = {s: (models[s].counts_min, models[s].counts_max) for s in models}
        """Per stream, the counts' range (a sample at either end is saturated)."""
        self._gyro_newer_weight = gyro_newer_weight(models[GYRO].delay_s, rates[GYRO]) \
            if GYRO in models else 0.5

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
        :func:`armfusion.fusion.tracking.start.imu_still_from_recording`) gives the gyro bias, heading and
        field reference.
        """
        st, L, n = self.settings, self.layout, self.arm.n_joints
        if len(startup.joints) != n:
            raise ValueError(f"startup result has {len(startup.joints)} joints; arm {self.arm.name!r} "
                             f"has {n}")
        imu = imu or ImuStill(np.zeros(3), 0.5 * DEG, None, None, None)
        prior = self.arm.ready_pose_rad if prior_q_rad is None else np.asarray(prior_q_rad, float)
        self._x0, self._P0, self._q_startup = initial_state(
            startup, imu, L, st, prior, calibrated.imu_bias_prior_var(
                self.arm, self.correction, self.R_0I if self._has_imu else None, startup.roll_rad,
                startup.pitch_rad), self.gyro_scale_sigma**2, prior_sigma_rad)
        fixed = self.arm.fixed_base
        if fixed is not None and fixed.roll_rad is not None:  # a bolted base's tilt, as levelled
            for i, v in ((L.roll, fixed.roll_rad), (L.pitch, fixed.pitch_rad)):
                self._x0[i] = v
                self._P0[i, :] = self._P0[:, i] = 0.0
                self._P0[i, i] = fixed.tilt_sigma_rad**2
        self.ambiguity_ = Ambiguity(startup)
        self._ukf = None  # created when the first encoder sample fixes the offsets
        self._q_enc = np.zeros(n)
        self._enc0 = None if encoder_counts is None else np.asarray(encoder_counts, float)
        if self._enc0 is not None:
            self.start_filter(self._enc0 / self.counts_per_rad)
        self._t = float(t_s)
        self.compass = Compass(self.arm, self.model, imu.field, st, t_s, self.R_0I, self._mag_delay_s)
        self.enc_rates = CausalDifferentiator(n, st.encoder_window, st.encoder_order)
        self.gyro_rates = CausalDifferentiator(3, st.gyro_window, st.gyro_order)
        self._omega = None  # last gyro, base axes, rad/s
        self.health = SensorHealth(self.sensor_names, len(self.accel_streams), st)
        self.slips = SlipDetector(st, L, self.sensor_names, len(self.link_names), len(self.accel_streams),
                                  self._sees, t_s)
        self.alarm = ModelChangeAlarm(self.link_names, MAG if self._has_imu else None, t_s,
                                      self._unmodelled_g[:len(self.link_names)], self._sees)
        self.observability.reset()
        if prior_q_rad is None:  # no saved pose: an unread joint may be anywhere in its limits
            # and one the startup read only poorly (ill_conditioned) counts as read once this
            # filter's own test says gravity sees it: on a moving start a vertical shaft's
            # centripetal acceleration, taken for gravity, gave it a number 56° off at a
            # sigma of 10° (a simulated rig at 300 °/s), which the gimbal lock then held
            poorly = np.array([j.flag == "ill_conditioned" for j in startup.joints], dtype=bool)
            unread = (~read_by_startup(startup) | poorly) & ~self.ambiguity_.joints
            self.observability.set_unread(np.where(unread, limits_cover_var(
                self._q_startup, self.arm.min_rad, self.arm.max_rad), 0.0))
        imu_model = self.readings.models.get(IMU_ACC)
        imu_noise_g = (0.0 if imu_model is None else
                       float(np.max(np.asarray(imu_model.noise_counts_rms) / np.abs(imu_model.gain))))
        self.still = StillDetector(st, L, t_s, imu_noise_g)
        # until the first update says more, each joint as the startup left it (a joint it
        # could not read is not "ok" for the first instants)
        self._flags = np.array([FLAG_CODE.get(j.flag, F_CONVERGING) for j in startup.joints], dtype=np.int8)
        self._named = (None, None, (), ())  # (status codes, flags, their names): see estimate
        self._combos = (None, -np.inf, (), None, None)  # see combinations_now
        self._obs_used_key = None
        self._obs_t = -np.inf
        self._link_read_t = np.full(len(self.link_names), -np.inf)  # each one's last accepted sample
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

    def _imu_up(self, x: np.ndarray) -> np.ndarray | None:
        """Up in base axes as the base IMU's accelerometer alone reads it: its average over
        ``still_tau_s`` (:class:`armfusion.fusion.tracking.process.StillDetector`), the filter's estimate
        of its bias removed, turned into base axes; None without an IMU reading yet. A
        shaking frame's acceleration averages out of it; the link accelerometers do not pull
        it (see :meth:`armfusion.fusion.tracking.observability.Observability.update`)."""
        mean = self.still.mean if self._has_imu else None
        if mean is None:
            return None
        f = self.R_0I @ (np.asarray(mean, float) - x[self.layout.imu_bias])
        norm = float(np.linalg.norm(f))
        return f / norm if norm > 0.5 else None

    def _check(self) -> None:
        if self._t is None:
            raise NotInitialisedError("the tracker is not initialised: call initialise(startup, t) "
                                      "with a startup calibration first")

    def _check_filter(self) -> None:
        self._check()
        if self._ukf is None:
            raise NotInitialisedError("no encoder sample yet: the first one fixes the offsets")

    @property
    def initialised(self) -> bool:
        return self._t is not None

    @property
    def t_s(self) -> float | None:
        return self._t

    @property
    def filter_started(self) -> bool:
        """Whether the filter runs (the first encoder sample has fixed the offsets)."""
        return self._ukf is not None

    @property
    def mean(self) -> np.ndarray:
        """The filter's mean itself, not a copy (:attr:`x` is one): for reading at once
        (:attr:`armfusion.fusion.tracking.ukf.BatchedUKF.mean`)."""
        return self._ukf.mean

    @property
    def covariance(self) -> np.ndarray:
        """The filter's covariance itself, not a copy (:attr:`P` is one); as :attr:`mean`."""
        return self._ukf.covariance

    @property
    def q_enc(self) -> np.ndarray:
        """The encoders' angles at the last fused instant (rad) itself, not a copy
        (:meth:`q_enc_now` is one): replaced at every instant, never written into."""
        return self._q_enc

    @property
    def joint_flag_codes(self) -> np.ndarray:
        """The joints' flags (codes of :data:`armfusion.fusion.tracking.settings.JOINT_FLAGS`) as last
        worked out: replaced when they are, never written into (a reader may keep it and
        compare by identity)."""
        return self._flags

    @property
    def last_gyro_B(self) -> np.ndarray | None:
        """The gyro's last reading, base axes (rad/s); None before any."""
        return self._omega

    @last_gyro_B.setter
    def last_gyro_B(self, w: np.ndarray | None) -> None:
        """Prime it (a start from a recording's still window, before the first step)."""
        self._omega = None if w is None else np.asarray(w, dtype=float)

    @property
    def x(self) -> np.ndarray:
        """The filter's state (read-only copy; names in :attr:`state_names`)."""
        self._check_filter()
        return self._ukf.x

    @property
    def P(self) -> np.ndarray:
        self._check_filter()
        return self._ukf.P

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
        motion averages, the compass's averaged reading, then the update (:meth:`_fuse`),
        the attitude folded back into Euler angles, the flags when due."""
        ukf = self._ukf
        self._q_enc = q_enc
        dt = t - self._t
        anchor = None
        st_any = self.settings.base_turns_about_any
        if dt > 0:
            w0 = self._omega if self._omega is not None else gyro
            k = self._gyro_newer_weight  # the interval's rate from its two samples (gyro_newer_weight)
            w = None if w0 is None else (w0 if gyro is None else (1.0 - k) * w0 + k * gyro)
            rate_sq = 0.0
            if w is not None and st_any:  # the gyro's scale error turns the tilt by σ_s |ω|
                om = self.process.rate(w, ukf.mean)
                rate_sq = float(om @ om)
            Q = self.process.Q(dt, w is not None, self.still.still, rate_sq)
            ukf.predict(self.process.fx_tangent, Q, dt=dt, w=w)
            # the attitude is now the propagated central point's plus a tangent vector
            Y = ukf.propagated_points
            anchor = Y[0, self.attitude_index].copy() if Y is not None else None
            if w is not None and self.compass.averaging:  # (the rate is needed mid-period only)
                self.compass.turn(self.process.rate(w, ukf.mean), dt)
        if gyro is not None:
            self._omega = gyro
        self._t = t
        if frame is None:
            acc = None
        imu_f = None
        if acc is not None and self._has_imu and acc.selection.imu_pos >= 0:
            imu_f = acc.g[acc.selection.imu_pos]
        self.still.update(dt, gyro, imu_f, ukf.mean.tolist())
        if self.intensity is not None and imu_f is not None:
            self.intensity.update(dt, imu_f)
        if mag is not None:
            self.health.heard(self.sensor_index[MAG], t)
            m_B, mag = mag.field_B_ut, None
            if self.compass.listening and frame is not None:
                om = (self.process.rate(self._omega, ukf.mean)
                      if self.compass.delay_s and self._omega is not None else None)
                mag = self.compass.average(t, m_B, om)
            if mag is not None:
                x, L = ukf.mean, self.layout
                mag = self.compass.prepare(t, mag[0], mag[1], float(x[L.roll]), float(x[L.pitch]),
                                           x[L.offset] + q_enc)
        if acc is not None or mag is not None:
            self._fuse(t, acc, mag, frame)
        if dt > 0 and anchor is not None:  # back to Euler angles about the anchor (a reset)
            ukf.recentre(self.process.fold_attitude(ukf.mean, anchor))
        if t - self._flags_t >= self.settings.observability_period_s or self.health.changed:
            self._update_flags(t)

    def _fuse(self, t: float, acc: AccelReadings | None, mag: tuple | None, frame: Frames | None) -> None:
        """One update with every accelerometer and the magnetometer of this instant, each
        sensor gated on its own NIS: stack and innovate (:meth:`_innovate`), gate
        (:meth:`_gate`: the base setting off; then health, slips, the alarm and the
        observability read the accelerometers' rows, :meth:`_listen_accels`, and the compass
        its row, :meth:`_listen_compass`, each deciding what is used), correct."""
        upd = self._innovate(t, acc, mag, frame)
        self._gate(upd)
        if upd.k:
            self._listen_accels(upd)
        if mag is not None:
            self._listen_compass(upd)
        self._ukf.correct(upd.inn, upd.accept, self.observability.hold, upd.mask)

    def _innovate(self, t: float, acc: AccelReadings | None, mag: tuple | None,
                  frame: Frames | None) -> UpdateResult:
        """Stack this instant's measurements with their noise (a recalibration alarm's
        widening, the compass's variance, a pivot's share) and innovate them at once."""
        st, ukf, L, ms = self.settings, self._ukf, self.layout, self.measurements
        m_B = check = None
        still = self.still.still and acc is not None and st.motion_compensation
        stack = ms.stack(acc, frame, still, mag is not None)
        var = stack.var
        k, m = len(stack.counts), len(stack.z)
        if k and self.alarm.active:  # a changed sensor is down-weighted until recalibrated
            self.alarm.widen(stack.index, var)
        if mag is not None:
            m_count, m_B, extra_var = mag
            x = ukf.mean
            check, var[-1] = self.compass.variance(m_B, up_from_tilt(x[L.roll], x[L.pitch]), m_count)
            var[-1] += extra_var
        plan = ms.plan(stack.selection.key, k, still, mag is not None)
        om = None
        if L.pivot_B is not None and k and self._omega is not None:
            # the base turns about its pivot: the origin's acceleration at every point's offset
            # (Measurements.h_all), the differentiated gyro's error times the offset as noise
            om = self.process.rate(self._omega, ukf.mean)
            var[:3 * k] += ms.pivot_variance(frame, ukf.mean[L.pivot_B], ukf.covariance[L.pivot_B, L.pivot_B])
        upd = UpdateResult(t, frame, stack, k, still, plan, (m - 1,) if mag is not None else (),
                           self.compass.heading_shift_rad() if mag is not None else 0.0, om, m_B, mag, check)
        upd.inn = inn = self._innovation(upd)
        upd.accept = inn.gate_ok.copy()
        upd.gate = inn.gate_ok.tolist()
        return upd

    def _innovation(self, upd: UpdateResult) -> Innovation:
        wz = self._prediction_weights() if self.settings.innovation_at_mean_state else None
        s = upd.stack
        return self._ukf.innovate(s.z, self._h_tangent, s.var, upd.plan, angle_rows=upd.angle_rows,
                                  z_weights=wz,
                                  frame=upd.frame, sel=s.index, m_B=upd.m_B, still=upd.still,
                                  heading_shift_rad=upd.heading_shift_rad, omega_B=upd.omega_B)

    def _gate(self, upd: UpdateResult) -> None:
        """Whether the base set off (its still rows failed, or the IMU disagrees while it
        stood): then its acceleration is freed and the update innovated again; whether it is
        calm (the slip detector listens only then)."""
        st, L, k = self.settings, self.layout, upd.k
        gate_l = upd.gate
        set_off = upd.still and not gate_l[k]
        imu_ok = True
        if k:
            imu_pos = upd.stack.selection.imu_pos
            if imu_pos >= 0:
                imu_ok = self.still.imu_agrees(upd.t, upd.inn.nis.item(imu_pos), gate_l[imu_pos])
            set_off |= self.still.still and not imu_ok
            # the slip detector listens only while the base behaves as modelled: the IMU
            # agrees and the chair is not wrenched about (a lurch is common to all sensors)
            upd.calm = (imu_ok and self.still.imu_nis < 4.5
                        and upd.frame.omega_dot_norm.item() < st.shift_max_angular_accel_rad_s2)
        if set_off:
            # the chair set off: it is no longer still (the averages will say so later), and
            # its acceleration, held near zero while it stood, must be free to follow at once
            ukf = self._ukf
            self.still.set_off()
            ukf.inflate(np.arange(L.accel.start, L.accel.stop), self.process.accel_sigma_mps2**2)
            if L.jerk_B is not None:
                ukf.inflate(np.arange(L.jerk_B.start, L.jerk_B.stop), st.base_jerk_sigma_mps3**2)
            upd.inn = inn = self._innovation(upd)
            upd.accept = inn.gate_ok.copy()
            if upd.still:
                upd.accept[k] = False
        upd.set_off = set_off

    def _listen_accels(self, upd: UpdateResult) -> None:
        """The accelerometers' rows: health's verdicts (which are used), the slip detector
        and the recalibration alarm on the residuals, the links read lately and the
        observability when they change."""
        st, ukf, L, ms, t, k = self.settings, self._ukf, self.layout, self.measurements, upd.t, upd.k
        s, inn, accept = upd.stack, upd.inn, upd.accept
        sel = s.index
        gate_l = None if upd.set_off else upd.gate
        accept[:k], u, nu, Su = self.health.accel(t, sel, s.counts, s.f_g, inn, s.var_a, s.selection.full,
                                                   gate_l, ms.rows, self._reacquire)
        if u is not None:
            calm = upd.calm and not upd.set_off
            self.slips.listen(t, u, nu, Su, calm, self._reacquire)
            self.alarm.listen(t, u, nu, Su, inn.z_pred, s.var, ms.rows, sel, calm, upd.frame,
                              ukf.mean[L.offset])
        # the link accelerometers read lately (settings.observability_read_periods)
        read_t = self._link_read_t
        for i, a in zip(sel.tolist(), accept[:k].tolist(), strict=True):
            if i < len(read_t):  # (a rejected sample leaves the set at once)
                read_t[i] = t if a else -np.inf
        used = tuple(np.flatnonzero(t - read_t <= self._link_read_horizon_s).tolist())
        if used != self._obs_used_key or t - self._obs_t >= st.observability_period_s:
            self._obs_used_key, self._obs_t = used, t
            self.observability.update(self._t, upd.frame, used, ukf.mean, ukf.covariance, self._P0,
                                      self._q_enc,
                                      self.slips.calibration, self._imu_up(ukf.mean))

    def _listen_compass(self, upd: UpdateResult) -> None:
        """The heading's row: the compass's verdict (used or not), the health's count, the
        alarm; the gain mask that keeps the heading off the tilt and the arm."""
        inn, check, t = upd.inn, upd.check, upd.t
        use = self.compass.verdict(t, bool(inn.gate_ok[-1]), check, inn.innovation[-1:], inn.S[-1:, -1:],
                                   inn.nis[-1])
        mi = self.sensor_index[MAG]
        self.health.rejecting[mi] = not use
        self.health.counts[mi, C_USED if use else C_REJECTED] += upd.mag[0]
        upd.accept[-1] = use
        self.alarm.compass(t, check.disturbed, check.magnitude_error_ut)
        upd.mask = self.measurements.heading_mask(len(upd.stack.z))

    def _prediction_weights(self) -> np.ndarray | None:
        """The sigma points' weights in the prediction an update's innovation is taken
        against: the unscented mean's (None) unless a joint is gimbal-locked (held) and
        known only widely (30 deg at startup: ``Observability.held_wide``). Then each pair of
        points keeps its weight only for the share of its offsets' displacement off those
        joints: the update does not correct along them, and the points' spread there
        (±65 deg) would shrink the predicted specific force that the joint turns (see
        ``TrackerSettings.innovation_at_mean_state``). None also when the step's points are
        not drawn yet."""
        U = self.observability.held_wide
        ukf = self._ukf
        X = ukf.propagated_points
        if U is None or X is None:
            return None
        n, ns = self.arm.n_joints, ukf.mean.shape[0]
        D = X[1:1 + ns, :n] - X[0, :n]  # each pair's displacement of the offsets
        d2 = np.einsum("ij,ij->i", D, D)
        along = np.einsum("ij,ij->i", D @ U, D @ U)
        keep = 1.0 - np.divide(along, d2, out=np.zeros(ns), where=d2 > 0.0)
        w = ukf.mean_weights.copy()
        w[1:1 + ns] *= keep
        w[1 + ns:] *= keep
        w[0] = 1.0 - w[1:].sum()
        return w

    def _h_tangent(self, X: np.ndarray, **kw) -> np.ndarray:
        """Every measurement at sigma points whose attitude is in the filter's tangent space
        (:meth:`armfusion.fusion.tracking.process.ProcessModel.fx_tangent`), through the Euler-angle
        models (:meth:`armfusion.fusion.tracking.measurement.Measurements.h_all`)."""
        return self.measurements.h_all(self.process.euler_points(X), **kw)

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
            t, codes, self._links_list, self._ukf.covariance, self._q_enc + self._ukf.mean[:n],
            self.ambiguity_.joints,
            self.slips.reacquiring_until, self._min_list, self._max_list)

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
            ambiguous=self.ambiguity_.snapshot())

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

    def snapshot(self) -> dict:
        """The tracker's state as a JSON-ready dict (:meth:`TrackerState.to_dict`): enough to
        resume after a restart of the process without a new startup calibration, provided the
        encoders kept counting."""
        return self.state().to_dict(self.arm.name, self.state_names)

    def restore(self, snap: Mapping) -> None:
        """Resume from :meth:`snapshot` (replaces :meth:`initialise`)."""
        self.resume(TrackerState.from_dict(snap, self.arm.name, self.state_names))

    # -- results (by value) ------------------------------------------------------------------
    def ambiguity(self) -> dict[str, tuple[float, ...]]:
        """Per joint the startup left ``ambiguous``: its candidate angles now (the startup's,
        moved by what the encoders counted since), rad. Empty once every branch is known."""
        return self.ambiguity_.at(self.arm.joint_names, self._q_enc)

    def q_enc_now(self) -> np.ndarray:
        """The encoders' angles (counts / counts per rad) at the last fused instant."""
        return self._q_enc.copy()

    def combination_vectors(self) -> tuple[tuple[Combination, ...], np.ndarray, np.ndarray]:
        """What gravity reads where it cannot read single joints, now: the combinations of
        the joints not ``ok`` (nor ``ambiguous``, nor flagged as read by no sensor:
        ``gimbal_lock``, ``unobserved``) and of the base's roll and pitch (where
        their sigma is above ``sigma_limit_deg``) that the filter knows within
        ``mean_state_held_sigma_deg`` and better than any of their terms
        (:func:`armfusion.fusion.startup.combinations.observable_combinations`), from the joint and
        tilt block of its covariance with the calibration's own share (the consider
        sensitivity and an unread joint's cover: what the reported sigmas hold). Returns the
        combinations, their coefficients ``(k, n + 2)`` over the joints, roll and pitch,
        and the state indices of those ``(n + 2,)``."""
        self._check_filter()
        L, n, st = self.layout, self.arm.n_joints, self.settings
        ix = np.r_[np.arange(n), L.roll, L.pitch]
        values, P = self._joint_tilt_block(ix)
        flags = self._flags
        cand = np.r_[(flags != 0) & ~np.isin(flags, (F_AMBIGUOUS, F_GIMBAL, F_UNOBSERVED)),
                     np.sqrt(np.clip(np.diag(P)[n:], 0.0, None)) > st.sigma_limit_deg * DEG]
        names = (*self.arm.joint_names, *TILT_NAMES)
        found = observable_combinations(P, values, names, st.mean_state_held_sigma_deg * DEG, cand)
        C = np.array([c.vector(names) for c in found]).reshape(len(found), n + 2)
        return found, C, ix

    def _joint_tilt_block(self, ix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joints' angles (as reported), roll and pitch, and their covariance with the
        calibration's own share (see :meth:`combination_vectors`)."""
        n, L = self.arm.n_joints, self.layout
        P = self._ukf.covariance[np.ix_(ix, ix)].copy()
        obs = self.observability
        P[:n, :n] += obs.consider @ obs.consider.T + np.diag(obs.unread_var)
        P[n, n] += obs.tilt_var[0]  # (a bolted base's floor in its tilt)
        P[n + 1, n + 1] += obs.tilt_var[1]
        x = self._ukf.x
        values = np.r_[self.arm.angles_in_range(self._q_enc + x[:n], self._q_enc), x[L.roll], x[L.pitch]]
        return values, P

    def combination_values(self, C: np.ndarray, ix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The combinations of coefficients ``C`` (from :meth:`combination_vectors`) now: their
        values and sigmas (rad)."""
        values, P = self._joint_tilt_block(ix)
        return C @ values, np.sqrt(np.clip(np.einsum("ki,ij,kj->k", C, P, C), 0.0, None))

    def combinations_now(self) -> tuple[Combination, ...]:
        """:meth:`combination_vectors`' combinations at the last fused instant: which ones,
        found again when the flags change and every ``observability_window_s``; their values
        and sigmas now (an estimate a sample carries no eigen-decomposition)."""
        flags, t_found, found, C, ix = self._combos
        if self._flags is not flags or self._t - t_found >= self.settings.observability_window_s:
            found, C, ix = self.combination_vectors()
            self._combos = (self._flags, self._t, found, C, ix)
            return found
        if not found:
            return ()
        v, sg = self.combination_values(C, ix)
        return tuple(replace(c, angle_rad=float(a), sigma_rad=float(b))
                     for c, a, b in zip(found, v, sg, strict=True))

    @property
    def estimate(self) -> Estimate:
        """The estimate at the last fused instant."""
        self._check_filter()
        L, n = self.layout, self.arm.n_joints
        x, sig = self._ukf.x, self._ukf.sigma.copy()
        sig[:n] = np.sqrt(sig[:n] ** 2 + self.observability.sys_var)  # the calibration's own uncertainty
        ai = self.attitude_index
        amb = self.ambiguity_
        if amb.joints.any():  # the sigma of a joint with rival branches covers them
            sig[:n] = np.maximum(sig[:n], amb.half_gap)
        named, codes = self._named, self.health.status_codes
        if named[0] is not codes or named[1] is not self._flags:
            # (both arrays are replaced, never written in place, when the flags are updated)
            self._named = named = (codes, self._flags, self.health.named_statuses(),
                                   tuple(JOINT_FLAGS[f] for f in self._flags.tolist()))
        return Estimate(
            t_s=self._t, q_rad=_ro(self.arm.angles_in_range(self._q_enc + x[:n], self._q_enc)),
            sigma_rad=_ro(sig[:n]),
            flags=named[3],
            roll_rad=float(x[L.roll]), pitch_rad=float(x[L.pitch]), yaw_rad=float(x[L.yaw]),
            attitude_sigma_rad=_ro(attitude_sigma_rad(x[ai], self._ukf.covariance[np.ix_(ai, ai)]
                                                      + np.diag(np.r_[self.observability.tilt_var, 0.0]),
                                                      self.compass.heading_floor_var)),
            gyro_bias_rad_s=_ro(x[L.bias]),
            axis_to_vertical_deg=_ro(self.observability.axis_deg), sensors=named[2],
            magnetic_disturbance=self.compass.flags[0], magnetic_recovery=self.compass.flags[1],
            joint_names=self.arm.joint_names, heading_status=HEADING_STATUS[self.heading_status_code()],
            true_north=self.arm.magnetic_declination_deg is not None,
            combinations=self.combinations_now(),
        )

    def gyro_scale(self) -> dict | None:
        """The gyro's scale error about the base's z axis as the filter holds it (fraction: it
        reads ``1 + value`` times the true rate) with its sigma and the config's (the prior),
        beyond what the config's own ``gyro_scale`` undoes; None where it is not a state (the
        config knows it exactly, or there is no gyro)."""
        self._check()
        L = self.layout
        if L.scale < 0 or self._ukf is None:
            return None
        x, P = self._ukf.mean, self._ukf.covariance
        return {"value": float(x[L.scale]), "sigma": float(np.sqrt(P[L.scale, L.scale])),
                "prior_sigma": self.gyro_scale_sigma}

    def heading_status_code(self) -> int:
        """The heading's status (an index into :data:`~armfusion.fusion.tracking.estimate.HEADING_STATUS`):
        the compass's, or ``gyro_only`` where the magnetometer has gone quiet (stale, dead or
        absent) since it last said otherwise."""
        code = STATUS_CODE[self.compass.status]
        mi = self.sensor_index.get(MAG)
        if mi is not None and code != STATUS_CODE[CALIBRATING] and \
                self.health.status_codes[mi] in (S_STALE, S_DEAD, S_ABSENT):
            return STATUS_CODE[GYRO_ONLY]
        return code

    def counters(self) -> dict[str, dict[str, int]]:
        """Per sensor: samples, used, rejected, nan, saturated, implausible, stuck,
        out_of_order, reacquisitions."""
        self._check()
        return self.health.counters()

    def sensor_warnings(self) -> list[str]:
        """The accelerometers rejected (or left out as implausible) more often than
        ``settings.warn_rejected_share`` of their samples so far, each with why
        (:func:`armfusion.fusion.tracking.health.sensor_warnings`)."""
        self._check()
        floors = dict(zip(self.accel_streams, self._unmodelled_g.tolist(), strict=True))
        if IMU_ACC in floors:
            floors[IMU_ACC] = self.arm.calibration.imu_accel_floor_g
        return sensor_warnings(self.counters(), self.nis_stats(), floors,
                               dict(self.arm.calibration.floors_by_default), self.settings)

    def innovations(self, sensor: str) -> InnovationLog:
        """The innovations kept for ``sensor`` (a link accelerometer, ``imu_acc``, ``imu_mag``):
        every one that was tested against the gate, accepted or not."""
        self._check()
        if sensor == MAG and self._has_imu:
            return self.compass.ring.log(sensor)
        if sensor not in self.accel_streams:
            kept = list(self.accel_streams) + ([MAG] if self._has_imu else [])
            raise KeyError(f"no innovations for {sensor!r}; kept for {kept}")
        return self.health.ring.log(sensor)

    def nis_stats(self) -> dict[str, tuple[float, int, int]]:
        """Per sensor: (mean NIS, count, degrees of freedom) over its healthy samples."""
        self._check()
        out = self.health.nis_stats()
        if self._has_imu:
            m = self.compass.ring
            out[MAG] = (m.nis_sum / m.nis_count if m.nis_count else float("nan"), m.nis_count, 1)
        return out


def _ro(a) -> np.ndarray:
    v = np.array(a, dtype=float)
    v.setflags(write=False)
    return v
