"""What a tracker is made of for an arm (:class:`TrackerSetup`, which
:class:`armfusion.fusion.tracking.filter.Tracker` extends with its lifecycle): the config's model and
corrections, the settings for the arm's base, the state's layout, the sensors' names, links,
delays and noise at their rates, and the parts that do not change over a start (the
measurements, the observability, the process model, the sigma points, the kinematic frames'
constants)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.startup.solve import StartupResult
from armfusion.fusion.tracking import calibrated, fixed_base
from armfusion.fusion.tracking.alarm import ModelChangeAlarm
from armfusion.fusion.tracking.compass import Compass
from armfusion.fusion.tracking.consider import ConsiderColumns
from armfusion.fusion.tracking.differentiator import CausalDifferentiator
from armfusion.fusion.tracking.frame_kernels import FrameConstants
from armfusion.fusion.tracking.health import SensorHealth
from armfusion.fusion.tracking.initial import (
    Ambiguity,
    ImuStill,
    initial_state,
    limits_cover_var,
    read_by_startup,
)
from armfusion.fusion.tracking.measurement import Measurements
from armfusion.fusion.tracking.observability import LinkSensors, Observability
from armfusion.fusion.tracking.process import MotionIntensity, ProcessModel, StillDetector, gyro_newer_weight
from armfusion.fusion.tracking.settings import (
    ENC,
    F_CONVERGING,
    FLAG_CODE,
    GYRO,
    IMU_ACC,
    MAG,
    G,
    StateLayout,
    TrackerSettings,
)
from armfusion.fusion.tracking.slips import SlipDetector
from armfusion.fusion.tracking.ukf import SigmaPoints
from armfusion.models.arm import ArmModel


@dataclass(frozen=True, slots=True)
class StartParts:
    """What a start (:meth:`TrackerSetup.start_parts`) gives a tracker: its first state and
    the parts that begin afresh."""

    x0: np.ndarray
    P0: np.ndarray
    q_startup: np.ndarray
    """The startup's joint angles (a joint it could not read: the prior's), rad."""
    ambiguity: Ambiguity
    compass: Compass
    enc_rates: CausalDifferentiator
    gyro_rates: CausalDifferentiator
    health: SensorHealth
    slips: SlipDetector
    alarm: ModelChangeAlarm
    still: StillDetector
    unread_var: np.ndarray | None
    """Per joint, the variance that covers its limits where the startup did not read it
    (None where a saved pose stands in for it)."""
    flags: np.ndarray
    """The joints' flags as the startup left them (a joint it could not read: ``converging``)."""


