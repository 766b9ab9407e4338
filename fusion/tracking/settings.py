"""The tracker's vocabulary: its settings (:class:`TrackerSettings`, units in the names),
the joint flags and sensor statuses it reports, its per-sensor counters, the stream names
it takes, and the layout of its state vector (:class:`StateLayout`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from armfusion.fusion.tracking.heading import HeadingSettings
from armfusion.models.rotations import GRAVITY_MPS2
from armfusion.models.sensor_models import MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ

G = GRAVITY_MPS2

JOINT_FLAGS: tuple[str, ...] = (
    "ok", "converging", "out_of_limits", "reacquiring", "ill_conditioned", "unobserved", "gimbal_lock",
    "ambiguous",
)
"""Per-joint flags, from least to most severe (a joint shows its most severe one):

- ``ok``: observed, sigma below ``sigma_limit_deg``;
- ``converging``: observed, but sigma still above the limit (e.g. a joint that was blind
  at startup and is being read for the first time);
- ``out_of_limits``: the estimate is outside the joint's limits (plus a margin);
- ``reacquiring``: a sensor that sees this joint disagreed for longer than a bump
  lasts (an encoder slip?); its offset was widened and is being read again;
- ``ill_conditioned``: the sensors read this joint only poorly, or only together with
  another joint; the unreadable direction is held (no correction flows through it);
- ``unobserved``: no working accelerometer sees this joint (dead, stuck or stale);
- ``gimbal_lock``: the joint's axis is within ``gimbal_lock_deg`` of vertical: gravity
  cannot read it; it is held, and its sigma grows with the offset random walk;
- ``ambiguous``: the startup found two or more branches that fit the still data equally
  (and no prior that fits chose): the joint is not tracked as known until a still window
  after a move tells them apart (:meth:`Tracker.ambiguity`: the candidates, moved by what
  the encoders counted since); its sigma covers them.
