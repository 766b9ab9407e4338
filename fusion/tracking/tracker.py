"""Continuous tracking: the absolute joint angles all day, from relative encoders, the link
accelerometers and the base IMU, with an unscented Kalman filter (:mod:`fusion.tracking.ukf`).

The state (:data:`STATE_NAMES`), seeded from the startup calibration:

=================  ====  ============================================================
block              size  model
=================  ====  ============================================================
``offset``         n     each relative encoder's absolute offset, rad:
                         ``q = counts / counts_per_rad + offset``; a slow random walk
                         (slips, missed counts)
``roll, pitch``    2     base tilt, rad; integrated with the gyro
``accel_B``        3     the base's own linear acceleration (chair driving, turning),
                         m/s², base axes; first-order Gauss-Markov
``yaw``            1     base heading, rad from magnetic north; integrated with the gyro
``gyro_bias``      3     the gyro's zero-rate offset, rad/s; random walk
``imu_bias``       3     what is left of the IMU accelerometer's own error after the
                         config's correction, g, IMU axes; a slow random walk from the
                         correction's uncertainty (a calibrated config's covariance, else
                         the config's unmodelled-error floor). Without it a parked chair's
                         IMU, read as exact, ties the arm's tilt about joint 1's axis and
                         joint 1 to its bias: joint 1 converged confidently to that bias
=================  ====  ============================================================

Every step:

1. **Encoders** give ``q`` (counts plus the offsets) and, through a causal polynomial
   differentiator (:class:`CausalDifferentiator`), the joint rates and accelerations.
2. **Gyro** propagates the attitude (every sigma point, its own bias).
3. **Link accelerometers and the IMU accelerometer** are predicted with motion
   compensated, ``f_S = R_0S^T (a_S + a_B + g·up)``: ``a_S`` (the joints' motion and
   the base's rotation, from :func:`models.motion.sensor_motion`), the base's linear
   acceleration ``a_B`` from the state (so the IMU accelerometer, which reads it too,
   separates the chair's acceleration from gravity and the arm's accelerometers stay
   right while the chair drives). The sigma points differ from the mean only in the
   offsets, the tilt and ``a_B``: their sensor rotations follow exactly from the mean's by
   the product-of-exponentials identity ``R_0S(q + δ) = Π_j exp([a_j]x δ_j) R_0S(q)``
   (axes ``a_j`` of the mean pose), so the kinematics run once per instant, not once per
   sigma point; the motion term ``a_S`` is taken at the mean pose (its change across the
   sigma points is first order in their offset spread: ~0.1 mg once converged). See
   docs/tracking.md.
4. **Magnetometer** corrects the yaw through the tilt-compensated heading, guarded by
   :class:`fusion.tracking.heading.MagneticGuard` (disturbance detection, rejection, recovery).

Every joint's observability is checked every step (its axis's angle to gravity, and the
eigen-decomposition of the accelerometers' information about the offsets, per second):
along directions that the sensors cannot read well (near gimbal lock, or two joints
that gravity only sees together), the update's gain is held to zero (Schmidt), so no
correction flows there and the sigma of those joints grows until they are readable
again. Each sensor has a chi-square gate; a sensor rejected for longer than
``reacquire_after_s`` (a slip, not a bump) widens the offsets it sees and re-acquires.
Samples that are not finite, saturated, implausible (far from the predicted magnitude:
a dead sensor) or stuck are skipped and counted.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.linalg import lapack
from scipy.stats import chi2

from fusion.startup.solve import StartupResult
from fusion.tracking.estimate import Estimate
from fusion.tracking.frame_kernels import FrameConstants, extrapolate_fit, poly_fit_one, push_fit
from fusion.tracking.heading import (
    FieldReference,
    HeadingSettings,
    MagneticGuard,
    heading_sigma_rad,
    tilt_compensated_heading,
)
from fusion.tracking.tracker_kernels import measurement_points, process_points
from fusion.tracking.ukf import BatchedUKF, GroupPlan, MeasurementGroup, SigmaPoints, nis_bound
from models.arm import ArmModel
from models.motion import MotionState, cross, link_motion, sensor_motion
from models.rotations import DEG, GRAVITY_MPS2, exp_so3_one, skew, up_from_tilt, wrap_angle
from models.sensor_models import (
    MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ,
    StreamModel,
    encoder_angles_at,
    mpu9150_temperature_c,
    stream_models,
)
from sensors.samples import Recording, Stream

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
_CONVERGING, _OUT, _REACQ, _ILL, _UNOBSERVED, _GIMBAL, _AMBIGUOUS = range(1, 8)
_REJECTING, _STALE, _STUCK, _DEAD, _ABSENT = range(1, 6)
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


# --------------------------------------------------------------------------------------
# settings
@dataclass(frozen=True)
class TrackerSettings:
    """Everything tunable, with units in the names; the defaults suit the WMRA's sensors."""

    # process noise
    offset_random_walk_deg_per_sqrt_s: float = 0.0035
    """Each encoder offset's random walk: lets a slip be absorbed in a few seconds while
    keeping the steady-state sigma near 0.01 deg."""
    gyro_noise_dps_per_sqrt_hz: float = MPU9150_GYRO_NOISE_DPS_PER_SQRT_HZ
    gyro_bias_random_walk_dps_per_sqrt_s: float = 0.0005
    imu_accel_bias_random_walk_g_per_sqrt_s: float = 2e-6
    compass_max_unmodelled_deg: float = 10.0
    """A compass whose config leaves more unmodelled iron than this (as a heading error,
    :func:`compass_unmodelled_rad`) is not fused: its error follows the heading, so
    averaging its readings would not shrink it. The heading is then the gyro's, from a
    start as wide as the compass's doubt."""
    """The IMU accelerometer's residual error drifts slowly (temperature): 0.1 mg in 40 min."""
    base_accel_sigma_mps2: float = 0.7
    """Steady-state spread of the chair's own acceleration (driving, turning, ramps)."""
    base_accel_tau_s: float = 5.0
    """Its correlation time: how long an acceleration typically lasts."""
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
    unknown_joint_sigma_deg: float = 30.0
    """Sigma of a joint the startup calibration could not read (gimbal lock, ambiguous)."""
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


class NotInitialisedError(RuntimeError):
    """The tracker was used before :meth:`Tracker.initialise`."""


# --------------------------------------------------------------------------------------
# state layout
@dataclass(frozen=True)
class StateLayout:
    n_joints: int

    @property
    def offset(self) -> slice:
        return slice(0, self.n_joints)

    @property
    def roll(self) -> int:
        return self.n_joints

    @property
    def pitch(self) -> int:
        return self.n_joints + 1

    @property
    def accel(self) -> slice:
        return slice(self.n_joints + 2, self.n_joints + 5)

    @property
    def yaw(self) -> int:
        return self.n_joints + 5

    @property
    def bias(self) -> slice:
        return slice(self.n_joints + 6, self.n_joints + 9)

    @property
    def imu_bias(self) -> slice:
        return slice(self.n_joints + 9, self.n_joints + 12)

    @property
    def size(self) -> int:
        return self.n_joints + 12

    def names(self, joint_names) -> tuple[str, ...]:
        return tuple([f"offset[{j}]" for j in joint_names] + ["roll", "pitch"]
                     + [f"accel_B[{a}]" for a in "xyz"] + ["yaw"] + [f"gyro_bias[{a}]" for a in "xyz"]
                     + [f"imu_accel_bias[{a}]" for a in "xyz"])


# --------------------------------------------------------------------------------------
# causal differentiation
def causal_poly_fit(t_win: np.ndarray, y_win: np.ndarray, t_eval: np.ndarray, order: int = 2) -> np.ndarray:
    """Least-squares polynomial through each window, evaluated at ``t_eval``.

    ``t_win (K, W)``, ``y_win (K, W, d)``, ``t_eval (K,)`` -> ``(K, 3, d)``: value, first and
    second derivative (zero for ``order`` 1). Batched over K windows; windows only hold
    samples at or before their evaluation time (causal). ``order`` is capped by W - 1.
    """
    t_win = np.asarray(t_win, float)
    K, W = t_win.shape
    order = int(min(order, W - 1))
    out = np.zeros((K, 3, y_win.shape[-1]))
    if W == 1 or order == 0:
        out[:, 0] = y_win[:, -1]
        return out
    tau = t_win - t_eval[:, None]
    h = np.maximum(tau[:, -1] - tau[:, 0], 1e-9)[:, None]  # the window's span (oldest first)
    s = tau / h
    A = np.stack([s**k for k in range(order + 1)], -1)  # (K, W, order+1)
    AtA = np.einsum("kwi,kwj->kij", A, A)
    Aty = np.einsum("kwi,kwd->kid", A, y_win)
    c = np.linalg.solve(AtA, Aty)  # (K, order+1, d)
    out[:, 0] = c[:, 0]
    out[:, 1] = c[:, 1] / h
    if order >= 2:
        out[:, 2] = 2.0 * c[:, 2] / h**2
    return out


def _derivative_noise_gain(t: np.ndarray, order: int) -> float:
    """How much unit white noise on the samples ``t`` puts on the causal fit's first
    derivative at the last sample (the norm of its weights)."""
    W = len(t)
    order = int(min(order, W - 1))
    tau = t - t[-1]
    h = max(abs(tau[0]), 1e-9)
    A = np.stack([(tau / h) ** k for k in range(order + 1)], -1)
    w = np.linalg.pinv(A)[1] / h  # weights of the derivative estimate
    return float(np.linalg.norm(w))


class CausalDifferentiator:
    """Sample-by-sample causal polynomial fit over the last ``window`` samples."""

    def __init__(self, dim: int, window: int, order: int):
        self.window, self.order, self.dim = int(window), int(order), int(dim)
        self._t = np.full(self.window, np.nan)
        self._y = np.zeros((self.window, dim))
        self._n = 0
        self._fit = None  # (3, d) at self._t_last
        self._t_last = -np.inf

    def push(self, t: float, y: np.ndarray) -> None:
        """Take one sample (its window shifts in place) and fit the window at it (compiled:
        :func:`fusion.tracking.frame_kernels.push_fit`, :func:`causal_poly_fit` for one window)."""
        self._n = min(self._n + 1, self.window)
        self._fit = push_fit(self._t, self._y, float(t), np.asarray(y, dtype=float).reshape(self.dim),
                             self._n, self.order)
        self._t_last = t

    def at(self, t: float) -> np.ndarray | None:
        """Value, rate and acceleration ``(3, d)`` at ``t`` (extrapolated from the last fit)."""
        if self._fit is None:
            return None
        return extrapolate_fit(self._fit, float(t - self._t_last))

    def snapshot(self) -> dict:
        return {"t": self._t.tolist(), "y": self._y.tolist(), "n": self._n}

    def restore(self, snap: dict) -> None:
        self._t = np.array(snap["t"], float)
        self._y = np.array(snap["y"], float)
        self._n = int(snap["n"])
        if self._n:
            w = self._n
            order = self.order if w > self.order else w - 1
            self._fit = poly_fit_one(self._t[-w:], self._y[-w:], float(self._t[-1]), order) \
                if w >= 2 else np.stack([self._y[-1], np.zeros(self.dim), np.zeros(self.dim)])
            self._t_last = float(self._t[-1])


def causal_fits(t: np.ndarray, y: np.ndarray, window: int, order: int) -> np.ndarray:
    """What :class:`CausalDifferentiator` gives after each sample, for a whole stream at
    once: ``(N, 3, d)`` (vectorised over samples)."""
    t = np.asarray(t, float)
    y = np.asarray(y, float).reshape(len(t), -1)
    N, d = y.shape
    out = np.zeros((N, 3, d))
    if N == 0:
        return out
    out[0, 0] = y[0]
    W = int(window)
    for k in range(1, min(W - 1, N)):  # the first windows are partial
        w = k + 1
        o = order if w > order else w - 1
        out[k] = causal_poly_fit(t[None, :w], y[None, :w], t[k:k + 1], o)[0]
    if N >= W:
        from numpy.lib.stride_tricks import sliding_window_view

        tw = sliding_window_view(t, W)  # (N-W+1, W)
        yw = np.moveaxis(sliding_window_view(y, W, axis=0), -1, 1)  # (N-W+1, W, d)
        o = order if W > order else W - 1
        for a in range(0, tw.shape[0], 20000):
            b = min(tw.shape[0], a + 20000)
            out[W - 1 + a:W - 1 + b] = causal_poly_fit(tw[a:b], yw[a:b], tw[a:b, -1], o)
    return out


# --------------------------------------------------------------------------------------
# kinematic frames: the mean pose's kinematics at each instant
class _FrameFields(NamedTuple):
    q_ref: np.ndarray
    offset_ref: np.ndarray
    R_0S: np.ndarray
    motion_mps2: np.ndarray
    axes: np.ndarray
    p_0S_m: np.ndarray
    omega_dot_B: np.ndarray
    K: np.ndarray
    motion_g: np.ndarray
    dist2_m2: np.ndarray
    omega_dot_norm: np.ndarray
    accel_var_g2: np.ndarray | None = None
    omega_S_rad_s: np.ndarray | None = None


class Frames(_FrameFields):
    """The kinematics at the reference poses of K instants (batched).

    ``q_ref (K, n)`` the reference joint angles (encoder angles plus the offsets the frame
    was made with, ``offset_ref (K, n)``); ``R_0S (K, S, 3, 3)`` and ``motion_mps2 (K, S, 3)``
    (each sensor's acceleration from the joints' motion and the base's rotation, base
    axes, without gravity or the base's own linear acceleration) for the accelerometers
    (link accelerometers then the IMU); ``axes (K, n, 3)`` the joint axes in base axes.
    ``K (., n, 3, 3)``: the axes' skew matrices; ``motion_g (., S)``:
    |motion| in g; ``dist2_m2 (., S)``: each sensor's squared distance from the base origin;
    ``accel_var_g2 (., S, 3)``: the accelerometers' measurement variances at these
    instants, when a tracker has added them; ``omega_S_rad_s (., S, 3)``: each
    accelerometer's angular velocity in its own axes. Read-only (a named tuple).
    """

    __slots__ = ()
    FIELDS = _FrameFields._fields

    def take(self, k: int) -> Frames:
        """The frame of instant ``k`` (a plain read-only record; one per fused instant)."""
        return tuple.__new__(Frames, [None if a is None else a[k] for a in self])


def make_frames(arm: ArmModel, names: tuple[str, ...], q_enc: np.ndarray, offset: np.ndarray,
                qd: np.ndarray, qdd: np.ndarray, omega_B: np.ndarray, omega_dot_B: np.ndarray,
                motion: bool = True, joint_effects=()) -> Frames:
    """Kinematic frames for K instants: ``q_enc (K, n)`` encoder angles, ``offset (n,)`` or
    ``(K, n)``, joint rates/accelerations ``(K, n)``, base rates ``(K, 3)``. ``motion``
    False: as if nothing moved (no motion compensation). ``joint_effects`` (effect,
    parameters) pairs turn the controller's angles into the geometric ones."""
    q = q_enc + offset
    K = q.shape[0]
    if not motion:
        qd = qdd = np.zeros_like(q)
        omega_B = omega_dot_B = np.zeros((K, 3))
    eye = np.broadcast_to(np.eye(3), (K, 3, 3))
    st = MotionState(np.zeros(K), q, qd, qdd, eye, omega_B, omega_dot_B, np.zeros((K, 3)), 25.0)
    if joint_effects:
        from models.effects import Context

        ctx = Context(arm, st)
        qg = np.array(q, dtype=float, copy=True)
        for e, th in joint_effects:
            qg[:, e.j] += e.delta(q, th, ctx)
        st = st.replace(q_rad=qg)
    lm = link_motion(arm, st)
    sm = sensor_motion(arm, st, list(names), lm=lm)
    Ks = skew(lm.axis_0)
    wd = np.asarray(omega_dot_B, float)
    return Frames(q, np.broadcast_to(offset, q.shape), sm.R_0S, sm.acc_0_mps2, lm.axis_0, sm.p_0S_m,
                  wd, Ks, np.linalg.norm(sm.acc_0_mps2, axis=-1) / G,
                  np.sum(sm.p_0S_m**2, axis=-1), np.linalg.norm(wd, axis=-1),
                  omega_S_rad_s=sm.omega_S_rad_s)


# --------------------------------------------------------------------------------------
# results
@dataclass(frozen=True)
class InnovationLog:
    """One sensor's innovations (oldest first): ``t_s (N,)``, ``innovation (N, k)``,
    ``S (N, k, k)``, ``nis (N,)``, ``accepted (N,)`` (used in the update)."""

    sensor: str
    t_s: np.ndarray
    innovation: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray


class _InnovationRing:
    def __init__(self, k: int, capacity: int):
        self.cap = max(int(capacity), 1)
        self.t = np.zeros(self.cap)
        self.nu = np.zeros((self.cap, k))
        self.S = np.zeros((self.cap, k, k))
        self.nis = np.zeros(self.cap)
        self.ok = np.zeros(self.cap, bool)
        self.n = 0
        # running NIS statistics (all healthy innovations, accepted or not)
        self.nis_sum = 0.0
        self.nis_count = 0

    def add(self, t, nu, S, nis, ok, count_stats: bool = True):
        i = self.n % self.cap
        self.t[i], self.nu[i], self.S[i], self.nis[i], self.ok[i] = t, nu, S, nis, ok
        self.n += 1
        if count_stats and np.isfinite(nis):
            self.nis_sum += nis
            self.nis_count += 1

    def log(self, name: str) -> InnovationLog:
        m = min(self.n, self.cap)
        idx = (np.arange(self.n - m, self.n)) % self.cap
        return InnovationLog(name, self.t[idx].copy(), self.nu[idx].copy(), self.S[idx].copy(),
                             self.nis[idx].copy(), self.ok[idx].copy())


class _AccelRing:
    """Innovations of every accelerometer, one row per update (a ring buffer)."""

    def __init__(self, names: tuple[str, ...], capacity: int):
        Sa = len(names)
        self.names = names
        self.cap = max(int(capacity), 1)
        self.t = np.zeros(self.cap)
        self.nu = np.zeros((self.cap, Sa, 3))
        self.S = np.zeros((self.cap, Sa, 3, 3))
        self.nis = np.zeros((self.cap, Sa))
        self.ok = np.zeros((self.cap, Sa), bool)
        self.present = np.zeros((self.cap, Sa), bool)
        self.n = 0
        self.nis_sum = np.zeros(Sa)
        self.nis_count = np.zeros(Sa, dtype=np.int64)  # rows with only some sensors
        self.nis_whole = 0  # rows with every sensor

    @property
    def counts(self) -> np.ndarray:
        """Healthy innovations counted per sensor."""
        return self.nis_count + self.nis_whole

    def add(self, t, which, nu, S, nis, ok, finite=False):
        """``which (k,)`` sensor indices; ``nu (k, 3)``, ``S (k, 3, 3)``, ``nis``, ``ok (k,)``;
        ``finite``: the caller knows every NIS is finite (each passed its gate)."""
        i = self.n % self.cap
        self.t[i] = t
        self.n += 1
        if len(which) == self.present.shape[1]:  # every sensor, in order: whole rows
            self.present[i] = True
            self.nu[i], self.S[i], self.nis[i], self.ok[i] = nu, S, nis, ok
            if finite or math.isfinite(nis.sum()):
                self.nis_sum += nis
                self.nis_whole += 1  # counted for every sensor (see counts)
                return
        else:
            self.present[i] = False
            self.present[i, which] = True
            self.nu[i, which] = nu
            self.S[i, which] = S
            self.nis[i, which] = nis
            self.ok[i, which] = ok
        good = np.isfinite(nis)
        self.nis_sum[which[good]] += nis[good]
        self.nis_count[which[good]] += 1

    def log(self, name: str) -> InnovationLog:
        j = self.names.index(name)
        m = min(self.n, self.cap)
        idx = (np.arange(self.n - m, self.n)) % self.cap
        idx = idx[self.present[idx, j]]
        return InnovationLog(name, self.t[idx].copy(), self.nu[idx, j].copy(), self.S[idx, j].copy(),
                             self.nis[idx, j].copy(), self.ok[idx, j].copy())


# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ImuStill:
    """What the IMU said during the still startup window: the gyro's zero-rate offset, the
    heading (tilt-compensated, from the startup's roll and pitch) and the field reference."""

    gyro_bias_rad_s: np.ndarray
    gyro_bias_sigma_rad_s: float
    yaw_rad: float | None
    yaw_sigma_rad: float | None
    field: FieldReference | None


def imu_still_from_recording(arm: ArmModel, rec: Recording, t_start_s: float, t_end_s: float,
                             startup: StartupResult, settings: TrackerSettings | None = None,
                             correction=None) -> ImuStill:
    """The gyro bias, initial heading and Earth-field reference from a still window.
    ``correction``: the config's :class:`fusion.identification.identify.StartupCorrection`, when the caller
    has it (else made here when the config has compass effects)."""
    st = settings or TrackerSettings()
    sm = stream_models(arm)
    R_0I = arm.imu.R_LS if arm.imu is not None else np.eye(3)
    bias = np.zeros(3)
    bias_sigma = 0.5 * DEG  # no gyro samples: a wide guess
    g = rec.get(GYRO)
    if g is not None:
        w = g.between(t_start_s, t_end_s + 1e-9)
        if len(w) >= 3:
            rate = w.rate_hz or 100.0
            omega = sm[GYRO].from_counts(w.values) @ R_0I.T
            bias = omega.mean(axis=0)
            noise = st.gyro_noise_dps_per_sqrt_hz * DEG * np.sqrt(rate / 2.0)
            bias_sigma = float(max(noise / np.sqrt(len(w)), 2e-5))
    yaw = yaw_sigma = None
    field_ref = None
    m = rec.get(MAG)
    if m is not None:
        w = m.between(t_start_s, t_end_s + 1e-9)
        if len(w) >= 1:
            y = sm[MAG].from_counts(w.values)
            undo = compass_map(arm, correction)
            if undo is not None:  # the config's hard and soft iron, as the tracker undoes them
                y = (y - undo[1]) @ undo[0]
            mB = y @ R_0I.T
            up = up_from_tilt(np.array(startup.roll_rad), np.array(startup.pitch_rad))
            if st.heading.reference == "model":
                field_ref = FieldReference.from_world_field()
            else:
                field_ref = FieldReference.from_samples(mB, up)
            mean = mB.mean(axis=0)
            yaw = float(tilt_compensated_heading(mean, startup.roll_rad, startup.pitch_rad,
                                                 field_ref.declination_rad))
            sig = heading_sigma_rad(field_ref, st.heading.noise_ut) / np.sqrt(len(w))
            tilt_sig = np.hypot(startup.roll_sigma_rad, startup.pitch_sigma_rad) * np.tan(field_ref.dip_rad)
            iron_sig = compass_unmodelled_rad(arm, field_ref)
            yaw_sigma = float(np.sqrt(sig**2 + tilt_sig**2 + iron_sig**2) + 0.2 * DEG)
    return ImuStill(bias, bias_sigma, yaw, yaw_sigma, field_ref)


def compass_unmodelled_ut(arm: ArmModel) -> float:
    """How far the compass's horizontal reading may be from Earth's field, µT, by what the
    config says: the σ of a hard iron it holds (the tracker undoes the hard and soft iron,
    :data:`fusion.identification.identify.COMPASS_MAP_EFFECTS`, so what stays is how well they are known),
    else ``calibration.mag_unmodelled_ut``, else 0."""
    for e in arm.effects or ():
        d = e if isinstance(e, Mapping) else e.model_dump()
        if d.get("effect") == "mag_hard_iron":
            s = np.asarray((d.get("sigma") or {}).get("offset_ut", [0.0, 0.0, 0.0]), float)
            return float(np.sqrt(np.sum(s[:2] ** 2)))
    return float((arm.calibration or {}).get("mag_unmodelled_ut", 0.0) or 0.0)


def compass_map(arm: ArmModel, correction=None) -> tuple[np.ndarray, np.ndarray] | None:
    """The config's soft and hard iron as the map that undoes them, ``(A, c)``: the field
    in the compass's axes is ``(y - c) @ A`` for readings ``y (N, 3)`` µT; None without them.
    ``correction``: the config's :class:`fusion.identification.identify.StartupCorrection`, if
    made already."""
    if correction is None:
        if not any(True for n in ("mag_hard_iron", "mag_soft_iron") for _ in _effect_dicts(arm, n)):
            return None
        from fusion.identification.identify import startup_correction

        correction = startup_correction(arm)
    m = correction.maps.get(MAG)
    return None if m is None else (np.linalg.inv(m[0]).T, np.asarray(m[1], float))


def compass_unmodelled_rad(arm: ArmModel, field: FieldReference) -> float:
    """:func:`compass_unmodelled_ut` as a heading error (rad) against the horizontal field;
    at or past the field itself the compass says nothing about the heading (π)."""
    u = compass_unmodelled_ut(arm)
    h = max(field.horizontal_ut, 1e-6)
    return float(np.pi if u >= h else np.arcsin(u / h))


@dataclass(frozen=True)
class Start:
    """How a tracker was started from a recording: the still window, the startup
    calibration, what the IMU said, and the notes on sensors left out."""

    t_start_s: float
    t_end_s: float
    startup: StartupResult
    imu: ImuStill
    notes: tuple[str, ...]
    geometric: StartupResult | None = None
    """The startup before the config's joint effects were undone (what a later still
    window's solve compares with, through :func:`fusion.startup.solve.prior_after_move`)."""
    encoder_rad: np.ndarray | None = None
    """The encoders' angles (counts / counts per rad) at the end of the still window."""


class NoStillWindowError(ValueError):
    """The recording has no still stretch to calibrate from."""


def warm_up(arm: ArmModel, settings: TrackerSettings | None = None) -> float:
    """Compile (the first run after an install) or load (later runs) the tracker's compiled
    kernels with the signatures the live path uses, by tracking 2 s of a simulated arm
    sample by sample after a startup on the 2 s before, so that a node does not pay for it
    while samples queue up. Returns the seconds it took."""
    from models.simulator import simulate

    t0 = time.perf_counter()
    rec, _ = simulate(arm, "daily-use", 4.0, seed=0)
    first = Recording({k: v.between(0.0, 2.0) for k, v in rec.streams.items()}, rec.meta)
    tr, _ = start_from_recording(arm, first, settings, propose_unlock=False)  # then 2 s more
    values = {s: rec.get(s).values for s in tr.sensor_names if s in rec.streams}
    t_enc = rec.get(ENC).t_s
    n = min(len(v) for v in values.values())
    for i in range(int(np.searchsorted(t_enc, tr.t_s + 1e-9)), n):
        t = float(t_enc[i])
        if i % 2:  # every sensor at one instant, and one device at a time
            tr.update_instant(t, {s: v[i] for s, v in values.items()})
        else:
            for k, (s, v) in enumerate(values.items()):
                tr.update(s, t + 1e-4 * k, v[i])
    return time.perf_counter() - t0


def start_from_recording(arm: ArmModel, rec: Recording, settings: TrackerSettings | None = None,
                         prior_q_rad: np.ndarray | None = None, window_s: float = 1.0,
                         startup_settings=None, propose_unlock: bool = True,
                         prior=None, resolve_by_motion_s: float | None = None) -> tuple[Tracker, Start]:
    """A tracker initialised from the recording's first still stretch: the startup
    calibration there (:func:`fusion.startup.solve.solve_still`), the gyro bias, heading and field
    reference from the same window; it starts tracking at the window's end.
    ``propose_unlock`` False: no search for a move that would unlock gravity-blind joints
    (about 2 s of the startup's time, for a caller that does not show it).
    ``prior_q_rad``: a pose saved at the last clean shutdown, checked against the still data
    before it may choose a branch (:class:`fusion.startup.solve.StartupPrior`); ``prior``: any
    other startup prior (e.g. ``StartupPrior.assume_parked``).
    ``resolve_by_motion_s``: for a whole recording (not live), when the startup left joints
    ``ambiguous``, track each candidate branch over the next this many seconds and keep the
    one the motion's readings favour (:func:`_branch_by_motion`); they stay ambiguous when no
    branch is decisively better (the arm did not move enough)."""
    from fusion.startup.solve import StartupPrior, readings_from_recording, solve_still

    if prior is None and prior_q_rad is not None:
        prior = StartupPrior.saved_pose(prior_q_rad)
    from fusion.startup.static import StaticDetectionSettings, find_static_segments

    segs = find_static_segments(rec, StaticDetectionSettings(window_s=min(window_s, 1.0)))
    if not segs:
        raise NoStillWindowError(
            "no still stretch in the recording (accelerometers, gyro and encoders quiet for at "
            "least 1 s): the tracker needs a startup calibration on a still arm")
    seg = segs[0]
    readings, checks = readings_from_recording(arm, rec, seg.t_start_s, seg.t_end_s, window_s)
    notes = [c.message for c in checks]
    corr = None
    if arm.effects:  # a calibrated config: the startup works on corrected readings
        from fusion.identification.identify import startup_correction

        temp = rec.get("imu_temp")
        still_temp = temp.between(seg.t_start_s, seg.t_end_s) if temp is not None else None
        if still_temp is None or not len(still_temp):
            still_temp = temp
        # corrected at the temperature of the still stretch (the tracker follows it after)
        temperature_c = (float(mpu9150_temperature_c(np.mean(still_temp.values)))
                         if still_temp is not None and len(still_temp) else 25.0)
        corr = startup_correction(arm, temperature_c, include_joint_offsets=True)
        readings = corr.readings(readings)
        notes.append("the config's effects applied: " + ", ".join(e.block_name for e in corr.model.effects))
    startup = solve_still(arm, readings, startup_settings, prior=prior,
                          propose_unlock=propose_unlock)
    notes.extend(startup.notes)
    geometric = startup
    if corr is not None:
        startup = corr.controller_result(startup)
    imu = imu_still_from_recording(arm, rec, seg.t_start_s, seg.t_end_s, startup, settings, corr)
    enc = rec.get(ENC)
    if enc is None or not len(enc):
        raise ValueError("the recording has no encoder stream 'enc': nothing to track")
    k, enc_rad = encoder_angles_at(arm, enc, seg.t_end_s)
    rates = {s: (v.rate_hz or 100.0) for s, v in rec.raw().items()}

    def tracker_from(result: StartupResult) -> Tracker:
        t = Tracker(arm, settings, rates_hz=rates, correction=corr)
        t.initialise(result, float(enc.t_s[k]), encoder_counts=enc.values[k], imu=imu,
                     prior_q_rad=prior_q_rad)
        t.prime(rec)
        return t

    if resolve_by_motion_s and startup.candidates_rad is not None and len(startup.candidates_rad) > 1:
        chosen, note = _branch_by_motion(startup, tracker_from, rec, float(enc.t_s[k]),
                                         resolve_by_motion_s, startup_settings)
        notes.append(note)
        if chosen is not None:
            startup = chosen
    tr = tracker_from(startup)
    return tr, Start(seg.t_start_s, seg.t_end_s, startup, imu, tuple(notes), geometric, enc_rad)


def _branch_by_motion(startup: StartupResult, tracker_from, rec: Recording, t0_s: float,
                      horizon_s: float, startup_settings=None,
                      decisive_nis: float = 50.0) -> tuple[StartupResult | None, str]:
    """The candidate branch the motion after a still window favours, offline.

    Twins that read the same still read differently once the arm or the chair moves (as a
    disambiguating move makes them). Each candidate of ``startup`` seeds a tracker, run over
    ``horizon_s`` of the recording after ``t0_s``; the link accelerometers' normalised
    innovations (NIS) summed over that stretch are the evidence. A candidate is chosen when
    it beats every other by ``decisive_nis`` (a log-likelihood ratio of 25); it is then a
    startup with those joints numbered (the candidate's own covariance), and the note says
    so. Otherwise ``None``: the joints stay ``ambiguous``."""
    from fusion.startup.solve import StartupSettings

    st = startup_settings or StartupSettings()
    n = len(startup.joints)
    amb = [j for j, je in enumerate(startup.joints) if je.flag == "ambiguous"]
    names = ", ".join(startup.joints[j].name for j in amb)
    covs = (startup.candidates_covariance if startup.candidates_covariance is not None
            else np.repeat(np.asarray(startup.covariance)[None], len(startup.candidates_rad), 0))
    window = Recording({kk: v.between(-np.inf, t0_s + horizon_s) for kk, v in rec.streams.items()},
                       dict(rec.meta))
    totals, variants = [], []
    for cand, cov in zip(startup.candidates_rad, covs, strict=True):
        sig = np.sqrt(np.clip(np.diag(cov)[:n], 0, None))
        joints = tuple(
            replace(je, angle_rad=float(cand[j]), sigma_rad=float(sig[j]), alternatives_rad=(),
                    flag="ok" if sig[j] <= st.sigma_limit_deg * DEG else "ill_conditioned")
            if j in amb else je for j, je in enumerate(startup.joints))
        v = replace(startup, joints=joints, q_rad=np.array(cand, float), covariance=np.array(cov),
                    candidates_rad=np.array(cand, float)[None], candidates_covariance=np.array(cov)[None],
                    disambiguating_move=None)
        tr = tracker_from(v)
        tr.run(window, truth=False)
        total = 0.0
        for s_ in tr.link_names:
            lg = tr.innovations(s_)
            ok = np.isfinite(lg.nis) & (lg.t_s > t0_s)
            total += float(np.sum(lg.nis[ok]))
        totals.append(total)
        variants.append(v)
    order = np.argsort(totals)
    best, second = totals[order[0]], totals[order[1]]
    if second - best >= decisive_nis:
        return variants[order[0]], (
            f"{names}: the branch chosen by the motion after the still window (the candidates' "
            f"summed NIS over {horizon_s:g} s: {best:.0f} against {second:.0f} at the next)")
    return None, (f"{names}: ambiguous, and the motion after the still window does not tell the "
                  f"branches apart (summed NIS over {horizon_s:g} s: {best:.0f} and {second:.0f})")