class TrackerSetup:
    """A tracker's constants and fixed parts for an arm (see the module's docstring)."""

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
        # base that turns about every axis, every axis's scale error as the attitude's noise instead
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
        stamps = calibrated.stamp_offsets(model, self.accel_names, delays_s[:-1])
        self._mag_delay_s = float(delays_s[-1]) if self._has_imu else 0.0
        unmodelled_g = calibrated.accel_floors_g(arm, self.link_names, self._has_imu)
        self._unmodelled_g = unmodelled_g
        self._fast_error_g = calibrated.accel_fast_errors_g(arm, self.link_names, self._has_imu)
        self._sees = links[:, None] > np.arange(n)[None, :]  # (S, n): sensor s sees joint j
        self._make_parts(links, unmodelled_g, stamps, scale_sigma)
        self.set_rates(rates_hz)
        self._points = SigmaPoints(L.size, st.alpha, st.beta, st.kappa)
        self.attitude_index = np.array([L.roll, L.pitch, L.yaw])
        """The attitude's (roll, pitch, yaw) indices in the state."""
        self.nees_index = np.r_[np.arange(n), L.roll, L.pitch, L.yaw]
        """The joints' and the attitude's indices in the state (what a NEES is taken over)."""

    def _make_parts(self, links: np.ndarray, unmodelled_g: np.ndarray, stamps: calibrated.StampOffsets,
                    scale_sigma: np.ndarray) -> None:
        """The stacked measurement, the observability, the process model and the motion's
        intensity, the kinematic frames' constants, for the sensors named."""
        st, L, arm, correction = self.settings, self.layout, self.arm, self.correction
        self._min_list = arm.min_rad.tolist()
        self._max_list = arm.max_rad.tolist()
        self.frame_constants = FrameConstants(arm, self.accel_names, self._joint_effects, G)
        """What the compiled kinematic frames are made with (:mod:`armfusion.fusion.tracking.frame_kernels`)."""
        # a reading's noise holds both the error that stays and the fast one; the consider
        # sensitivity (Observability) carries only the one that stays
        self.measurements = Measurements(st, L, self.sensor_names, self.accel_streams, links,
                                         self.sensor_index.get(IMU_ACC, -1),
                                         np.hypot(unmodelled_g, self._fast_error_g), stamps)
        sensors = LinkSensors(self.link_names, self._links_list, self._sees, self._min_list, self._max_list)
        columns = ConsiderColumns(self.link_names, self.accel_streams, correction,
                                  calibrated.spread_maps(correction), unmodelled_g, scale_sigma,
                                  self.R_0I if self._has_imu else None)
        self.observability = Observability(st, L, sensors, columns)
        # the tilt's floor, which no averaging lowers: every accelerometer that reads it. The
        # IMU's lasting error is a state of the filter (its prior the config's floor): a base
        # that turns about any axis reveals it (gravity turns in the IMU's axes, the bias does
        # not), one that only yaws (a chair) never does, and it stays in the tilt
        imu_floor_g = ([arm.calibration.imu_accel_floor_g]
                       if self._has_imu and not st.base_turns_about_any else [])
        floors_g = np.r_[unmodelled_g[:len(self.link_names)], imu_floor_g]
        self.observability.tilt_floor_var = fixed_base.floor_var_rad2(floors_g)
        self.observability.tilt_start_holds = arm.fixed_base is not None
        self.process = ProcessModel(st, L, arm.joint_names)
        if st.base_turns_about_any:
            self.process.set_scale_noise(self.gyro_scale_sigma)
        # a base whose speed is bounded (a hand): how vigorously it moves, from the IMU
        self.intensity = MotionIntensity(st) if L.vel is not None and self._has_imu else None
        self.process.intensity = self.intensity

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

    def start_parts(self, startup: StartupResult, imu: ImuStill, t_s: float, prior_q_rad: np.ndarray | None,
                    prior_sigma_rad: np.ndarray | None) -> StartParts:
        """A start's first state and fresh parts (see
        :meth:`armfusion.fusion.tracking.filter.Tracker.initialise` for the arguments)."""
        st, L, n, arm = self.settings, self.layout, self.arm.n_joints, self.arm
        if len(startup.joints) != n:
            raise ValueError(f"startup result has {len(startup.joints)} joints; arm {arm.name!r} "
                             f"has {n}")
        prior = arm.ready_pose_rad if prior_q_rad is None else np.asarray(prior_q_rad, float)
        x0, P0, q_startup = initial_state(
            startup, imu, L, st, prior, calibrated.imu_bias_prior_var(
                arm, self.correction, self.R_0I if self._has_imu else None, startup.roll_rad,
                startup.pitch_rad), self.gyro_scale_sigma**2, prior_sigma_rad)
        fixed = arm.fixed_base
        if fixed is not None and fixed.roll_rad is not None:  # a bolted base's tilt, as levelled
            for i, v in ((L.roll, fixed.roll_rad), (L.pitch, fixed.pitch_rad)):
                x0[i] = v
                P0[i, :] = P0[:, i] = 0.0
                P0[i, i] = fixed.tilt_sigma_rad**2
        ambiguity = Ambiguity(startup)
        unread_var = None
        if prior_q_rad is None:  # no saved pose: an unread joint may be anywhere in its limits
            # and one the startup read only poorly (ill_conditioned) counts as read once this
            # filter's own test says gravity sees it: on a moving start a vertical shaft's
            # centripetal acceleration, taken for gravity, gave it a number 56° off at a
            # sigma of 10° (a simulated rig at 300 °/s), which the gimbal lock then held
            poorly = np.array([j.flag == "ill_conditioned" for j in startup.joints], dtype=bool)
            unread = (~read_by_startup(startup) | poorly) & ~ambiguity.joints
            unread_var = np.where(unread, limits_cover_var(q_startup, arm.min_rad, arm.max_rad), 0.0)
        imu_model = self.readings.models.get(IMU_ACC)
        imu_noise_g = (0.0 if imu_model is None else
                       float(np.max(np.asarray(imu_model.noise_counts_rms) / np.abs(imu_model.gain))))
        nl, na = len(self.link_names), len(self.accel_streams)
        return StartParts(
            x0, P0, q_startup, ambiguity,
            Compass(arm, self.model, imu.field, st, t_s, self.R_0I, self._mag_delay_s),
            CausalDifferentiator(n, st.encoder_window, st.encoder_order),
            CausalDifferentiator(3, st.gyro_window, st.gyro_order),
            SensorHealth(self.sensor_names, na, st),
            SlipDetector(st, L, self.sensor_names, nl, na, self._sees, t_s),
            ModelChangeAlarm(self.link_names, MAG if self._has_imu else None, t_s,
                             self._unmodelled_g[:nl], self._sees),
            StillDetector(st, L, t_s, imu_noise_g), unread_var,
            # until the first update says more, each joint as the startup left it (a joint it
            # could not read is not "ok" for the first instants)
            np.array([FLAG_CODE.get(j.flag, F_CONVERGING) for j in startup.joints], dtype=np.int8))