"""
SENSOR_STATUS: tuple[str, ...] = ("ok", "rejecting", "stale", "stuck", "dead", "absent")
"""Per-sensor status: ``ok``; ``rejecting`` (its last sample failed the chi-square gate);
``stale`` (no sample for ``stale_after_s``); ``stuck`` (identical counts while the
prediction moved); ``dead`` (implausible readings for ``dead_after_s``); ``absent``
(never seen)."""
FLAG_CODE = {f: i for i, f in enumerate(JOINT_FLAGS)}
STATUS_CODE = {s: i for i, s in enumerate(SENSOR_STATUS)}
# the codes of the flags and statuses above ``ok``
F_CONVERGING, F_OUT, F_REACQ, F_ILL, F_UNOBSERVED, F_GIMBAL, F_AMBIGUOUS = range(1, 8)
S_REJECTING, S_STALE, S_STUCK, S_DEAD, S_ABSENT = range(1, 6)
COUNTERS: tuple[str, ...] = (
    "samples", "used", "rejected", "nan", "saturated", "implausible", "stuck", "out_of_order",
    "reacquisitions",
)
(C_SAMPLES, C_USED, C_REJECTED, C_NAN, C_SATURATED, C_IMPLAUSIBLE, C_STUCK, C_OUT_OF_ORDER,
 C_REACQUISITIONS) = range(len(COUNTERS))

ENC = "enc"
GYRO = "imu_gyro"
IMU_ACC = "imu_acc"
MAG = "imu_mag"


@dataclass(frozen=True)
class TrackerSettings:
    """Everything tunable, with units in the names; the defaults suit the WMRA's sensors."""

    # process noise
    offset_random_walk_deg_per_sqrt_s: float = 0.0035
    """Each encoder offset's random walk: lets a slip be absorbed in a few seconds while
    keeping the steady-state sigma near 0.01 deg."""
    offset_random_walk_by_joint_deg_per_sqrt_s: tuple[tuple[str, float], ...] = ()
    """``(joint, deg/√s)`` pairs: a joint whose relative angle drifts more than a slipping
    encoder's (its encoder withheld and its angle integrated from the gyros on either side,
    :mod:`armfusion.fusion.tracking.gyro_encoder`) takes this random walk instead."""
    gyro_noise_dps_per_sqrt_hz: float = MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ
    gyro_bias_random_walk_dps_per_sqrt_s: float = 0.0005
    gyro_scale_sigma: float = 0.015
    """The gyro's scale error about the vertical, 1 sigma (fraction), where the config holds
    no ``gyro_scale`` and says its IMU is not exact: the MPU-9150's ±3 % sensitivity tolerance."""
    gyro_scale_random_walk_per_sqrt_s: float = 2e-5
    """Where the gyro's scale about the vertical is a state (its sigma above zero), how it
    drifts (fraction per √s, temperature): 0.1 % in 40 min."""
    imu_accel_bias_random_walk_g_per_sqrt_s: float = 2e-6
    """The IMU accelerometer's residual error drifts slowly (temperature): 0.1 mg in 40 min."""
    base_accel_sigma_mps2: float = 0.7
    """Steady-state spread of the chair's own acceleration (driving, turning, ramps); a
    config's ``base_motion`` replaces it (:meth:`for_base`)."""
    base_accel_tau_s: float = 5.0
    """Its correlation time: how long an acceleration typically lasts."""
    base_jerk_sigma_mps3: float = 0.0
    """A chair's acceleration changes smoothly (its motors' torque, its controller's ramps:
    a turn's or a start's onset takes about a second): where above zero (and the base's
    speed is not bounded), the state holds the acceleration's rate of change, its jerk, a
    Gauss-Markov process of this spread and correlation time ``base_jerk_tau_s``, and the
    acceleration changes by it (``a' = -a/τ_a + j``). Without it the acceleration's own
    white noise carries every change: the filter lags each onset by a step, and the IMU's
    innovations, averaged over 0.5 s, alternate in sign through each onset (r -0.4 from one
    block to the next on a chair turning back and forth). 3 m/s³ made 36 of 37 clean drives
    white (35 without), but on ``tools/bench_track_realistic.py`` j1-j3 came out 0.002-0.06°
    worse: off (zero) by default. Those onsets were the arm base's swing about the chair's
    turning centre in turns on the spot, which a config's ``chair:`` block now has the
    frame predict from the gyro (45 of 45 white without this state); 3 m/s³ with 0.3 s and
    ``base_accel_tau_s`` 5 s means an acceleration spread of 3.6 m/s², five times a chair's
    (docs/tracking.md, *Limits*)."""
    base_jerk_tau_s: float = 0.3
    """How long a jerk lasts: about half an onset (the acceleration rises, then levels)."""
    base_accel_direct_share: float = 0.05
    """With the jerk state, the share of ``base_accel_sigma_mps2`` left as the acceleration's
    own white noise (bumps): most of its change comes through the jerk."""
    base_speed_sigma_mps: float | None = None
    """The spread of the base's speed, where it is bounded (a hand carrying a sensor): the
    state then holds the base's velocity too, and its acceleration is that velocity's
    derivative (:func:`armfusion.fusion.tracking.process_kernels._velocity_step`), so it averages to
    zero over time however large it is. None (a chair, which may cruise at any speed for
    minutes): no velocity, the acceleration alone (a config's ``base_motion.speed_sigma_mps``
    sets it, :meth:`for_base`)."""
    base_pivot_sigma_m: float | None = None
    """Where the base turns about a point off its origin (a hand turning a sensor it holds
    about the wrist or the elbow), the prior spread of the origin's offset from that point,
    m per base axis: the state then holds the offset ``r`` (base axes, constant in the base,
    a slow random walk ``base_pivot_random_walk_m_per_sqrt_s``), the acceleration state is the
    pivot's, and the origin's is the pivot's plus ``ω̇ × r + ω × (ω × r)`` (the gyro's rate and
    its causal derivative): a sensor swung at 400 °/s on a 15 cm lever is accelerated by
    7 m/s² towards the pivot, in the base's own axes, which a zero-mean acceleration cannot
    explain (:meth:`armfusion.fusion.tracking.measurement.Measurements.h_all`). None (a chair: its
    turning centre is the config's ``chair:`` block instead, its swing predicted from the gyro;
    docs/tracking.md, step 3): no such state (a config's
    ``base_motion.pivot_sigma_m`` sets it, :meth:`for_base`)."""
    base_turns_about_any: bool = False
    """The base turns about every axis (a hand turning a sensor it holds; a config's
    ``base_motion.turns_about: any``), not about its vertical only (a chair): the gyro's scale
    error about the base's z axis is then no state (it describes a chair's turns only), and
    the scale-and-axes error of every axis (:func:`armfusion.fusion.tracking.calibrated.heading_scale_sigma`)
    turns the tilt by ``σ_s |ω|``: roll and pitch take that as process noise over the turn's
    correlation time (:meth:`armfusion.fusion.tracking.process.ProcessModel.Q`)."""
    base_intensity_range: tuple[float, float] = (1.0 / 16.0, 9.0)
    """Where the base's speed is bounded (a hand), the range of its motion's intensity
    (:class:`armfusion.fusion.tracking.process.MotionIntensity`): its acceleration spread between 1/16
    and 9 times the config's ``accel_sigma_mps2`` (0.19-27 m/s² for a hand's 3)."""
    base_pivot_random_walk_m_per_sqrt_s: float = 0.01
    """How the pivot's offset drifts where it is a state: a hand changes its grip, or turns
    from the wrist to the elbow, over seconds: 1 cm/√s (10 cm in 100 s)."""
    still_gyro_dps: float = 0.5
    still_accel_g: float = 0.004
    still_tau_s: float = 0.3
    """The chair stands still when, averaged over ``still_tau_s``, the gyro reads less than
    ``still_gyro_dps`` and the IMU accelerometer wanders less than ``still_accel_g`` rms:
    then its own acceleration is zero, which pins the tilt (a zero-acceleration update)."""
    still_accel_sigma_mps2: float = 0.1
    """Noise of that zero-acceleration pseudo-measurement, per sample."""
    still_accel_q_factor: float = 1e-4
    """While the chair stands still, its acceleration's process noise is scaled by this."""
    attitude_random_walk_deg_per_sqrt_s: float = 0.5
    """Used instead of the gyro when there is none."""
    # measurement noise, on top of each sensor's datasheet noise at its rate
    accel_floor_g: float = 0.0008
    """What the model does not capture (sensor errors left after calibration), g rms."""
    motion_model_fraction: float = 0.04
    """Share of the predicted motion acceleration taken as extra noise (the differentiator's
    lag and noise), per axis."""
    motion_compensation: bool = True
    """Predict the accelerometers with the arm's and the chair's motion (and estimate the
    chair's acceleration). Off, they are predicted as if everything stood still: only for
    comparison (the tests show what it costs)."""
    # gating and re-acquisition
    gate_significance: float = 1e-3
    """Chi-square gate on each sensor's NIS: probability that a good sample is rejected."""
    warn_rejected_share: float = 0.05
    """A sensor whose samples the gate rejected (or left out as implausible) more often than
    this share of the time is named, with why, in the tracker's warnings
    (:meth:`armfusion.fusion.tracking.tracker.Tracker.sensor_warnings`): fifty times what the gate
    costs a sensor its model fits (``gate_significance``)."""
    reacquire_after_s: float = 0.4
    """A sensor rejected for this long is a state change (a slip), not a bump."""
    slip_sigma_deg: float = 1.0
    """How much the offsets a disagreeing sensor sees are widened when it re-acquires
    (doubled each time it happens again within 10 s)."""
    reacquiring_flag_s: float = 3.0
    shift_tau_s: float = 1.0
    shift_slow_tau_s: float = 4.0
    shift_threshold: float = 60.0
    shift_slow_threshold: float = 24.0
    shift_max_angular_accel_rad_s2: float = 0.5
    """The slip detector pauses while the base's angular acceleration exceeds this (a chair
    starting or stopping a turn) or the IMU accelerometer disagrees with the model."""
    """Slip detector: each link accelerometer's innovation, normalised per axis and averaged
    over ``shift_tau_s`` and over ``shift_slow_tau_s`` (exponential averages), is tested
    against zero; a chi-square (3 dof) above ``shift_threshold`` (``shift_slow_threshold``
    for the slow average: it wanders less) is a lasting shift (a slip or a drift of a few
    tenths of a degree) that the gate alone may let through slowly: the offsets the sensor
    sees (and no agreeing sensor does) are widened."""
    # observability
    gimbal_lock_deg: float = 2.5
    """A joint whose axis is within this angle of vertical is gravity-blind: held."""
    sigma_limit_deg: float = 0.5
    """A joint the sensors cannot read to this sigma within ``observability_window_s`` is
    ill-conditioned (held along the weak direction); a joint whose sigma is above it is
    ``converging``."""
    observability_window_s: float = 1.0
    observability_period_s: float = 0.05
    """How often the observability (axis angles, information, hold) is recomputed; at
    once whenever the set of working sensors changes."""
    observability_read_periods: float = 2.5
    """A link accelerometer counts among the sensors that read the offsets (its information
    in the window's, the directions only it reads not held) while its latest sample was
    accepted and is no older than this many of its sample periods (one late sample
    forgiven), or ``observability_period_s`` where that is longer. Real drivers read each device at an
    instant of its own: the set is the sensors read lately, not the one of this instant
    (with that, every update held what its one sensor cannot see, and the corrections
    that the other sensors' readings carry through the filter's correlations were lost:
    j5 0.93 deg RMS instead of 0.05 on a demo drive read 1-6 ms apart)."""
    unknown_joint_sigma_deg: float = 30.0
    """Sigma of a joint the startup calibration could not read (gimbal lock, ambiguous)."""
    settle_s: float = 2.0
    """The last this many seconds of the startup's still stretch are left to the tracker
    (the startup calibrates on the rest, never on less than its window): a still stretch
    ends because the chair or the arm set off, and a filter that starts at that instant has
    not yet learnt, on a still chair, what its IMU accelerometer reads against the link
    accelerometers. Started there, a chair that set off gently was taken for a turned j1 on
    the WMRA (0.7 deg at a sigma of 0.1 deg, the demo's recording); settled for 2 s, j1
    tracked within 0.11 deg, within 3 sigma throughout."""
    limit_margin_deg: float = 1.0
    # sensor health
    stale_after_s: float = 0.25
    plausible_tolerance_g: float = 0.35
    """A reading whose magnitude differs from the prediction's by more than this is implausible."""
    dead_after_s: float = 0.5
    stuck_samples: int = 20
    """Identical raw readings in a row (while the prediction moved) that make a sensor stuck."""
    # differentiators
    encoder_window: int = 9
    encoder_order: int = 3
    """The causal polynomial fit (samples, order) that gives joint rates and accelerations:
    a cubic over 9 samples follows minimum-jerk moves with ~0.1 mg of error at the
    sensors, where a quadratic lags by a third of the window."""
    gyro_window: int = 15
    gyro_order: int = 2
    """The causal fit that gives the base's angular acceleration from the gyro."""
    angular_accel_error_fraction: float = 0.15
    """The differentiated gyro's error: its noise (from the gyro's noise and the fit's
    weights) plus its lag, taken as this share of the estimate; times each sensor's
    distance from the IMU it becomes extra accelerometer noise."""
    innovation_at_mean_state: bool = True
    mean_state_held_sigma_deg: float = 5.0
    """While a joint is gimbal-locked (held: its axis vertical, gravity cannot read it) and
    the filter knows it no better than ``mean_state_held_sigma_deg``, each update's
    innovation is taken without the sigma points' spread along it: each pair of points keeps
    its weight in the prediction only for the share of its offsets' displacement off the
    held joints (:meth:`armfusion.fusion.tracking.fuse.InstantUpdate.prediction_weights`,
    ``BatchedUKF.innovate(z_weights=)``); the innovation covariance and the cross covariance
    stay the unscented ones. Such a joint starts at ``unknown_joint_sigma_deg``: the points
    spread it over ±65°, and their weighted mean shrank every horizontal specific force that
    joint turns by 13 % (the chair's turns and starts, the arm's own motion): the
    innovations followed the chair's acceleration, and the gain passed that bias to the
    joints that are read. The update does not correct along a held joint, so the points'
    curvature there is information it does not use; a wide joint being *read* (converging
    from startup) keeps the weighted mean, which converges better from far. False: always
    the weighted mean (filterpy's)."""
    # sigma points (filterpy's MerweScaledSigmaPoints parameters)
    alpha: float = 0.5
    beta: float = 2.0
    kappa: float = 0.0
    # heading
    heading: HeadingSettings = field(default_factory=HeadingSettings)
    mag_fuse_period_s: float = 0.1
    """The magnetometer's samples are averaged over this period and fused as one heading
    (its noise is white; the field checks see the average)."""
    # diagnosis
    innovation_capacity: int = 100_000
    """Innovations kept per sensor (a ring buffer), for the diagnosis workbench."""


    base_fixed: bool = False
    """The base is bolted down (the config's ``base: fixed``, :meth:`bolted`): its
    acceleration is held at zero and its attitude takes no random walk (what the sensors
    read of its tilt accumulates)."""

    def bolted(self) -> TrackerSettings:
        """These settings for a base bolted down: no acceleration, no jerk, no tilt walk."""
        return replace(self, base_fixed=True, base_jerk_sigma_mps3=0.0, base_speed_sigma_mps=None,
                       base_pivot_sigma_m=None)

    def for_base(self, base_motion) -> TrackerSettings:
        """These settings with the base's acceleration model a config describes
        (:class:`armfusion.models.arm.BaseMotion`: an IMU in a hand is not a wheelchair), first-order
        (no jerk state); unchanged without one."""
        if base_motion is None:
            return self
        speed = base_motion.speed_sigma_mps
        # (the jerk's spread is a wheelchair's: a base described otherwise keeps the
        # first-order acceleration it describes)
        pivot = getattr(base_motion, "pivot_sigma_m", None)
        return replace(self, base_accel_sigma_mps2=float(base_motion.accel_sigma_mps2),
                       base_turns_about_any=getattr(base_motion, "turns_about", "vertical") == "any",
                       base_accel_tau_s=float(base_motion.accel_tau_s),
                       base_speed_sigma_mps=None if speed is None else float(speed),
                       base_pivot_sigma_m=None if pivot is None else float(pivot),
                       base_jerk_sigma_mps3=0.0)