def _effect_dicts(arm: ArmModel, name: str):
    """The config's entries of effect ``name`` as plain dicts."""
    for e in arm.effects or ():
        d = e if isinstance(e, Mapping) else e.model_dump()
        if d.get("effect") == name:
            yield d


def _encoder_scales(arm: ArmModel) -> np.ndarray:
    """Per joint, the config's calibrated encoder scale error (``encoder_scale``: the
    encoder gives ``1 + s`` times the counts the config's counts per revolution say)."""
    s = np.zeros(arm.n_joints)
    for d in _effect_dicts(arm, "encoder_scale"):
        if d.get("target") in arm.joint_names:
            value = (d.get("params") or {}).get("scale_error", [0.0])
            s[arm.joint_names.index(d["target"])] = float(np.ravel(value)[0])
    return s


def _encoder_scale_sigmas(arm: ArmModel) -> np.ndarray:
    """Per joint, the sigma of the config's encoder scale error (0 where it gives none)."""
    s = np.zeros(arm.n_joints)
    for d in _effect_dicts(arm, "encoder_scale"):
        sig = (d.get("sigma") or {}).get("scale_error")
        if d.get("target") in arm.joint_names and sig is not None:
            s[arm.joint_names.index(d["target"])] = float(np.ravel(sig)[0])
    return s


def _offset_per_degree(arm: ArmModel, correction) -> dict[str, np.ndarray]:
    """Per accelerometer stream, how the correction's offset moves per °C (the config's
    ``temperature_drift``), so that readings are corrected at the temperature the IMU reads
    now rather than the startup's."""
    if not any(True for _ in _effect_dicts(arm, "temperature_drift")):
        return {}
    from fusion.identification.identify import startup_correction

    t0 = float(correction.temperature_c)
    warmer = startup_correction(arm, t0 + 1.0, include_joint_offsets=True)
    out = {}
    for stream, (_, c) in correction.maps.items():
        slope = np.asarray(warmer.maps[stream][1], float) - np.asarray(c, float)
        if np.any(slope):
            out[stream] = slope
    return out


def _with_lever_arms(arm: ArmModel) -> ArmModel:
    """The arm with each sensor where its config's calibrated lever arm puts it (the
    ``motion_acceleration`` effects: an offset in the link's axes), so that the motion the
    tracker predicts at a sensor (centripetal, tangential) is at the right point."""
    shift: dict[str, np.ndarray] = {}
    for d in _effect_dicts(arm, "motion_acceleration"):
        if d.get("target"):
            v = np.asarray((d.get("params") or {}).get("lever_arm_offset_m", [0.0, 0.0, 0.0]), float)
            if v.shape == (3,) and np.any(v):
                shift[d["target"]] = v
    if not shift:
        return arm
    sensors = tuple(replace(s, p_L_m=np.asarray(s.p_L_m, float) + shift[s.name]) if s.name in shift else s
                    for s in arm.sensors)
    return replace(arm, sensors=sensors)