class NotInitialisedError(RuntimeError):
    """The tracker was used before :meth:`Tracker.initialise`."""


@dataclass(frozen=True)
class StateLayout:
    """Where each block of the state is, for ``n_joints`` joints: the offsets, then roll,
    pitch, the base's acceleration (3), yaw, the gyro bias (3) and the IMU accelerometer's
    bias (3), then with ``velocity`` the base's velocity (3; ``vel`` None without), then
    with ``jerk`` its acceleration's jerk (3; ``jerk_B`` None without), then with ``pivot``
    the base origin's offset from the point it turns about (3, m, base axes; ``pivot_B``
    None without), then
    with ``gyro_scale`` the gyro's scale error about the base's z axis (a fraction: the rate
    it reads is ``(1 + s)`` times the true one; ``scale`` -1 without); an index for a scalar
    block, a slice for the others."""

    n_joints: int
    velocity: bool = False
    """A base velocity block after the others (:attr:`TrackerSettings.base_speed_sigma_mps`)."""
    gyro_scale: bool = False
    """The gyro's scale about z as a state, last (:func:`armfusion.fusion.tracking.calibrated.heading_scale_sigma`)."""
    jerk: bool = False
    """The base acceleration's rate of change (3), after the velocity
    (:attr:`TrackerSettings.base_jerk_sigma_mps3`; ``jerk_B`` None without)."""
    pivot: bool = False
    """The base origin's offset from its pivot (3), after the jerk
    (:attr:`TrackerSettings.base_pivot_sigma_m`; ``pivot_B`` None without)."""
    offset: slice = field(init=False, compare=False, repr=False)
    roll: int = field(init=False, compare=False, repr=False)
    pitch: int = field(init=False, compare=False, repr=False)
    accel: slice = field(init=False, compare=False, repr=False)
    yaw: int = field(init=False, compare=False, repr=False)
    bias: slice = field(init=False, compare=False, repr=False)
    imu_bias: slice = field(init=False, compare=False, repr=False)
    vel: slice | None = field(init=False, compare=False, repr=False)
    jerk_B: slice | None = field(init=False, compare=False, repr=False)
    pivot_B: slice | None = field(init=False, compare=False, repr=False)
    scale: int = field(init=False, compare=False, repr=False)
    size: int = field(init=False, compare=False, repr=False)

    def __post_init__(self):
        n, start = self.n_joints, 0
        # width None: a scalar block (an index); the offsets are a slice even with no joints
        for name, width in (("offset", n), ("roll", None), ("pitch", None), ("accel", 3), ("yaw", None),
                            ("bias", 3), ("imu_bias", 3)):
            object.__setattr__(self, name, start if width is None else slice(start, start + width))
            start += 1 if width is None else width
        object.__setattr__(self, "vel", slice(start, start + 3) if self.velocity else None)
        start += 3 if self.velocity else 0
        object.__setattr__(self, "jerk_B", slice(start, start + 3) if self.jerk else None)
        start += 3 if self.jerk else 0
        object.__setattr__(self, "pivot_B", slice(start, start + 3) if self.pivot else None)
        start += 3 if self.pivot else 0
        object.__setattr__(self, "scale", start if self.gyro_scale else -1)
        object.__setattr__(self, "size", start + int(self.gyro_scale))

    def names(self, joint_names) -> tuple[str, ...]:
        return tuple([f"offset[{j}]" for j in joint_names] + ["roll", "pitch"]
                     + [f"accel_B[{a}]" for a in "xyz"] + ["yaw"] + [f"gyro_bias[{a}]" for a in "xyz"]
                     + [f"imu_accel_bias[{a}]" for a in "xyz"]
                     + ([f"vel_B[{a}]" for a in "xyz"] if self.velocity else [])
                     + ([f"jerk_B[{a}]" for a in "xyz"] if self.jerk else [])
                     + ([f"pivot_B[{a}]" for a in "xyz"] if self.pivot else [])
                     + (["gyro_scale[z]"] if self.gyro_scale else []))