# --------------------------------------------------------------------------------------
class Tracker:
    """The joint-angle and heading tracker, driven sample by sample (or a whole recording).

    Lifecycle: ``Tracker(arm, settings)`` -> :meth:`initialise` (from a startup result) ->
    :meth:`update` for every raw sample as it arrives (or :meth:`update_instant` for all
    samples of one instant, or :meth:`run` for a recording) -> :attr:`estimate`.
    :meth:`snapshot` / :meth:`restore` carry the state across a restart of the process.
    """

    def __init__(self, arm: ArmModel, settings: TrackerSettings | None = None,
                 rates_hz: Mapping[str, float] | float = 100.0, correction=None):
        """``correction`` (a :class:`fusion.identification.identify.StartupCorrection`, default: made from the
        config's effects when it has any) undoes the calibrated accelerometer errors (affine:
        mount, axes, scale, bias) on every sample, and maps the controller's joint angles to
        the geometric ones (zero offsets, sag, play) in the kinematics."""
        arm = _with_lever_arms(arm)
        self.arm = arm
        if correction is None and arm.effects:
            from fusion.identification.identify import startup_correction

            correction = startup_correction(arm, include_joint_offsets=True)
        self.correction = correction
        self._undo = {}
        self._undo_per_c: dict[str, np.ndarray] = {}
        self._temperature_ref_c = float(getattr(correction, "temperature_c", 25.0)) if correction else 25.0
        self._temperature_c = self._temperature_ref_c
        self._joint_effects = []
        self._spread: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        if correction is not None:
            for stream, (Lm, c) in correction.maps.items():
                self._undo[stream] = (np.linalg.inv(Lm).T, np.asarray(c, float))
            for stream, maps in correction.spread.items():
                if stream != MAG:  # (the compass's doubt is compass_unmodelled_ut)
                    self._spread[stream] = [(np.linalg.inv(L1), np.asarray(c1, float)) for L1, c1 in maps]
            self._undo_per_c = _offset_per_degree(arm, correction)
            from models.effects import JointEffect

            th = correction.model.unpack()
            self._joint_effects = [(e, th[e.block_name]) for e in correction.model.effects
                                   if isinstance(e, JointEffect)]
        self.settings = st = settings or TrackerSettings()
        n = arm.n_joints
        self.layout = L = StateLayout(n)
        self.state_names = L.names(arm.joint_names)
        self.link_names = tuple(s.name for s in arm.link_accelerometers)
        self._has_imu = arm.imu is not None
        self.accel_names = self.link_names + ((arm.imu.name,) if self._has_imu else ())
        self.accel_streams = self.link_names + ((IMU_ACC,) if self._has_imu else ())
        self.sensor_names = self.accel_streams + ((GYRO, MAG) if self._has_imu else ()) + (ENC,)
        self._sidx = {s: i for i, s in enumerate(self.sensor_names)}
        self._links = np.array([arm.sensor(nm).link for nm in self.accel_names], dtype=int)
        self._R_0I = arm.imu.R_LS if self._has_imu else np.eye(3)
        self._cpr = arm.counts_per_rad * (1.0 + _encoder_scales(arm))
        self._rates: dict[str, float] = {}
        self._unmodelled_g = self._unmodelled_floor()
        self._consider_columns()
        self._time_offset_s, self._time_var_s2 = self._stamp_offsets()
        self.set_rates(rates_hz)
        self._gate3 = float(nis_bound(3, st.gate_significance))
        self._gate1 = float(nis_bound(1, st.gate_significance))
        self._points = SigmaPoints(L.size, st.alpha, st.beta, st.kappa)
        self._ukf: BatchedUKF | None = None
        self._t: float | None = None
        self._sees = self._links[:, None] > np.arange(n)[None, :]  # (S, n): sensor s sees joint j
        self._att_idx = np.array([L.roll, L.pitch, L.yaw])
        self._nees_idx = np.r_[np.arange(n), L.roll, L.pitch, L.yaw]
        self._nees_ix = np.ix_(self._nees_idx, self._nees_idx)
        self._acc_rows = np.arange(3 * len(self.accel_streams)).reshape(-1, 3)
        self._links_i64 = self._links.astype(np.int64)
        self._no_field = np.full(3, np.nan)
        self._no_sel = np.zeros(0, dtype=np.int64)
        self._accel_decay: dict[float, float] = {}
        self._zeros3 = np.zeros(3)
        self._still_var3 = np.full(3, st.still_accel_sigma_mps2**2)
        self._eye3 = np.eye(3)
        self._eye_state = np.eye(L.size)
        self._Q_cache: dict = {}
        self._links_list = [int(k) for k in self._links[: len(self.link_names)]]
        self._min_list = arm.min_rad.tolist()
        self._max_list = arm.max_rad.tolist()
        self._imu_acc_index = self._sidx.get(IMU_ACC, -1)
        self._plan_cache: dict = {}
        self._mag_mask: dict = {}
        # the live path's one-instant frame, compiled (False: make_frames, the NumPy reference)
        self._frame_consts = FrameConstants(arm, self.accel_names, self._joint_effects, G)
        self._frames_compiled = True

    def _consider_columns(self) -> None:
        """The columns of the consider sensitivity (see :meth:`_consider_update`): each
        correction spread of a calibrated config, and, per link accelerometer whose config
        states an unmodelled error (``calibration.accel_unmodelled_g``), one column per axis:
        an error of that size that stays (an uncalibrated ADXL345's offset and its board's
        tilt do not average away)."""
        self._spread_cols: dict[str, np.ndarray] = {}
        self._spread_stack: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._floor_cols: dict[str, tuple[np.ndarray, float]] = {}
        m = 0
        for stream, maps in self._spread.items():
            if maps:
                self._spread_cols[stream] = np.arange(m, m + len(maps))
                self._spread_stack[stream] = (np.array([M for M, _ in maps]), np.array([c for _, c in maps]))
                m += len(maps)
        for stream, floor_g in zip(self.link_names, self._unmodelled_g.tolist(), strict=False):
            if floor_g > 0.0:
                self._floor_cols[stream] = (np.arange(m, m + 3), floor_g)
                m += 3
        # an encoder scale known to sigma_s moves the joint's true offset by sigma_s per radian
        # the encoder turns: one column per joint whose config gives that sigma
        sig_s = _encoder_scale_sigmas(self.arm)
        self._scale_joints = np.flatnonzero(sig_s > 0.0)
        self._scale_sigma = sig_s[self._scale_joints]
        self._scale_cols = np.arange(m, m + len(self._scale_joints))
        m += len(self._scale_joints)
        self._spread_m = m

    def _stamp_offsets(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Per accelerometer stream, the config's calibrated time offset (s: samples stamped
        late by it, ``time_offset``) and its variance (s², the estimate's sigma, or the
        prior's where the calibration held it). While a link turns, a reading stamped dt late
        saw gravity as it was dt earlier (7 ms at 30 deg/s is 0.2 deg): the offset is undone,
        its sigma is measurement noise. ``None`` when the config has no time offsets."""
        idx = {nm: i for i, nm in enumerate(self.accel_names)}
        off = np.zeros(len(self.accel_names))
        var = np.zeros(len(self.accel_names))
        for d in _effect_dicts(self.arm, "time_offset"):
            if d.get("target") not in idx:
                continue
            i = idx[d["target"]]
            off[i] = float(np.ravel((d.get("params") or {}).get("offset_s", [0.0]))[0])
            sig = (d.get("sigma") or {}).get("offset_s")
            var[i] = float(np.ravel(sig)[0]) ** 2 if sig is not None else 0.0
        if not off.any() and not var.any():
            return None, None
        return off, var

    def _imu_bias_prior_var(self, roll_rad: float, pitch_rad: float) -> np.ndarray:
        """Prior variance (g²) of what the IMU accelerometer's correction leaves, per IMU
        axis, at the still reading of the startup's tilt: a calibrated config's correction
        spread there, else the config's unmodelled-error floor (its statement of how far its
        sensors are from their model)."""
        if not self._has_imu:
            return np.full(3, 1e-12)
        corr = self.correction
        m = self._R_0I.T @ up_from_tilt(roll_rad, pitch_rad)
        if corr is not None and corr.spread.get(IMU_ACC):
            y0 = corr.readings_one(IMU_ACC, m)
            var = np.zeros(3)
            for L1, c1 in corr.spread[IMU_ACC]:
                var += (np.linalg.solve(L1, m - c1) - y0) ** 2
            return np.maximum(var, 1e-12)
        cal = self.arm.calibration or {}
        floor = float(cal.get("imu_accel_unmodelled_g", cal.get("accel_unmodelled_g", 0.0)) or 0.0)
        return np.full(3, max(floor, 1e-6) ** 2)

    def _unmodelled_floor(self) -> np.ndarray:
        """Per accelerometer stream, the config's unmodelled-error floor (g), as startup uses."""
        cal = self.arm.calibration or {}
        per = cal.get("accel_unmodelled_g_per_sensor") or {}
        base = float(cal.get("accel_unmodelled_g", 0.0) or 0.0)
        out = []
        for nm in self.link_names:
            out.append(float(per.get(nm, base)))
        if self._has_imu:
            out.append(0.0)
        return np.array(out)

    # -- configuration -------------------------------------------------------------------
    def set_rates(self, rates_hz: Mapping[str, float] | float) -> None:
        """Sample rates (Hz) per stream, which set each sensor's noise (datasheet rms at rate)."""
        if isinstance(rates_hz, Mapping):
            rates = {s: float(rates_hz.get(s, 100.0)) for s in self.sensor_names}
        else:
            rates = dict.fromkeys(self.sensor_names, float(rates_hz))
        self._rates = rates
        self._sm: dict[str, StreamModel] = stream_models(self.arm, rates)
        st = self.settings
        sig = []
        for i, s in enumerate(self.accel_streams):
            m = self._sm[s]
            floor = max(st.accel_floor_g, self._unmodelled_g[i])
            sig.append(np.sqrt((m.noise_counts_rms / np.abs(m.gain)) ** 2 + floor**2))
        self._accel_sigma_g = np.array(sig).reshape(-1, 3)  # (S, 3)
        self._accel_var_g2 = self._accel_sigma_g**2
        self._accel_rate = np.array([rates[s] for s in self.accel_streams])
        # noise of the gyro's causal derivative: the fit's weights on unit white noise
        r = rates.get(GYRO, 100.0)
        W = st.gyro_window
        t = np.arange(W) / r
        gain = _derivative_noise_gain(t, st.gyro_order)
        sig_w = st.gyro_noise_dps_per_sqrt_hz * DEG * np.sqrt(r / 2.0)
        self._omega_dot_noise = float(gain * sig_w)
        self._limits = {s: (self._sm[s].counts_min, self._sm[s].counts_max) for s in self._sm}
        sa = self.accel_streams
        lo = [self._sm[s].counts_min for s in sa]
        hi = [self._sm[s].counts_max for s in sa]
        self._acc_lo = np.array([-np.inf if v is None else v for v in lo], dtype=float)
        self._acc_hi = np.array([np.inf if v is None else v for v in hi], dtype=float)
        self._sel_cache: dict = {}  # per set of accelerometers: see _sel_info
        self._obs_cache: dict = {}  # per set of link accelerometers: see _obs_sel

    # -- lifecycle -----------------------------------------------------------------------
    def initialise(self, startup: StartupResult, t_s: float, encoder_counts: np.ndarray | None = None,
                   imu: ImuStill | None = None, prior_q_rad: np.ndarray | None = None) -> None:
        """Seed the filter from the startup calibration (its joint angles and covariance).

        ``encoder_counts`` are the counts while the startup window was still (default: the
        first encoder sample that arrives). A joint the startup could not read starts at
        ``prior_q_rad`` (the pose saved at the last clean shutdown; default the ready pose)
        with ``unknown_joint_sigma_deg``, and is ``converging`` until read. ``imu`` (from
        :func:`imu_still_from_recording`) gives the gyro bias, heading and field reference.
        """
        st, L, n = self.settings, self.layout, self.arm.n_joints
        if len(startup.joints) != n:
            raise ValueError(f"startup result has {len(startup.joints)} joints; arm {self.arm.name!r} "
                             f"has {n}")
        imu = imu or ImuStill(np.zeros(3), 0.5 * DEG, None, None, None)
        x = np.zeros(L.size)
        P = np.zeros((L.size, L.size))
        cov = np.array(startup.covariance, dtype=float)
        q0 = np.array(startup.q_rad, dtype=float)
        known = np.array([j.flag not in ("gimbal_lock", "ambiguous") and j.sigma_rad is not None
                          for j in startup.joints])
        # a joint the startup could not read starts at the prior pose (the saved pose, else
        # the ready pose), not at the solve's arbitrary value
        prior = self.arm.ready_pose_rad if prior_q_rad is None else np.asarray(prior_q_rad, float)
        amb = np.array([j.flag == "ambiguous" for j in startup.joints])
        cands = startup.candidates_rad
        if amb.any() and cands is not None and len(cands) > 1:
            # rival branches: the filter runs on one of them, the one nearest the prior pose
            # (where the search started: no evidence, so the flag stays `ambiguous` and the
            # sigma covers every candidate), each one a real minimum with its own covariance
            d = np.abs(wrap_angle(np.asarray(cands) - prior))[:, amb].sum(1)
            c = int(np.argmin(d))
            q0 = np.array(cands[c], dtype=float)
            if startup.candidates_covariance is not None:
                cov = np.array(startup.candidates_covariance[c], dtype=float)
            known = known | amb
        q0 = np.where(known, q0, prior)
        jb = np.r_[np.arange(n), n, n + 1]  # joints, roll, pitch in the startup covariance
        tgt = np.r_[np.arange(n), L.roll, L.pitch]
        if cov.shape == (n + 2, n + 2):
            block = cov[np.ix_(jb, jb)].copy()
        else:
            block = np.diag(np.r_[[j.sigma_rad or 0.0 for j in startup.joints], startup.roll_sigma_rad,
                                  startup.pitch_sigma_rad] ** 2)
        block = np.where(np.isfinite(block), block, 0.0)
        wide = (st.unknown_joint_sigma_deg * DEG) ** 2
        for j in np.flatnonzero(~known):
            block[j, :] = 0.0
            block[:, j] = 0.0
            block[j, j] = wide
        # a floor: the startup's sigma is for a still average; the tracker's model adds a little
        block[np.diag_indices(n + 2)] += (0.005 * DEG) ** 2
        P[np.ix_(tgt, tgt)] = block
        x[L.roll], x[L.pitch] = startup.roll_rad, startup.pitch_rad
        # the startup window was still: the chair's acceleration is zero there
        P[L.accel, L.accel] = np.eye(3) * (0.01**2 if st.motion_compensation else 1e-16)
        if imu.yaw_rad is not None:
            x[L.yaw] = imu.yaw_rad
            P[L.yaw, L.yaw] = imu.yaw_sigma_rad**2
        else:
            P[L.yaw, L.yaw] = np.pi**2
        x[L.bias] = imu.gyro_bias_rad_s
        P[L.bias, L.bias] = np.eye(3) * imu.gyro_bias_sigma_rad_s**2
        P[L.imu_bias, L.imu_bias] = np.diag(self._imu_bias_prior_var(startup.roll_rad, startup.pitch_rad))
        self._q_startup = q0
        # joints the startup left with rival branches: not known until a move resolves them
        self._ambiguous = np.array([j.flag == "ambiguous" for j in startup.joints], dtype=bool)
        self._amb_candidates = tuple(tuple(j.alternatives_rad) for j in startup.joints)
        self._amb_q_enc = None  # the encoders' angles when the candidates held
        self._amb_half_gap = np.array([
            (max(a) - min(a)) / 2.0 if j.flag == "ambiguous" and len(a) > 1 else 0.0
            for j, a in ((j, j.alternatives_rad) for j in startup.joints)])
        self._x0, self._P0 = x, P
        self._ukf = None  # created when the first encoder sample fixes the offsets
        self._q_enc = np.zeros(n)
        self._enc0 = None if encoder_counts is None else np.asarray(encoder_counts, float)
        if self._enc0 is not None:
            self._start_filter(self._enc0 / self._cpr)
        self._t = float(t_s)
        self._field = imu.field
        self._guard = MagneticGuard(imu.field, st.heading) if imu.field is not None else None
        self._sigma_psi = heading_sigma_rad(imu.field, st.heading.noise_ut) if imu.field else np.inf
        # an unmodelled hard iron turns every compass heading by up to asin(h / B_h), a
        # different amount at every heading: taken as noise of that size on each update
        self._iron_var = compass_unmodelled_rad(self.arm, imu.field) ** 2 if imu.field else 0.0
        self._compass_usable = self._iron_var <= (st.compass_max_unmodelled_deg * DEG) ** 2
        self._enc_diff = CausalDifferentiator(n, st.encoder_window, st.encoder_order)
        self._gyro_diff = CausalDifferentiator(3, st.gyro_window, st.gyro_order)
        self._omega = None  # last gyro, base axes, rad/s
        S, Sa = len(self.sensor_names), len(self.accel_streams)
        # sensor health, as arrays (sensor order: self.sensor_names; accelerometers first)
        self._seen = np.zeros(S, bool)
        self._last_t = np.full(S, -np.inf)
        self._counts = np.zeros((S, len(COUNTERS)), dtype=np.int64)
        self._rejecting = [False] * S  # per-sensor verdicts as plain lists (read one by one)
        self._reject_since = np.full(S, np.nan)
        # per accelerometer: last counts, identical run, prediction when it began, stuck,
        # implausible since, rejecting since
        self._acc_health = [[None, 0, None, False, None, None] for _ in range(Sa)]
        self._last_counts: list = [None] * Sa  # per accelerometer: its last counts (3 floats)
        self._acc_dirty = [False] * Sa  # a sensor whose health bookkeeping is not at rest
        # averages of the normalised innovations, on each of the detector's time scales
        self._shift_taus = np.array([st.shift_tau_s, st.shift_slow_tau_s])
        self._shift_thr = np.array([st.shift_threshold, st.shift_slow_threshold])
        self._shift = np.zeros((Sa, 2, 3))
        self._shift_t = np.full(Sa, np.nan)
        self._shift_cool = np.full(Sa, -np.inf)
        self._shift_stat = np.zeros(Sa)
        # per link accelerometer: the covariance of the lasting error the calibration leaves in
        # its normalised innovations (see _consider_update); the slip test allows for it
        self._shift_cal = np.zeros((len(self.link_names), 3, 3))
        self._shift_sum = np.zeros((Sa, 3))
        self._shift_n = np.zeros(Sa, dtype=np.int64)
        self._shift_block_t = float(t_s)
        self._reacq_log: dict[int, list[float]] = {}
        self._stuck = [False] * Sa
        self._dead = [False] * Sa
        self._acc_ring = _AccelRing(self.accel_streams, st.innovation_capacity)
        self._mag_ring = _InnovationRing(1, st.innovation_capacity)
        self._reacq_until = np.full(n, -np.inf)
        self._axis_deg = np.full(n, 90.0)
        self._flags = np.where(self._ambiguous, _AMBIGUOUS, 0).astype(np.int8)
        self._named = (None, None, (), ())  # (status codes, flags, their names): see estimate
        self._status_codes = np.full(S, STATUS_CODE["absent"], dtype=np.int8)
        self._hold = None
        self._ill = np.zeros(n, bool)
        self._sys_var = np.zeros(n)
        self._consider = np.zeros((n, self._spread_m))
        self._consider_t = None
        self._consider_q_enc = None
        self._consider_used: set[int] = set()
        self._locked = np.zeros(n, bool)
        self._observed = np.zeros(n, bool)
        self._obs_key = None
        self._obs_used_key = None
        self._obs_t = -np.inf
        self._mag_flags = (False, False)
        self._mag_recovery_t = -np.inf
        self._flags_t = -np.inf
        self._health_changed = True
        self._mag_sum = None
        self._mag_n = 0
        self._mag_t0 = float(t_s)
        self._mag_rot = np.eye(3)  # the base's turn since the averaging period began
        self._frame_cache = None
        # the tracker starts at the end of a still window: the chair stands still
        self._still_w = 0.0  # EMA of the bias-corrected gyro norm, rad/s
        self._still_mean = None  # EMA of the IMU accelerometer, g
        self._still_var = 0.0  # EMA of its squared deviation, g^2 (summed over axes)
        self._still = True
        self._imu_nis_ema = 3.0
        self._imu_nis_t = float(t_s)

    def _start_filter(self, q_enc: np.ndarray) -> None:
        L = self.layout
        self._q_enc = np.array(q_enc, dtype=float)
        if self._amb_q_enc is None:
            self._amb_q_enc = self._q_enc.copy()  # the candidates hold at these encoder angles
        x = self._x0.copy()
        x[L.offset] = self._q_startup - q_enc
        self._ukf = BatchedUKF(x, self._P0, self._points, angle_states=(L.yaw,))

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
    def x(self) -> np.ndarray:
        """The filter's state (read-only copy; names in :attr:`state_names`)."""
        self._check_filter()
        return self._ukf.x

    @property
    def P(self) -> np.ndarray:
        self._check_filter()
        return self._ukf.P

    # -- public update API -----------------------------------------------------------------
    def update(self, stream: str, t_s: float, values) -> Estimate | None:
        """Fuse one raw sample (counts, as the device gave them) of ``stream`` at ``t_s``.

        Returns the estimate after it, or None if the sample was dropped (out of order,
        not finite, saturated, or before the first encoder sample).
        """
        return self.update_instant(t_s, {stream: values})

    def update_instant(self, t_s: float, samples: Mapping[str, np.ndarray]) -> Estimate | None:
        """Fuse every sample of one instant together (one stacked update)."""
        self._check()
        unknown = [s for s in samples if s not in self._sidx and s != "imu_temp"]
        if unknown:
            raise KeyError(f"unknown stream {unknown[0]!r}; the tracker takes {list(self.sensor_names)}")
        t = float(t_s)
        if t < self._t - 1e-9:
            for s in samples:
                if s in self._sidx:
                    self._counts[self._sidx[s], C_OUT_OF_ORDER] += 1
            return None
        phys = {}
        temp = samples.get("imu_temp")
        if temp is not None:
            raw_t = float(np.ravel(temp)[0])
            if math.isfinite(raw_t):
                self._temperature_c = float(mpu9150_temperature_c(raw_t))
        for s, v in samples.items():
            if s == "imu_temp":
                continue
            i = self._sidx[s]
            self._counts[i, C_SAMPLES] += 1
            c = np.asarray(v, dtype=float).reshape(-1)
            cl = c.tolist()  # a handful of numbers: plain floats are cheaper to check
            if not all(map(math.isfinite, cl)):
                self._counts[i, C_NAN] += 1
                continue
            lo, hi = self._limits[s]
            if lo is not None and (min(cl) <= lo or max(cl) >= hi):
                self._counts[i, C_SATURATED] += 1
                self._seen[i], self._last_t[i] = True, t
                continue
            phys[s] = (c, self._physical(s, c[None])[0])
        enc = phys.get(ENC)
        if enc is not None:
            q_enc = enc[0] / self._cpr
            self._mark_used(ENC, t)
            if self._ukf is None:
                self._start_filter(q_enc if self._enc0 is None else self._enc0 / self._cpr)
            self._enc_diff.push(t, q_enc)
            self._frame_cache = None
        if self._ukf is None:
            return None
        gyro = None
        if GYRO in phys:
            gyro = self._R_0I @ phys[GYRO][1]
            self._gyro_diff.push(t, gyro)
            self._mark_used(GYRO, t)
        present = [s for s in self.accel_streams if s in phys]
        acc = None
        if present:
            sel = np.array([self._sidx[s] for s in present], dtype=np.int64)
            acc = (sel, np.stack([phys[s][0] for s in present]), np.stack([phys[s][1] for s in present]),
                   self._sel_info(sel))
        mag = phys.get(MAG)
        frame = self._frame_now(t) if acc is not None else None
        e = self._enc_diff.at(t)
        q_enc = self._q_enc if e is None else e[0]
        self._step(t, gyro, acc, None if mag is None else (mag[0], self._R_0I @ mag[1]), frame, q_enc)
        return self.estimate

    def _physical(self, s: str, counts: np.ndarray, temperature_c=None) -> np.ndarray:
        """Counts ``(N, k)`` to SI units, the config's calibrated sensor errors undone at
        ``temperature_c`` (scalar or ``(N,)``, °C; default the latest the IMU read)."""
        y = self._sm[s].from_counts(counts)
        u = self._undo.get(s)
        if u is None:
            return y
        c = u[1]
        slope = self._undo_per_c.get(s)
        if slope is not None:
            t_c = self._temperature_c if temperature_c is None else np.asarray(temperature_c, float)
            c = c + np.multiply.outer(t_c - self._temperature_ref_c, slope)
        return (y - c) @ u[0]

    def _mark_used(self, s: str, t: float) -> None:
        i = self._sidx[s]
        self._seen[i], self._last_t[i] = True, t
        self._counts[i, C_USED] += 1

    def _frame_now(self, t: float) -> Frames | None:
        """The mean pose's kinematics at ``t`` (kept for further samples of the same
        instant: the product of exponentials carries any change of the offsets). Compiled
        (:mod:`fusion.tracking.frame_kernels`); ``_frames_compiled`` False: :func:`make_frames`."""
        if self._frame_cache is not None and self._frame_cache[0] == t:
            return self._frame_cache[1]
        e = self._enc_diff.at(t)
        if e is None:
            return None
        L = self.layout
        x = self._ukf.x
        om = None if self._omega is None else self._omega - x[L.bias]
        g = self._gyro_diff.at(t)
        omd = None if g is None else g[1]
        if self._frames_compiled:
            fields = self._frame_consts.fields(e, x[L.offset], om, omd, self.settings.motion_compensation)
            frame = self._with_noise(tuple.__new__(Frames, fields))
        else:  # the NumPy reference
            z = np.zeros(3)
            frame = self._with_noise(make_frames(
                self.arm, self.accel_names, e[0][None], x[L.offset][None], e[1][None], e[2][None],
                (z if om is None else om)[None], (z if omd is None else omd)[None],
                self.settings.motion_compensation, self._joint_effects)).take(0)
        self._frame_cache = (t, frame)
        return frame

    # -- the step ---------------------------------------------------------------------------
    def _step(self, t: float, gyro: np.ndarray | None, acc, mag, frame: Frames | None,
              q_enc: np.ndarray) -> None:
        ukf = self._ukf
        self._q_enc = q_enc
        dt = t - self._t
        if dt > 0:
            w0 = self._omega if self._omega is not None else gyro
            w = None if w0 is None else (w0 if gyro is None else 0.5 * (w0 + gyro))
            ukf.predict(self._fx, self._Q(dt, w is not None), dt=dt, w=w)
            if self._mag_n and w is not None:
                b = self.layout.n_joints + 6  # gyro_bias
                bx, by, bz = ukf._x[b:b + 3].tolist()
                wx, wy, wz = w.tolist()
                self._mag_rot = self._mag_rot @ exp_so3_one(((wx - bx) * dt, (wy - by) * dt, (wz - bz) * dt))
        if gyro is not None:
            self._omega = gyro
        self._t = t
        if frame is None:
            acc = None
        self._update_still(dt, gyro, acc)
        if mag is not None:
            mi = self._sidx[MAG]
            self._seen[mi], self._last_t[mi] = True, t
            mag = self._mag_average(t, mag) if self._guard is not None and self._compass_usable else None
        if acc is not None or mag is not None:
            self._fuse(t, acc, mag, frame)
        if t - self._flags_t >= self.settings.observability_period_s or self._health_changed:
            self._update_flags(t)

    def _mag_average(self, t: float, mag):
        """The magnetometer is averaged over ``mag_fuse_period_s`` and fused as one heading:
        returns (count, mean field) when a period is complete, else None. Each sample is
        first turned, with the gyro, into the base's axes at the period's end, so that a
        turning chair does not smear the average."""
        m = self._mag_rot @ mag[1]  # in the base's axes at the period's start
        self._mag_sum = m if self._mag_n == 0 else self._mag_sum + m
        self._mag_n += 1
        if t - self._mag_t0 < self.settings.mag_fuse_period_s - 1e-9:
            return None
        out = (self._mag_n, self._mag_rot.T @ (self._mag_sum / self._mag_n))
        self._mag_n = 0
        self._mag_t0 = t
        self._mag_rot = np.eye(3)
        return out

    def _update_still(self, dt: float, gyro: np.ndarray | None, acc) -> None:
        """Exponential averages of the gyro and the IMU accelerometer: is the chair still?"""
        st = self.settings
        a = min(1.0, max(dt, 1e-4) / st.still_tau_s)
        xl = self._ukf._x.tolist()
        if gyro is not None:
            b = self.layout.n_joints + 6  # gyro_bias
            gx, gy, gz = gyro.tolist()
            wx, wy, wz = gx - xl[b], gy - xl[b + 1], gz - xl[b + 2]
            wn = math.sqrt(wx * wx + wy * wy + wz * wz)
            w0 = self._still_w
            self._still_w = wn if not math.isfinite(w0) else w0 + a * (wn - w0)
        if acc is not None and self._has_imu:
            _, _, f, (_, pos, _, _) = acc
            if pos >= 0:
                fi = f[pos].tolist()
                if self._still_mean is None:
                    self._still_mean = fi
                else:
                    d = [u - v for u, v in zip(fi, self._still_mean, strict=True)]
                    self._still_mean = [m + a * e for m, e in zip(self._still_mean, d, strict=True)]
                    self._still_var += a * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - self._still_var)
        # and the filter itself no longer sees the chair accelerate (a smooth stop looks
        # quiet to the averages before it is over)
        ax, ay, az = xl[self.layout.n_joints + 2:self.layout.n_joints + 5]  # accel_B
        self._still = (self._still_w < st.still_gyro_dps * DEG
                       and self._still_var < 3.0 * st.still_accel_g**2
                       and ax * ax + ay * ay + az * az < (2.0 * st.still_accel_g * G) ** 2)

    def _fx(self, X: np.ndarray, dt: float, w: np.ndarray | None) -> np.ndarray:
        """The process model, every sigma point at once (compiled:
        :func:`fusion.tracking.tracker_kernels.process_points`): the gyro (minus each point's bias)
        turns the attitude (midpoint rule on the Euler-angle rates), the base's
        acceleration decays, offsets and bias stay."""
        L = self.layout
        decay = self._accel_decay.get(dt)
        if decay is None:
            if len(self._accel_decay) > 64:
                self._accel_decay.clear()
            decay = self._accel_decay[dt] = math.exp(-dt / self.settings.base_accel_tau_s)
        have_w = w is not None
        return process_points(np.ascontiguousarray(X), dt, w if have_w else self._zeros3, have_w,
                              L.roll, L.yaw, L.n_joints + 6, L.n_joints + 2, decay)

    def _Q(self, dt: float, have_gyro: bool) -> np.ndarray:
        key = (round(dt * 1e9), have_gyro, self._still)  # dt to the nanosecond
        Q = self._Q_cache.get(key)
        if Q is None:
            if len(self._Q_cache) > 64:
                self._Q_cache.clear()
            Q = self._Q_cache[key] = self._make_Q(dt, have_gyro)
        return Q

    def _make_Q(self, dt: float, have_gyro: bool) -> np.ndarray:
        st, L = self.settings, self.layout
        q = np.zeros(L.size)
        q[L.offset] = (st.offset_random_walk_deg_per_sqrt_s * DEG) ** 2 * dt
        rw = st.gyro_noise_dps_per_sqrt_hz if have_gyro else st.attitude_random_walk_deg_per_sqrt_s
        q[L.roll] = q[L.pitch] = q[L.yaw] = (rw * DEG) ** 2 * dt
        q[L.accel] = st.base_accel_sigma_mps2**2 * (1.0 - np.exp(-2.0 * dt / st.base_accel_tau_s))
        if self._still:  # a parked chair's acceleration changes only when it sets off
            q[L.accel] *= st.still_accel_q_factor
        if not st.motion_compensation:
            q[L.accel] = 0.0
        q[L.bias] = (st.gyro_bias_random_walk_dps_per_sqrt_s * DEG) ** 2 * dt
        q[L.imu_bias] = st.imu_accel_bias_random_walk_g_per_sqrt_s**2 * dt
        return np.diag(q)

    # -- measurement models ---------------------------------------------------------------
    def _h_all(self, X, frame, sel, m_B, still=False):
        """Every measurement of one update at every sigma point, ``(N, m)``: the
        accelerometers ``sel`` (specific force in g), the still chair's zero acceleration,
        the heading residual ``yaw - tilt-compensated heading`` when ``m_B`` (the mean
        field in base axes) is given. Compiled:
        :func:`fusion.tracking.tracker_kernels.measurement_points` (its docstring has the model)."""
        L = self.layout
        n = L.n_joints
        if sel is None:
            sel = self._no_sel
        field = self._no_field if m_B is None else m_B
        shift = (self._field.declination_rad - np.pi) if m_B is not None else 0.0
        return measurement_points(np.ascontiguousarray(X), sel, self._links_i64, frame.axes, frame.offset_ref,
                                  frame.motion_mps2, frame.R_0S, self._imu_acc_index, L.roll, n + 2, L.yaw,
                                  n + 9, G, bool(still), field, shift)

    # -- the stacked update -----------------------------------------------------------------
    def _with_noise(self, frames: Frames) -> Frames:
        """``frames`` with the accelerometers' measurement variances at their instants
        (g²): the datasheet noise at the stream's rate with the unmodelled floor, a share of
        the predicted motion acceleration (the differentiator), and the differentiated
        gyro's error times the sensor's distance from the IMU."""
        st = self.settings
        wd_err = (self._omega_dot_noise + st.angular_accel_error_fraction * frames.omega_dot_norm) / G
        extra = (st.motion_model_fraction * frames.motion_g) ** 2 + (wd_err**2)[..., None] * frames.dist2_m2
        var = self._accel_var_g2 + extra[..., None]
        if self._time_var_s2 is not None and frames.omega_S_rad_s is not None:
            # a stamp known to sigma_t reads gravity turned by omega x g sigma_t (sensor axes)
            turn = cross(frames.omega_S_rad_s, frames.R_0S[..., 2, :])
            var = var + self._time_var_s2[:, None] * turn**2
        return frames._replace(accel_var_g2=var)

    def _sel_info(self, sel: np.ndarray) -> tuple:
        """For the accelerometers ``sel`` (cached): its key, the IMU's position in it (-1:
        absent), whether it is every accelerometer in order, and their datasheet variances."""
        key = sel.tobytes()
        info = self._sel_cache.get(key)
        if info is None:
            hit = np.flatnonzero(sel == self._imu_acc_index)
            full = bool(len(sel) == len(self.accel_streams) and np.array_equal(sel, np.arange(len(sel))))
            info = self._sel_cache[key] = (key, int(hit[0]) if len(hit) else -1, full,
                                           self._accel_var_g2[sel].copy())
        return info

    def _plan(self, sel_key: bytes, k: int, still: bool, mag: bool) -> GroupPlan:
        key = (sel_key, still, mag)
        plan = self._plan_cache.get(key)
        if plan is None:
            sel = np.frombuffer(sel_key, dtype=np.int64)
            groups = [MeasurementGroup(self.sensor_names[sel[i]], self._acc_rows[i], self._gate3)
                      for i in range(k)]
            if still:
                groups.append(MeasurementGroup("base_still", np.arange(3 * k, 3 * k + 3), self._gate3))
            if mag:
                groups.append(MeasurementGroup(MAG, np.array([3 * k + (3 if still else 0)]), self._gate1))
            plan = self._plan_cache[key] = GroupPlan(groups)
        return plan

    def _fuse(self, t: float, acc, mag, frame: Frames | None) -> None:
        """One update with every accelerometer and the magnetometer of this instant, each
        sensor gated on its own NIS; health checks and re-acquisition on the way."""
        st, ukf, L = self.settings, self._ukf, self.layout
        sel = m_B = check = None
        k = 0
        key, imu_pos, full = b"", -1, False
        if acc is not None:
            sel, counts, f, (key, imu_pos, full, _) = acc
            k = len(sel)
            if self._time_offset_s is not None and frame.omega_S_rad_s is not None:
                # a reading stamped late by dt saw gravity dt earlier: turn it to the stamp
                f = f - self._time_offset_s[sel][:, None] * cross(frame.omega_S_rad_s[sel], f)
            var_a = frame.accel_var_g2 if full else frame.accel_var_g2[sel]
        still = self._still and acc is not None and st.motion_compensation
        n_still = 3 if still else 0
        m = 3 * k + n_still + (mag is not None)
        z = np.zeros(m)
        var = np.empty(m)
        if k:
            z[:3 * k] = f.reshape(-1)
            var[:3 * k] = var_a.reshape(-1)
        if still:
            var[3 * k:3 * k + 3] = self._still_var3
        if mag is not None:
            m_count, m_B = mag
            x = ukf._x
            check = self._guard.check_field(m_B, up_from_tilt(x[L.roll], x[L.pitch]))
            v = self._sigma_psi**2 / m_count + self._iron_var
            if check.disturbed:
                v += check.doubt_rad(self._field) ** 2
            var[-1] = v
        plan = self._plan(key, k, still, mag is not None)
        angle_rows = (3 * k + n_still,) if mag is not None else ()
        inn = ukf.innovate(z, self._h_all, var, plan, angle_rows=angle_rows,
                           frame=frame, sel=sel, m_B=m_B, still=still)
        accept = inn.gate_ok.copy()
        gate_l = inn.gate_ok.tolist()
        set_off = still and not gate_l[k]
        imu_ok = True
        if k:
            if imu_pos >= 0:
                # the IMU's NIS, averaged over 0.2 s: a chair that sets off smoothly shows there
                # before any average of the raw readings does
                a = min(1.0, max(t - self._imu_nis_t, 0.0) / 0.2)
                self._imu_nis_t = t
                self._imu_nis_ema += a * (min(inn.nis.item(imu_pos), 100.0) - self._imu_nis_ema)
                imu_ok = gate_l[imu_pos] and self._imu_nis_ema < 6.0
            set_off |= self._still and not imu_ok
            # the slip detector listens only while the base behaves as modelled: the IMU
            # agrees and the chair is not wrenched about (a lurch is common to all sensors)
            calm = (imu_ok and self._imu_nis_ema < 4.5
                    and frame.omega_dot_norm.item() < st.shift_max_angular_accel_rad_s2)
        if set_off:
            # the chair set off: it is no longer still (the averages will say so later), and
            # its acceleration, held near zero while it stood, must be free to follow at once
            self._still = False
            self._still_var = max(self._still_var, 10.0 * st.still_accel_g**2)
            ukf.inflate(np.arange(L.accel.start, L.accel.stop), st.base_accel_sigma_mps2**2)
            inn = ukf.innovate(z, self._h_all, var, plan, angle_rows=angle_rows,
                               frame=frame, sel=sel, m_B=m_B, still=still)
            accept = inn.gate_ok.copy()
            if still:
                accept[k] = False
        if k:
            accept[:k] = self._accel_health(t, sel, counts, f, inn, var_a, shift=calm and not set_off,
                                            full=full, gate_l=None if set_off else gate_l)
            key = (key, accept[:k].tobytes())
            if key != self._obs_used_key or t - self._obs_t >= st.observability_period_s:
                self._obs_used_key, self._obs_t = key, t
                used = tuple(int(i) for i in sel[accept[:k]] if i < len(self.link_names))
                self._observability(frame, used, ukf._x)
        mask = None
        if mag is not None:
            passed = bool(inn.gate_ok[-1]) and not check.disturbed
            use = self._guard.record(t, passed, check.disturbed)
            if use and not passed:  # recovery: a doubtful field, once per interval
                use = t - self._mag_recovery_t >= st.heading.recovery_interval_s
                if use:
                    self._mag_recovery_t = t
            mi = self._sidx[MAG]
            self._mag_ring.add(t, inn.innovation[-1:], inn.S[-1:, -1:], inn.nis[-1], use,
                               count_stats=not check.disturbed)
            self._mag_flags = (check.disturbed, self._guard.last_recovering)
            self._rejecting[mi] = not use
            self._counts[mi, C_USED if use else C_REJECTED] += m_count
            accept[-1] = use
            # the heading corrects only yaw and the gyro's vertical bias: never the tilt (a
            # steel door must not tilt gravity), the arm, or the chair's acceleration
            mask = self._mag_mask.get(m)
            if mask is None:
                mask = np.ones((L.size, m))
                mask[:, -1] = 0.0
                mask[L.yaw, -1] = 1.0
                mask[L.bias.start + 2, -1] = 1.0
                self._mag_mask[m] = mask
        ukf.correct(inn, accept, self._hold, mask)

    def _accel_health(self, t: float, sel: np.ndarray, counts: np.ndarray, f: np.ndarray, inn,
                      var: np.ndarray, shift: bool = True, full: bool = False,
                      gate_l: list | None = None) -> np.ndarray:
        """Stuck, implausible (dead) and gate verdicts for the accelerometers ``sel``;
        returns which may enter the update. (A handful of sensors: plain Python is faster
        here than array calls.) ``full``: ``sel`` is every accelerometer, in order;
        ``gate_l``: ``inn.gate_ok`` as a list, when the caller has it."""
        st = self.settings
        k = len(sel)
        ix = slice(0, k) if full else sel  # plain slices where every sensor spoke
        if gate_l is None:
            gate_l = inn.gate_ok.tolist()
        zp = inn.z_pred[: 3 * k].reshape(k, 3)
        cl, last = counts.tolist(), self._last_counts
        if full:
            same = [c == b for c, b in zip(cl, last, strict=True)]
            last[:] = cl
        else:
            sl = sel.tolist()
            same = [c == last[s] for c, s in zip(cl, sl, strict=True)]
            for c, s in zip(cl, sl, strict=True):
                last[s] = c
        # |f| against |prediction|, sensor by sensor in plain floats (a handful of sensors)
        tol = st.plausible_tolerance_g
        implausible = [abs(math.sqrt(a * a + b * b + c * c) - math.sqrt(u * u + v * v + w * w)) > tol
                       for (a, b, c), (u, v, w) in zip(f.tolist(), zp.tolist(), strict=True)]
        gate_ok = inn.gate_ok[:k]
        self._seen[ix] = True
        self._last_t[ix] = t
        if not (any(same) or any(implausible) or any(self._acc_dirty)) and all(gate_l[:k]):
            # the usual case: every sensor healthy and consistent
            self._counts[ix, C_USED] += 1
            ok = usable = gate_ok
            all_usable = True
        else:
            ok, usable = self._accel_health_slow(t, sel, counts, zp, inn, var, same, implausible)
            all_usable = bool(usable.all())
        if all_usable or usable.any():
            which, Sb = inn.blocks[3]  # accelerometer groups come first, in order
            if all_usable:
                Su = Sb[:k]
                nu = inn.innovation[: 3 * k].reshape(k, 3)
                self._acc_ring.add(t, sel, nu, Su, inn.nis[:k], ok, finite=ok is gate_ok)
                u = ix
            else:
                ui = np.flatnonzero(usable)
                nu = inn.innovation[self._acc_rows[ui]]
                Su = Sb[ui]
                u = sel[ui]
                self._acc_ring.add(t, u, nu, Su, inn.nis[ui], ok[ui])
            # the slip detector sees the normalised innovations, averaged over 50 ms; not
            # while the IMU disagrees too (the chair lurched: that is common to all sensors)
            if shift:
                self._shift_sum[u] += nu / np.sqrt(np.diagonal(Su, axis1=1, axis2=2))
                self._shift_n[u] += 1
            else:  # paused: the averages keep what they had, and do not count the pause
                self._shift_t[u] = t
                self._shift_sum[u] = 0.0
                self._shift_n[u] = 0
            if t - self._shift_block_t >= 0.05 and self._shift_n.any():
                nl = len(self.link_names)
                have = (self._shift_n[:nl] > 0).nonzero()[0]
                if len(have):
                    n_ = self._shift_n[have]
                    self._detect_shift(t, slice(0, nl) if len(have) == nl else have,
                                       self._shift_sum[have] / n_[:, None], n_)
                self._shift_sum[:] = 0.0
                self._shift_n[:] = 0
                self._shift_block_t = t
        return ok

    def _accel_health_slow(self, t, sel, counts, zp, inn, var, same, implausible):
        """The sensor by sensor path: a stuck, implausible or rejected sample somewhere."""
        st = self.settings
        k = len(sel)
        zl = zp.tolist()
        gate = inn.gate_ok[:k].tolist()
        sd = np.sqrt(var).tolist()
        ok = np.zeros(k, dtype=bool)
        usable = np.zeros(k, dtype=bool)
        H = self._acc_health
        for i, s in enumerate(sel.tolist()):
            h = H[s]
            # implausible: far from the predicted magnitude (a dead or disconnected sensor)
            if implausible[i]:
                self._counts[s, C_IMPLAUSIBLE] += 1
                if h[4] is None:
                    h[4] = t
                dead = t - h[4] >= st.dead_after_s
                if dead != self._dead[s]:
                    self._dead[s] = dead
                    self._health_changed = True
                h[1], h[2] = 0, None
                self._acc_dirty[s] = True
                continue
            # stuck: identical counts in a row while the prediction moved
            if same[i]:
                h[1] += 1
                if h[2] is None:
                    h[2] = zl[i]
                moved = max(abs(a - b) / e for a, b, e in zip(zl[i], h[2], sd[i], strict=True)) > 6.0
                if h[1] + 1 >= st.stuck_samples and moved:
                    h[3] = True
            else:
                h[1], h[2], h[3] = 0, None, False
            if h[3] != self._stuck[s]:
                self._stuck[s] = h[3]
                self._health_changed = True
            if h[3]:
                self._counts[s, C_STUCK] += 1
                continue
            h[4] = None
            if self._dead[s]:
                self._dead[s] = False
                self._health_changed = True
            usable[i] = True
            if gate[i]:
                ok[i] = True
                self._counts[s, C_USED] += 1
                self._rejecting[s] = False
                h[5] = None
            else:
                self._counts[s, C_REJECTED] += 1
                self._rejecting[s] = True
                if h[5] is None:
                    h[5] = t
                elif t - h[5] >= st.reacquire_after_s:
                    self._reacquire(s, t)
                    h[5] = None
            self._acc_dirty[s] = (h[1] > 0 or h[2] is not None or h[3] or h[4] is not None
                                  or h[5] is not None or self._dead[s] or self._rejecting[s])
        return ok, usable

    def _detect_shift(self, t: float, which: np.ndarray | slice, nu_w: np.ndarray, count: np.ndarray) -> None:
        """A lasting shift of a link accelerometer's innovations (see ``shift_threshold``),
        on two time scales: a slip shows within a second, a slow drift of the counts over a
        few. ``nu_w`` are the normalised innovations averaged over ``count`` samples, for the
        link accelerometers ``which`` (indices, or a slice of them)."""
        last = self._shift_t[which]
        dt = np.where(np.isnan(last), 0.0, t - last)
        self._shift_t[which] = t
        a = np.minimum(1.0, dt[:, None] / self._shift_taus)  # (k, 2)
        ema = self._shift[which]  # (k, 2, 3)
        ema += a[:, :, None] * (nu_w[:, None, :] - ema)
        self._shift[which] = ema
        # the average of unit white noise (block means of n samples) has variance
        # a / (2 - a) / n; each time scale has its threshold
        pos = a > 0
        var_w = np.where(pos, a, 1.0) / ((2.0 - a) * count[:, None])  # (k, 2)
        stat = np.square(ema).sum(axis=2) / var_w
        stat[~pos] = 0.0  # a sensor heard for the first time: no average yet
        stat /= self._shift_thr
        # (whether the sensor agrees: no shift at all, see _slip_candidates)
        self._shift_stat[which] = worst = stat.max(axis=1)
        cal = self._shift_cal[which]  # (k, 3, 3)
        if cal.any():
            # the sensor's own calibration error lasts: it does not average away, so the
            # test that sets off a re-acquisition allows for it,
            # stat = ema^T (var_w I + C)^-1 ema (per time scale)
            M = cal[:, None] + var_w[:, :, None, None] * self._eye3
            stat = np.einsum("kti,kti->kt", ema, np.linalg.solve(M, ema[..., None])[..., 0])
            stat[~pos] = 0.0
            stat /= self._shift_thr
            worst = stat.max(axis=1)
        hit = worst > 1.0
        if hit.any():
            ids = np.arange(len(self._shift_t))[which]
            for s in ids[hit & (t >= self._shift_cool[which])]:
                self._reacquire(int(s), t)
                self._shift[s] = 0.0
                self._shift_cool[s] = t + self.settings.reacquiring_flag_s

    def _reacquire(self, i: int, t: float) -> None:
        """A sensor rejected for longer than a bump lasts: widen what it sees, read it again."""
        st, L = self.settings, self.layout
        self._counts[i, C_REACQUISITIONS] += 1
        if self.sensor_names[i] == IMU_ACC:
            idx = np.r_[L.roll, L.pitch, np.arange(L.accel.start, L.accel.stop)]
            self._ukf.inflate(idx, np.r_[(2 * DEG) ** 2, (2 * DEG) ** 2, np.full(3, 1.0)])
            return
        joints = self._slip_candidates(i, t)
        # a sensor that keeps disagreeing widens further each time (a large slip), up to
        # what an unread joint starts with
        recent = [u for u in self._reacq_log.get(i, []) if t - u < 10.0]
        recent.append(t)
        self._reacq_log[i] = recent
        sig = min(st.slip_sigma_deg * 2.0 ** (len(recent) - 1), st.unknown_joint_sigma_deg)
        self._ukf.inflate(joints, (sig * DEG) ** 2)
        self._reacq_until[joints] = t + st.reacquiring_flag_s

    def _slip_candidates(self, i: int, t: float) -> np.ndarray:
        """The joints a disagreeing sensor ``i`` may have slipped: those it sees that no
        agreeing link accelerometer sees too, and that gravity can read now (widening a
        held joint would only throw away what is known of it)."""
        sees = self._sees[i].copy()
        for s in range(len(self.link_names)):
            if s == i or not self._seen[s] or self._dead[s] or self._stuck[s]:
                continue
            # agreeing: nowhere near a shift of its own (a slip shows on every sensor beyond
            # the joint, some sooner than others)
            agrees = (not self._rejecting[s] and t >= self._shift_cool[s]
                      and self._shift_stat[s] < 0.25)
            if agrees and t - self._last_t[s] < self.settings.stale_after_s:
                sees &= ~self._sees[s]
        readable = sees & ~self._locked
        if readable.any():
            return np.flatnonzero(readable)
        fallback = self._sees[i] & ~self._locked
        return np.flatnonzero(fallback if fallback.any() else self._sees[i])

    # -- observability -----------------------------------------------------------------------
    def _observability(self, frame: Frames, used: tuple[int, ...], x: np.ndarray) -> None:
        """Each joint axis's angle to vertical, and the information the usable link
        accelerometers give about the offsets in ``observability_window_s``; sets the hold
        projection (Schmidt) and the inputs of the joint flags. Recomputed every
        ``observability_period_s`` and whenever the set of working sensors changes."""
        st, L, n = self.settings, self.layout, self.arm.n_joints
        key = self._obs_key
        if key is not None and key[1] == used and self._t - key[0] < st.observability_period_s:
            return
        self._obs_key = (self._t, used)
        sr, cr = math.sin(x[L.roll]), math.cos(x[L.roll])
        sp, cp = math.sin(x[L.pitch]), math.cos(x[L.pitch])
        up = np.array([-sp, sr * cp, cr * cp])
        c = np.abs(frame.axes @ up)
        self._axis_deg = np.degrees(np.arccos(np.minimum(c, 1.0)))
        locked = self._axis_deg < st.gimbal_lock_deg
        sel, coef = self._obs_sel(used)
        info = np.zeros((n, n))
        base = x[L.accel] + G * up
        if len(sel):
            v, W = self._info_rows(frame, sel, coef, base)
            info = W.T @ W
        lam, V, _ = lapack.dsyevd(info)
        V2 = V**2
        readable = lam > 1e-12
        if readable.all():
            self._achievable = np.sqrt(V2 @ (1.0 / lam))
        else:
            self._achievable = np.sqrt(V2[:, readable] @ (1.0 / lam[readable]))
            self._achievable[(V2[:, ~readable] > 1e-12).any(axis=1)] = np.inf
        self._observed = self._sees[sel].any(axis=0) if len(sel) else np.zeros(n, bool)
        self._locked = locked
        U = self._held_span(lam, V, locked)
        if U is not None:
            T = self._eye_state.copy()
            T[:n, :n] -= U @ U.T
            self._hold = T
        else:
            self._hold = None
        if self._spread_m:
            # the calibration's pull, over every link accelerometer used since the last time
            # (sensors read at instants of their own each make a set of one)
            self._consider_used.update(used)
            if self._consider_t is None:  # the first time: the startup read every one of them
                self._consider_used.update(range(len(self.link_names)))
            if self._consider_t is None or self._t - self._consider_t >= st.observability_period_s:
                both = tuple(sorted(self._consider_used))
                self._consider_used = set()
                if both:
                    sel_c, coef_c = self._obs_sel(both)
                    if both == tuple(used):
                        v_c, W_c, hold_c = v, W, self._hold
                    else:  # what the filter holds, judged on the information of them all
                        v_c, W_c = self._info_rows(frame, sel_c, coef_c, base)
                        lam_c, V_c, _ = lapack.dsyevd(W_c.T @ W_c)
                        U_c = self._held_span(lam_c, V_c, locked)
                        hold_c = None if U_c is None else self._eye_state[:n, :n] - U_c @ U_c.T
                    self._consider_update(frame, sel_c, v_c, base, W_c, hold_c)
        self._ill = np.sqrt(self._achievable**2 + self._sys_var) > st.sigma_limit_deg * DEG

    def _held_span(self, lam: np.ndarray, V: np.ndarray, locked: np.ndarray) -> np.ndarray | None:
        """An orthonormal basis (n, h) of the offsets' directions to hold, from the window's
        information (eigenvalues ``lam``, vectors ``V``) and the gimbal-locked joints; ``None``
        when nothing is held. A weak direction is held only where the window's information
        would not beat what the filter already knows along it (a joint still wide from
        startup takes weak readings)."""
        st, n = self.settings, self.arm.n_joints
        weak = lam < 1.0 / (st.sigma_limit_deg * DEG) ** 2
        if weak.any():
            prior_var = (V * (self._ukf._P[:n, :n] @ V)).sum(axis=0)
            weak &= lam * prior_var < 1.0
        any_weak, any_locked = bool(weak.any()), bool(locked.any())
        if not (any_weak or any_locked):
            return None
        # the span of the held directions (orthonormal already when of one kind)
        if not any_locked:
            return V[:, weak]
        if not any_weak:
            return self._eye_state[:n, :n][:, locked]
        B = np.concatenate([V[:, weak], self._eye_state[:n, :n][:, locked]], axis=1)
        w, U, _ = lapack.dsyevd(B @ B.T)
        return U[:, w > 1e-6]

    def _info_rows(self, frame: Frames, sel: np.ndarray, coef: np.ndarray, base: np.ndarray):
        """The used link accelerometers' acceleration less gravity ``v`` (S', 3: motion plus
        the base's ``base``) and their information rows ``W`` (3S', n): the Jacobian of each
        reading with respect to the offsets, over its sigma, times sqrt(rate * window)."""
        n = self.arm.n_joints
        v = frame.motion_mps2[sel] + base  # (S', 3)
        # df_s/d offset_j = R_0S^T (v_s x a_j) / g for the joints before the sensor's link;
        # v x a_j = -[a_j]x v, every (j, s) in one product
        Kv = (frame.K.reshape(3 * n, 3) @ v.T).reshape(n, 3, -1).transpose(2, 1, 0)  # (S', 3, n)
        W = (frame.R_0S[sel].transpose(0, 2, 1) @ Kv) * coef  # J / sigma * sqrt(rate * window)
        return v, W.reshape(-1, n)

    def _consider_update(self, frame: Frames, sel: np.ndarray, v: np.ndarray, base: np.ndarray,
                         W: np.ndarray, hold: np.ndarray | None) -> None:
        """The calibration's own uncertainty in the offsets, carried as the filter carries
        what it learnt (a consider, or Schmidt, sensitivity). Each of a calibrated config's
        correction spreads (every calibrated element moved by its sigma along a principal
        direction, ``StartupCorrection.spread``) is a constant error in a sensor's corrected
        reading; ``self._consider`` (n, m) is how far each spread has pulled the offsets'
        estimate so far. Since the last update the filter took the information ``A`` that
        the used readings gave (the window's ``W``, scaled to the time elapsed, without the
        held directions) and, with it, each spread's pull ``B``; the estimate moved by the
        same gain: ``S += P (B - A S)``, with P the filter's offset covariance, which already
        holds ``A``. What the filter learnt from a pose keeps that pose's calibration error
        until new readings replace it (a joint read once in a poorly conditioned pose, then
        held, keeps its doubt). Reported sigmas and the ``ill_conditioned`` flag include
        ``diag(S S^T)``; the filter's own covariance does not."""
        n = self.arm.n_joints
        t = self._t
        window = self.settings.observability_window_s
        # the first time: the startup's answer already rests on at least a window of these
        # readings (its still stretch), so it carries a whole window's pull
        first = self._consider_t is None
        dt = window if first else max(t - self._consider_t, 0.0)
        self._consider_t = t
        w = min(dt, window) / window
        if w <= 0.0:
            return
        k = len(sel)
        E = self._spread_errors(frame, sel, v, base).reshape(3 * k, -1)  # (3k, m)
        Wn = W if hold is None else W @ hold[:n, :n]
        A = (Wn.T @ Wn) * w
        B = (Wn.T @ E) * w
        # the information the filter held before these readings: its covariance's inverse
        # less what they gave (clipped: a gated reading gave less than the window says); the
        # first time, the startup's (the filter has taken a few of these readings already)
        P = self._P0[:n, :n] if first else self._ukf._P[:n, :n]
        lam, V = np.linalg.eigh(np.linalg.inv(P) - A)
        prior = (V * np.clip(lam, 0.0, None)) @ V.T
        S = self._consider
        if len(self._scale_joints):  # the true offsets moved with the encoders since
            if self._consider_q_enc is not None:
                travel = self._q_enc[self._scale_joints] - self._consider_q_enc[self._scale_joints]
                S[self._scale_joints, self._scale_cols] += self._scale_sigma * travel
            self._consider_q_enc = self._q_enc.copy()
        self._consider = np.linalg.solve(prior + A + 1e-12 * np.eye(n), prior @ S + B)
        self._sys_var = (self._consider**2).sum(axis=1)
        # what each spread leaves in the readings once the offsets have taken their pull: a
        # lasting shift of the innovations the slip test must not take for a slip
        links = sel < len(self.link_names)
        if links.any():
            D = E.reshape(k, 3, -1)[links]
            scale = self._accel_rate[sel[links]] * self.settings.observability_window_s
            self._shift_cal[sel[links]] = (D @ D.transpose(0, 2, 1)) / scale[:, None, None]

    def _spread_errors(self, frame: Frames, sel: np.ndarray, v: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Each correction spread's error in the used sensors' corrected readings, in the
        information rows' units (per sigma, times sqrt(rate * window)): (k, 3, m), the
        columns in ``self._spread_cols`` order. A link accelerometer's spread errs on its own
        rows; the IMU's turns the base's reference (tilt and the chair's acceleration) for
        every link accelerometer at once."""
        k = len(sel)
        E = np.zeros((k, 3, self._spread_m))
        R = frame.R_0S[sel]  # (k, 3, 3)
        f = np.einsum("kji,kj->ki", R, v) / G  # corrected readings, g (sensor axes)
        for i, s_idx in enumerate(sel.tolist()):
            stream = self.accel_streams[s_idx]
            floor = self._floor_cols.get(stream)
            if floor is not None:
                E[i, :, floor[0]] = floor[1] * self._eye3
            cols = self._spread_cols.get(stream)
            if cols is None:
                continue
            Lm, c = self.correction.maps[stream]
            raw = Lm @ f[i] + c
            M1, c1 = self._spread_stack[stream]  # (m_s, 3, 3), (m_s, 3)
            E[i, :, cols] = (M1 @ raw - np.einsum("mab,mb->ma", M1, c1) - f[i])
        cols = self._spread_cols.get(IMU_ACC) if self._has_imu else None
        if cols is not None:
            Lm, c = self.correction.maps[IMU_ACC]
            raw = Lm @ (self._R_0I.T @ base / G) + c
            y0 = np.linalg.solve(Lm, raw - c)
            M1, c1 = self._spread_stack[IMU_ACC]
            d = M1 @ raw - np.einsum("mab,mb->ma", M1, c1) - y0  # (m_s, 3)
            r = cross(y0 / np.linalg.norm(y0), d) @ self._R_0I.T  # the reference turned by
            # each link sensor's reading error: R^T (r x v) / g
            rv = cross(r[:, None, :], v[None, :, :])  # (m_s, k, 3)
            E[:, :, cols] = np.einsum("kji,mkj->kim", R, rv) / G
        scale = np.sqrt(self._accel_rate[sel] * self.settings.observability_window_s)
        return E / self._accel_sigma_g[sel][:, :, None] * scale[:, None, None]

    def _obs_sel(self, used: tuple[int, ...]):
        """The link accelerometers ``used`` as an index array, and the factor that turns
        their Jacobian rows into information rows: ``-sees / sigma * sqrt(rate * window) / g``
        (cached per set)."""
        hit = self._obs_cache.get(used)
        if hit is None:
            sel = np.array(used, dtype=int)
            w = np.sqrt(self._accel_rate[sel] * self.settings.observability_window_s)
            coef = -(self._sees[sel][:, None, :] / self._accel_sigma_g[sel][:, :, None])
            coef *= (w / G)[:, None, None]
            hit = self._obs_cache[used] = (sel, coef)
        return hit

    def _update_flags(self, t: float) -> None:
        """Sensor statuses and joint flags (the most severe condition wins), every
        ``observability_period_s`` and at once when a sensor's health changes. A few sensors
        and joints: plain Python."""
        st, n = self.settings, self.arm.n_joints
        self._flags_t = t
        self._health_changed = False
        stale_s = st.stale_after_s
        Sa = len(self.accel_streams)
        codes = []
        for i in range(len(self.sensor_names)):
            if not self._seen[i]:
                c = _ABSENT
            elif i < Sa and self._dead[i]:
                c = _DEAD
            elif i < Sa and self._stuck[i]:
                c = _STUCK
            elif t - self._last_t[i] > stale_s:
                c = _STALE
            elif self._rejecting[i]:
                c = _REJECTING
            else:
                c = 0
            codes.append(c)
        self._status_codes = np.array(codes, dtype=np.int8)
        if self._ukf is None:
            return
        nl = len(self.link_names)
        links = self._links_list
        # a joint is seen by a usable link accelerometer on a later link
        reach = max((links[i] for i in range(nl) if codes[i] <= _REJECTING), default=-1)
        sig = [math.sqrt(max(p, 0.0) + v)
               for p, v in zip(self._ukf._P.diagonal()[:n].tolist(), self._sys_var.tolist(), strict=True)]
        q = (self._q_enc + self._ukf._x[:n]).tolist()
        lim, margin = st.sigma_limit_deg * DEG, st.limit_margin_deg * DEG
        lo, hi = self._min_list, self._max_list
        flags = []
        for j in range(n):
            if self._ambiguous[j]:
                f = _AMBIGUOUS
            elif self._locked[j]:
                f = _GIMBAL
            elif reach <= j:
                f = _UNOBSERVED
            elif self._ill[j] and self._observed[j]:
                f = _ILL
            elif self._reacq_until[j] > t:
                f = _REACQ
            elif q[j] < lo[j] - margin or q[j] > hi[j] + margin:
                f = _OUT
            elif sig[j] > lim:
                f = _CONVERGING
            else:
                f = 0
            flags.append(f)
        self._flags = np.array(flags, dtype=np.int8)

    # -- a whole recording -------------------------------------------------------------------
    def run(self, rec: Recording, t_stop_s: float | None = None, truth: bool = True,
            block: int = 256, progress: Callable[[float], None] | None = None) -> TrackRun:
        """Fuse every sample of ``rec`` after the current time (up to ``t_stop_s``).

        The same steps as :meth:`update_instant`, with the work that does not depend on
        the filter done for many instants at once: counts to SI units, the saturation
        checks, the causal differentiators, and the kinematics of the mean pose (``block``
        instants per call, with the offsets and gyro bias of the block's start; the offsets'
        drift since then is carried exactly by the product of exponentials, and enters the
        motion term only to first order). With ``truth`` and truth streams in ``rec``,
        errors and NEES are kept too. ``progress(fraction_done)`` is called after every block.
        """
        import time as _time

        self._check()
        st, L, n = self.settings, self.layout, self.arm.n_joints
        t0_wall = _time.perf_counter()
        raw = {s: rec.get(s) for s in self.sensor_names if rec.get(s) is not None and len(rec.get(s))}
        if ENC not in raw:
            raise ValueError("the recording has no encoder stream 'enc': nothing to track")
        self.set_rates({s: (v.rate_hz or 100.0) for s, v in raw.items()})
        t_from = self._t
        t_stop = np.inf if t_stop_s is None else float(t_stop_s)
        # only what this run needs: its span, and a little history for the differentiators
        raw = {s: v.between(t_from - 2.0, t_stop + 1e-6) for s, v in raw.items()}
        raw = {s: v for s, v in raw.items() if len(v)}
        if ENC not in raw:
            raise ValueError(f"the recording has no encoder sample after t = {t_from:.3f} s")
        times = np.unique(np.concatenate([v.t_s for v in raw.values()]))
        times = times[(times > t_from + 1e-9) & (times <= t_stop + 1e-9)]
        T = len(times)
        rows, phys, valid = {}, {}, {}
        temp = rec.get("imu_temp")
        temp_t = temp_c = None
        if temp is not None and len(temp) and self._undo_per_c:
            temp_t = temp.t_s
            temp_c = mpu9150_temperature_c(temp.values[:, 0])

        def temperature_at(t: np.ndarray):
            """The IMU's latest temperature reading at each time (the tracker's, before any)."""
            if temp_t is None:
                return None
            k = np.searchsorted(temp_t, t, side="right") - 1
            return np.where(k >= 0, temp_c[np.maximum(k, 0)], self._temperature_c)
        for s, v in raw.items():
            rows[s] = _rows_at(times, v.t_s)
            c = v.values.astype(float)
            ok = ~self._sm[s].saturated(c).any(axis=1)
            valid[s] = ok
            phys[s] = self._physical(s, c, temperature_at(v.t_s))
            used = rows[s][rows[s] >= 0]
            i = self._sidx[s]
            self._counts[i, C_SAMPLES] += len(used)
            self._counts[i, C_SATURATED] += int((~ok[used]).sum())
        enc = raw[ENC]
        q_enc_all = enc.values / self._cpr
        enc_fit = causal_fits(enc.t_s, q_enc_all, st.encoder_window, st.encoder_order)
        gyro_B = gyro_fit = None
        if GYRO in raw:
            gyro_B = phys[GYRO] @ self._R_0I.T
            gyro_fit = causal_fits(raw[GYRO].t_s, gyro_B, st.gyro_window, st.gyro_order)
        mag_B = phys[MAG] @ self._R_0I.T if MAG in raw else None
        if self._ukf is None:  # the offsets are fixed by the first encoder sample
            k = min(int(np.searchsorted(enc.t_s, t_from - 1e-9)), len(enc) - 1)
            self._start_filter(q_enc_all[k] if self._enc0 is None else self._enc0 / self._cpr)
        # encoder angles and rates at every instant: the latest sample's fit, extrapolated
        ie = np.searchsorted(enc.t_s, times + 1e-9) - 1
        has_enc = ie >= 0
        ie = np.maximum(ie, 0)
        dt_e = np.where(has_enc, times - enc.t_s[ie], 0.0)[:, None]
        v0, d1, d2 = enc_fit[ie, 0], enc_fit[ie, 1], enc_fit[ie, 2]
        q_t = v0 + d1 * dt_e + 0.5 * d2 * dt_e**2
        qd_t = d1 + d2 * dt_e
        qdd_t = d2
        if gyro_B is not None:
            ig = np.searchsorted(raw[GYRO].t_s, times + 1e-9) - 1
            has_g = (ig >= 0)[:, None]
            ig = np.maximum(ig, 0)
            w_t = np.where(has_g, gyro_B[ig], 0.0)
            wd_t = np.where(has_g, gyro_fit[ig, 1], 0.0)
        else:
            w_t = wd_t = np.zeros((T, 3))
        acc_streams = [s for s in self.accel_streams if s in raw]
        acc_idx = np.array([self._sidx[s] for s in acc_streams], dtype=np.int64)
        acc_info = self._sel_info(acc_idx)
        # per instant: which accelerometers have a valid sample, as (T, Sa) row indices
        acc_rows = np.stack([np.where(rows[s] >= 0, rows[s], -1) for s in acc_streams], 1) \
            if acc_streams else np.full((T, 0), -1)
        acc_ok = np.stack([(rows[s] >= 0) & valid[s][np.maximum(rows[s], 0)] for s in acc_streams], 1) \
            if acc_streams else np.zeros((T, 0), bool)
        acc_seen = acc_rows >= 0
        # every instant's accelerometer samples as (T, Sa, 3) arrays: one index per step
        Sa = len(acc_streams)
        acc_counts = np.zeros((T, Sa, 3))
        acc_phys = np.zeros((T, Sa, 3))
        for j, s in enumerate(acc_streams):
            have = acc_rows[:, j] >= 0
            acc_counts[have, j] = raw[s].values[acc_rows[have, j]]
            acc_phys[have, j] = phys[s][acc_rows[have, j]]
        all_ok = acc_ok.all(axis=1)
        enc_rows = rows[ENC]
        gyro_rows = rows.get(GYRO)
        gyro_ok = None if gyro_rows is None else (gyro_rows >= 0) & valid[GYRO][np.maximum(gyro_rows, 0)]
        mag_rows = rows.get(MAG)
        mag_ok = None if mag_rows is None else (mag_rows >= 0) & valid[MAG][np.maximum(mag_rows, 0)]
        mag_counts = raw[MAG].values if MAG in raw else None
        has_truth = truth and rec.get("true_q") is not None and rec.get("true_base") is not None
        out = _RunArrays(T, n, len(self.sensor_names), keep_cov=has_truth, size=L.size)
        i_enc, i_gyro = self._sidx[ENC], self._sidx.get(GYRO)
        for b0 in range(0, T, block):
            b1 = min(T, b0 + block)
            x = self._ukf.x
            frames = self._with_noise(make_frames(
                self.arm, self.accel_names, q_t[b0:b1], x[L.offset], qd_t[b0:b1], qdd_t[b0:b1],
                w_t[b0:b1] - x[L.bias], wd_t[b0:b1], st.motion_compensation, self._joint_effects))
            # the block's per-instant flags as plain Python values (cheaper to test one by one)
            t_l = times[b0:b1].tolist()
            enc_l = (enc_rows[b0:b1] >= 0).tolist()
            gyro_l = [-1] * (b1 - b0) if gyro_ok is None else \
                np.where(gyro_ok[b0:b1], gyro_rows[b0:b1], -1).tolist()
            mag_l = [-1] * (b1 - b0) if mag_ok is None else \
                np.where(mag_ok[b0:b1], mag_rows[b0:b1], -1).tolist()
            all_l = all_ok[b0:b1].tolist()
            for i in range(b0, b1):
                r = i - b0
                t = t_l[r]
                if enc_l[r]:
                    self._seen[i_enc], self._last_t[i_enc] = True, t
                    self._counts[i_enc, C_USED] += 1
                gyro = None
                kg = gyro_l[r]
                if kg >= 0:
                    gyro = gyro_B[kg]
                    self._seen[i_gyro], self._last_t[i_gyro] = True, t
                    self._counts[i_gyro, C_USED] += 1
                acc = None
                if all_l[r]:
                    acc = (acc_idx, acc_counts[i], acc_phys[i], acc_info)
                else:
                    ok = acc_ok[i]
                    if ok.any():
                        sel = acc_idx[ok]
                        acc = (sel, acc_counts[i, ok], acc_phys[i, ok], self._sel_info(sel))
                    if acc_seen[i].any():  # saturated samples: the sensors did speak
                        self._seen[acc_idx[acc_seen[i]]] = True
                        self._last_t[acc_idx[acc_seen[i]]] = t
                mag = None
                km = mag_l[r]
                if km >= 0:
                    mag = (mag_counts[km], mag_B[km])
                frame = frames.take(r) if acc is not None else None
                self._step(t, gyro, acc, mag, frame, q_t[i])
                out.record(self, i)
            if progress is not None:
                progress(b1 / T)
        if gyro_B is not None:
            k = int(np.searchsorted(raw[GYRO].t_s, self._t + 1e-9)) - 1
            if k >= 0:
                self._omega = gyro_B[k]
        # the online differentiators continue from the recording's last samples
        self._prime(self._enc_diff, enc.t_s, q_enc_all, self._t)
        if gyro_B is not None:
            self._prime(self._gyro_diff, raw[GYRO].t_s, gyro_B, self._t)
        elapsed = _time.perf_counter() - t0_wall
        truth_q = rec.get("true_q") if truth else None
        truth_b = rec.get("true_base") if truth else None
        tq = truth_at(truth_q, times) if truth_q is not None and len(truth_q) else None
        tb = truth_at(truth_b, times, angles=True) if truth_b is not None and len(truth_b) else None
        return out.finish(self, times, elapsed, tq, tb)

    @staticmethod
    def _prime(diff: CausalDifferentiator, t: np.ndarray, y: np.ndarray, t_now: float) -> None:
        k = int(np.searchsorted(t, t_now + 1e-9))
        for j in range(max(0, k - diff.window), k):
            diff.push(float(t[j]), y[j])

    def prime(self, rec: Recording) -> None:
        """Fill the causal differentiators with the recording's samples up to the current
        time (the still window), so that the first instants have a full window."""
        self._check()
        enc = rec.get(ENC)
        if enc is not None and len(enc):
            self._prime(self._enc_diff, enc.t_s, enc.values / self._cpr, self._t)
        g = rec.get(GYRO)
        if g is not None and len(g):
            wB = self._sm[GYRO].from_counts(g.values) @ self._R_0I.T
            self._prime(self._gyro_diff, g.t_s, wB, self._t)
            k = int(np.searchsorted(g.t_s, self._t + 1e-9)) - 1
            if k >= 0:
                self._omega = wB[k]

    # -- restart -----------------------------------------------------------------------------
    SNAPSHOT_FORMAT = "armfusion.tracker/1"

    def snapshot(self) -> dict:
        """The tracker's state as a JSON-ready dict: enough to resume after a restart of the
        process without a new startup calibration, provided the encoders kept counting."""
        self._check_filter()
        g = self._guard
        return {
            "format": self.SNAPSHOT_FORMAT,
            "arm": self.arm.name,
            "state_names": list(self.state_names),
            "t_s": self._t,
            "x": self._ukf._x.tolist(),
            "P": self._ukf._P.tolist(),
            "q_enc": self._q_enc.tolist(),
            "omega": None if self._omega is None else np.asarray(self._omega).tolist(),
            "encoder_fit": self._enc_diff.snapshot(),
            "gyro_fit": self._gyro_diff.snapshot(),
            "field": None if self._field is None else {
                "magnitude_ut": self._field.magnitude_ut, "dip_rad": self._field.dip_rad,
                "declination_rad": self._field.declination_rad},
            "guard": None if g is None else g.snapshot(),
            "counters": self._counts.tolist(),
            "still": [self._still_w, self._still_mean, self._still_var, self._still],
            "shift": [self._shift.tolist(), np.nan_to_num(self._shift_t, nan=-1e300).tolist()],
            "consider": self._consider.tolist(),
            "ambiguous": {"joints": self._ambiguous.tolist(),
                          "candidates_rad": [list(c) for c in self._amb_candidates],
                          "q_enc": None if self._amb_q_enc is None else self._amb_q_enc.tolist()},
        }

    def restore(self, snap: Mapping) -> None:
        """Resume from :meth:`snapshot` (replaces :meth:`initialise`)."""
        if snap.get("format") != self.SNAPSHOT_FORMAT:
            raise ValueError(f"not a tracker snapshot (format {snap.get('format')!r}, expected "
                             f"{self.SNAPSHOT_FORMAT!r})")
        if snap.get("arm") != self.arm.name or tuple(snap.get("state_names", ())) != self.state_names:
            raise ValueError(f"the snapshot is for arm {snap.get('arm')!r} with another state; this "
                             f"tracker is for {self.arm.name!r}")
        n, L = self.arm.n_joints, self.layout
        fld = snap.get("field")
        field_ref = None if fld is None else FieldReference(fld["magnitude_ut"], fld["dip_rad"],
                                                            fld["declination_rad"])
        x = np.array(snap["x"], dtype=float)
        P = np.array(snap["P"], dtype=float)
        dummy = StartupResult(
            joints=tuple(_JointStub(nm) for nm in self.arm.joint_names), roll_rad=0.0, pitch_rad=0.0,
            roll_sigma_rad=0.0, pitch_sigma_rad=0.0, residual_rms_g=0.0, chi2_per_dof=0.0,
            q_rad=np.zeros(n), covariance=np.eye(n + 2), branches_rad=np.zeros((1, n)), method="restore")
        self.initialise(dummy, float(snap["t_s"]),
                        imu=ImuStill(x[L.bias], 1e-3, None, None, field_ref))
        q_enc = np.array(snap["q_enc"], dtype=float)
        self._q_enc = q_enc
        self._ukf = BatchedUKF(x, P, self._points, angle_states=(L.yaw,))
        self._omega = None if snap.get("omega") is None else np.array(snap["omega"], dtype=float)
        self._enc_diff.restore(snap["encoder_fit"])
        self._gyro_diff.restore(snap["gyro_fit"])
        if self._guard is not None and snap.get("guard") is not None:
            self._guard.restore(snap["guard"])
        self._counts = np.array(snap["counters"], dtype=np.int64)
        if "still" in snap:
            self._still_w, self._still_mean, self._still_var, self._still = snap["still"]
        if "shift" in snap:
            self._shift = np.array(snap["shift"][0], dtype=float)
            st_ = np.array(snap["shift"][1], dtype=float)
            self._shift_t = np.where(st_ < -1e299, np.nan, st_)
        amb = snap.get("ambiguous")
        if amb is not None and len(amb.get("joints", ())) == n:  # rival branches still open
            self._ambiguous = np.array(amb["joints"], dtype=bool)
            self._amb_candidates = tuple(tuple(float(a) for a in c) for c in amb["candidates_rad"])
            self._amb_q_enc = None if amb.get("q_enc") is None else np.array(amb["q_enc"], float)
            self._amb_half_gap = np.array([(max(c) - min(c)) / 2.0 if len(c) > 1 else 0.0
                                           for c in self._amb_candidates])
            self._flags = np.where(self._ambiguous, _AMBIGUOUS, self._flags).astype(np.int8)
        consider = np.array(snap.get("consider", []), dtype=float)
        if consider.shape == self._consider.shape:  # the calibration's pull on the offsets so far
            self._consider = consider
            self._sys_var = (consider**2).sum(axis=1)
            self._consider_t = float(snap["t_s"])

    # -- results ---------------------------------------------------------------------------
    def ambiguity(self) -> dict[str, tuple[float, ...]]:
        """Per joint the startup left ``ambiguous``: its candidate angles now (the startup's,
        moved by what the encoders counted since), rad. Empty once every branch is known."""
        if not self._ambiguous.any():
            return {}
        moved = (np.zeros(self.arm.n_joints) if self._amb_q_enc is None
                 else self._q_enc - self._amb_q_enc)
        return {self.arm.joint_names[j]: tuple(float(a + moved[j]) for a in self._amb_candidates[j])
                for j in np.flatnonzero(self._ambiguous)}

    def q_enc_now(self) -> np.ndarray:
        """The encoders' angles (counts / counts per rad) at the last fused instant."""
        return self._q_enc.copy()

    @property
    def estimate(self) -> Estimate:
        """The estimate at the last fused instant."""
        self._check_filter()
        L, n = self.layout, self.arm.n_joints
        x, sig = self._ukf.x, self._ukf.sigma.copy()
        sig[:n] = np.sqrt(sig[:n] ** 2 + self._sys_var)  # the calibration's own uncertainty
        if self._ambiguous.any():  # the sigma of a joint with rival branches covers them
            sig[:n] = np.maximum(sig[:n], self._amb_half_gap)
        named = self._named
        if named[0] is not self._status_codes or named[1] is not self._flags:
            # (both arrays are replaced, never written in place, when the flags are updated)
            codes = self._status_codes.tolist()
            status = tuple((s, SENSOR_STATUS[c]) for s, c in zip(self.sensor_names, codes, strict=True))
            self._named = named = (self._status_codes, self._flags, status,
                                   tuple(JOINT_FLAGS[f] for f in self._flags.tolist()))
        return Estimate(
            t_s=self._t, q_rad=_ro(self._q_enc + x[:n]), sigma_rad=_ro(sig[:n]),
            flags=named[3],
            roll_rad=float(x[L.roll]), pitch_rad=float(x[L.pitch]), yaw_rad=float(x[L.yaw]),
            attitude_sigma_rad=_ro(sig[[L.roll, L.pitch, L.yaw]]), gyro_bias_rad_s=_ro(x[L.bias]),
            axis_to_vertical_deg=_ro(self._axis_deg), sensors=named[2],
            magnetic_disturbance=self._mag_flags[0], magnetic_recovery=self._mag_flags[1],
            joint_names=self.arm.joint_names,
        )

    def counters(self) -> dict[str, dict[str, int]]:
        """Per sensor: samples, used, rejected, nan, saturated, implausible, stuck,
        out_of_order, reacquisitions."""
        self._check()
        return {s: {c: int(self._counts[i, k]) for k, c in enumerate(COUNTERS)}
                for i, s in enumerate(self.sensor_names)}

    def innovations(self, sensor: str) -> InnovationLog:
        """The innovations kept for ``sensor`` (a link accelerometer, ``imu_acc``, ``imu_mag``):
        every one that was tested against the gate, accepted or not."""
        self._check()
        if sensor == MAG and self._has_imu:
            return self._mag_ring.log(sensor)
        if sensor not in self.accel_streams:
            kept = list(self.accel_streams) + ([MAG] if self._has_imu else [])
            raise KeyError(f"no innovations for {sensor!r}; kept for {kept}")
        return self._acc_ring.log(sensor)

    def nis_stats(self) -> dict[str, tuple[float, int, int]]:
        """Per sensor: (mean NIS, count, degrees of freedom) over its healthy samples."""
        self._check()
        r = self._acc_ring
        cnt = r.counts
        out = {s: (float(r.nis_sum[i] / cnt[i]) if cnt[i] else float("nan"),
                   int(cnt[i]), 3) for i, s in enumerate(self.accel_streams)}
        if self._has_imu:
            m = self._mag_ring
            out[MAG] = (m.nis_sum / m.nis_count if m.nis_count else float("nan"), m.nis_count, 1)
        return out


# --------------------------------------------------------------------------------------
# a whole run
def _rows_at(times: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Index into ``t_s`` of the sample at each of ``times`` (-1 where there is none)."""
    pos = np.searchsorted(t_s, times)
    pos_c = np.minimum(pos, len(t_s) - 1)
    return np.where(np.abs(t_s[pos_c] - times) < 1e-9, pos_c, -1)


def truth_at(truth: Stream, times: np.ndarray, angles: bool = False) -> np.ndarray:
    """The truth at each of ``times``, (T, k): linear between the truth's own samples (a
    live recording's instants fall between the simulator's grid), NaN outside its span or
    across a gap of more than two of its periods. ``angles``: interpolated unwrapped."""
    t, v = truth.t_s, truth.values
    if angles:
        v = np.unwrap(v, axis=0)
    out = np.full((len(times), v.shape[1]), np.nan)
    if len(t) < 2:
        if len(t) == 1:
            out[np.abs(times - t[0]) < 1e-9] = v[0]
        return out
    i = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
    span = t[i + 1] - t[i]
    period = float(np.median(np.diff(t)))
    ok = (times >= t[0] - 1e-9) & (times <= t[-1] + 1e-9) & (span <= 2.0 * period + 1e-9)
    w = np.clip((times - t[i]) / np.where(span > 0, span, 1.0), 0.0, 1.0)[:, None]
    val = v[i] * (1.0 - w) + v[i + 1] * w
    out[ok] = val[ok]
    return out


class _RunArrays:
    """Per fused instant: the state, the diagonal of its covariance, the encoder angles and the
    flags, as the run goes (a few row copies per step); angles and sigmas are made from them
    at the end. The joint flags, sensor statuses and the calibration's share of the joints'
    variance change only now and then (the tracker replaces those arrays when they do): they
    are kept where they changed and spread over the instants at the end."""

    def __init__(self, T: int, n: int, S: int, keep_cov: bool = True, size: int | None = None):
        size = n + 9 if size is None else size
        self.x = np.full((T, size), np.nan)
        self.var = np.full((T, size), np.nan)
        self.q_enc = np.full((T, n), np.nan)
        self.flags = np.zeros((T, n), dtype=np.int8)
        self.magnetic = np.zeros(T, dtype=np.int8)
        self.status = np.zeros((T, S), dtype=np.int8)
        self.sys_var = np.zeros((T, n))
        self.P = np.full((T, n + 3, n + 3), np.nan) if keep_cov else None
        self._P_rows = None if self.P is None else self.P.reshape(T, (n + 3) ** 2)
        self.T = T
        self._flat = None
        self._held = (None, None, None)
        self._changes: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self._last = -1

    def record(self, tr: Tracker, i: int) -> None:
        ukf = tr._ukf
        P = ukf._P
        self.x[i] = ukf._x
        self.var[i] = P.diagonal()
        self.q_enc[i] = tr._q_enc
        held = self._held
        if tr._flags is not held[0] or tr._status_codes is not held[1] or tr._sys_var is not held[2]:
            self._held = held = (tr._flags, tr._status_codes, tr._sys_var)
            self._changes.append((i, *held))
        mf = tr._mag_flags
        if mf[0] or mf[1]:
            self.magnetic[i] = (1 if mf[0] else 0) | (2 if mf[1] else 0)
        if self.P is not None:  # for the NEES
            if self._flat is None:
                ix = tr._nees_idx
                self._flat = (ix[:, None] * P.shape[1] + ix[None, :]).reshape(-1)
            P.take(self._flat, out=self._P_rows[i])
        self._last = i

    def _spread_changes(self) -> None:
        """The flags, statuses and the calibration's share at every recorded instant, and that
        share added to the joints' variances."""
        ends = [c[0] for c in self._changes[1:]] + ([self._last + 1] if self._changes else [])
        for (i, flags, status, sys_var), j in zip(self._changes, ends, strict=True):
            self.flags[i:j] = flags
            self.status[i:j] = status
            self.sys_var[i:j] = sys_var
        n = self.sys_var.shape[1]
        self.var[:, :n] += self.sys_var  # the calibration's own uncertainty
        if self.P is not None:
            self.P[:, np.arange(n), np.arange(n)] += self.sys_var

    def _arrays(self, tr: Tracker) -> None:
        L, n = tr.layout, tr.arm.n_joints
        self._spread_changes()
        d = np.sqrt(np.maximum(self.var, 0.0))
        self.q = self.q_enc + self.x[:, :n]
        self.sigma = d[:, :n]
        self.rpy = self.x[:, tr._att_idx]
        self.rpy_sigma = d[:, tr._att_idx]
        self.bias = self.x[:, L.bias]

    def finish(self, tr: Tracker, times, elapsed, truth_q: np.ndarray | None,
               truth_b: np.ndarray | None) -> TrackRun:
        """``truth_q``, ``truth_b``: the truth at each instant (NaN where there is none)."""
        n = tr.arm.n_joints
        self._arrays(tr)
        q_err = yaw_err = nees = None
        if truth_q is not None:
            q_err = self.q - truth_q
        if truth_b is not None:
            att_err = wrap_angle(self.rpy - truth_b)
            yaw_err = att_err[:, 2]
            if q_err is not None and self.P is not None:
                e = np.concatenate([q_err, att_err], axis=1)
                good = np.all(np.isfinite(e), axis=1)
                nees = np.full(self.T, np.nan)
                if good.any():
                    nees[good] = np.einsum("ti,ti->t", e[good],
                                           np.linalg.solve(self.P[good], e[good][..., None])[..., 0])
        return TrackRun(
            joint_names=tr.arm.joint_names, sensor_names=tr.sensor_names, t_s=np.asarray(times),
            q_rad=self.q, sigma_rad=self.sigma, flags=self.flags, rpy_rad=self.rpy,
            rpy_sigma_rad=self.rpy_sigma, gyro_bias_rad_s=self.bias, magnetic=self.magnetic,
            sensor_status=self.status, elapsed_s=elapsed, counters=tr.counters(), nis=tr.nis_stats(),
            q_error_rad=q_err, yaw_error_rad=yaw_err, nees=nees, nees_dof=n + 3,
        )


@dataclass(frozen=True)
class TrackRun:
    """A run over a recording: per fused instant (``t_s (T,)``) the joint angles, their
    sigma and flag codes (:data:`JOINT_FLAGS`), the base attitude and its sigma, the gyro
    bias, magnetic flags (bit 1: disturbance, bit 2: recovery), sensor status codes
    (:data:`SENSOR_STATUS`); with truth, the errors and the NEES (joints, roll, pitch, yaw)."""

    joint_names: tuple[str, ...]
    sensor_names: tuple[str, ...]
    t_s: np.ndarray
    q_rad: np.ndarray
    sigma_rad: np.ndarray
    flags: np.ndarray
    rpy_rad: np.ndarray
    rpy_sigma_rad: np.ndarray
    gyro_bias_rad_s: np.ndarray
    magnetic: np.ndarray
    sensor_status: np.ndarray
    elapsed_s: float
    counters: dict
    nis: dict
    q_error_rad: np.ndarray | None = None
    yaw_error_rad: np.ndarray | None = None
    nees: np.ndarray | None = None
    nees_dof: int = 0

    @property
    def steps(self) -> int:
        return int(len(self.t_s))

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.elapsed_s if self.elapsed_s > 0 else float("nan")

    def flags_seen(self) -> dict:
        """How many instants each joint showed each flag, and each sensor each status."""
        joints = {nm: _tally(self.flags[:, j], JOINT_FLAGS) for j, nm in enumerate(self.joint_names)}
        sensors = {nm: _tally(self.sensor_status[:, i], SENSOR_STATUS)
                   for i, nm in enumerate(self.sensor_names)}
        mag = {"magnetic_disturbance": int(np.sum(self.magnetic & 1 > 0)),
               "magnetic_recovery": int(np.sum(self.magnetic & 2 > 0))}
        return {"joints": joints, "sensors": sensors, "heading": mag}

    def summary(self, after_s: float = 60.0, t0_s: float | None = None) -> dict:
        """The JSON summary (see docs/tracking.md): steps, speed, rejections, flags seen, and
        with truth the RMS errors after ``after_s`` (from ``t0_s``, default the first
        instant), NEES and NIS means with their 95 % chi-square bounds."""
        t0 = (float(self.t_s[0]) if len(self.t_s) else 0.0) if t0_s is None else t0_s
        d: dict = {
            "steps": self.steps,
            "duration_s": float(self.t_s[-1] - self.t_s[0]) if self.steps > 1 else 0.0,
            "elapsed_s": self.elapsed_s,
            "steps_per_s": self.steps_per_s,
            "rejections": {s: c["rejected"] for s, c in self.counters.items()},
            "skipped": {s: {k: c[k] for k in ("nan", "saturated", "implausible", "stuck", "out_of_order")}
                        for s, c in self.counters.items()},
            "reacquisitions": {s: c["reacquisitions"] for s, c in self.counters.items()
                               if c["reacquisitions"]},
            "flags_seen": self.flags_seen(),
        }
        nis = {}
        for s, (mean, count, dof) in self.nis.items():
            if count:
                lo, hi = chi2.ppf([0.025, 0.975], count * dof) / count
                nis[s] = {"mean": mean, "dof": dof, "count": count, "bounds_95": [float(lo), float(hi)],
                          "inside": bool(lo <= mean <= hi)}
        d["nis"] = nis
        late = self.t_s >= t0 + after_s
        if self.q_error_rad is not None:
            e = np.degrees(self.q_error_rad[late])
            good = np.isfinite(e)
            d["rms_error_deg"] = {nm: _rms(e[:, j][good[:, j]]) for j, nm in enumerate(self.joint_names)}
            ok = (self.flags[late] == FLAG_CODE["ok"]) & good
            d["rms_error_ok_deg"] = {nm: _rms(e[:, j][ok[:, j]]) for j, nm in enumerate(self.joint_names)}
            d["max_error_deg"] = {nm: _maxabs(e[:, j][good[:, j]]) for j, nm in enumerate(self.joint_names)}
            d["rms_after_s"] = after_s
        if self.yaw_error_rad is not None:
            y = np.degrees(self.yaw_error_rad[late])
            d["heading_rms_deg"] = _rms(y[np.isfinite(y)])
        if self.nees is not None:
            v = self.nees[late & np.isfinite(self.nees)]
            if len(v):
                lo, hi = chi2.ppf([0.025, 0.975], self.nees_dof)
                d["nees"] = {"mean": float(np.mean(v)), "dof": self.nees_dof, "count": int(len(v)),
                             "bounds_95_single": [float(lo), float(hi)],
                             "bounds_95": [float(x) for x in chi2.ppf([0.025, 0.975], len(v) * self.nees_dof)
                                           / len(v)],
                             "states": [f"q[{nm}]" for nm in self.joint_names] + ["roll", "pitch", "yaw"]}
        return d


def _tally(codes: np.ndarray, names: tuple[str, ...]) -> dict[str, int]:
    vals, counts = np.unique(codes, return_counts=True)
    return {names[int(c)]: int(k) for c, k in zip(vals, counts, strict=True)}


def _maxabs(v: np.ndarray) -> float | None:
    return float(np.max(np.abs(v))) if len(v) else None


def _rms(v: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(v**2))) if len(v) else None


@dataclass(frozen=True)
class _JointStub:
    name: str
    flag: str = "ok"
    sigma_rad: float = 0.0
    alternatives_rad: tuple[float, ...] = ()


def _ro(a) -> np.ndarray:
    v = np.array(a, dtype=float)
    v.setflags(write=False)
    return v


__all__ = [
    "COUNTERS", "FLAG_CODE", "JOINT_FLAGS", "SENSOR_STATUS", "CausalDifferentiator", "Estimate",
    "Frames", "ImuStill", "InnovationLog", "NotInitialisedError", "StateLayout", "Tracker",
    "TrackerSettings", "causal_fits", "causal_poly_fit", "imu_still_from_recording",
    "NoStillWindowError", "Start", "TrackRun", "make_frames", "start_from_recording",
]
