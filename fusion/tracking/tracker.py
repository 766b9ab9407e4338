"""Continuous tracking: the absolute joint angles all day, from relative encoders, the link
accelerometers and the base IMU, with an unscented Kalman filter (:mod:`armfusion.fusion.tracking.ukf`).

The state (:class:`armfusion.fusion.tracking.settings.StateLayout`), seeded from the startup calibration:

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
   differentiator (:class:`armfusion.fusion.tracking.differentiator.CausalDifferentiator`), the joint
   rates and accelerations.
2. **Gyro** propagates the attitude (every sigma point, its own bias).
3. **Link accelerometers and the IMU accelerometer** are predicted with motion
   compensated, ``f_S = R_0S^T (a_S + a_B + g·up)``: ``a_S`` (the joints' motion and
   the base's rotation, from :func:`armfusion.models.motion.sensor_motion`), the base's linear
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
   :class:`armfusion.fusion.tracking.heading.MagneticGuard` (disturbance detection, rejection, recovery).

Every joint's observability is checked every step (its axis's angle to gravity, and the
eigen-decomposition of the accelerometers' information about the offsets, per second):
along directions that the sensors cannot read well (near gimbal lock, or two joints
that gravity only sees together), the update's gain is held to zero (Schmidt), so no
correction flows there and the sigma of those joints grows until they are readable
again. Each sensor has a chi-square gate; a sensor rejected for longer than
``reacquire_after_s`` (a slip, not a bump) widens the offsets it sees and re-acquires.
Samples that are not finite, saturated, implausible (far from the predicted magnitude:
a dead sensor) or stuck are skipped and counted.

One filter path, live and over a recording alike: each instant's readings go through
:meth:`Tracker.step` (the differentiators take them, the mean pose's kinematic frame is
made in one compiled call, the filter predicts and fuses). :meth:`Tracker.update_instant`
(:mod:`armfusion.fusion.tracking.live`) feeds it one instant's raw samples; :meth:`Tracker.run`
(:mod:`armfusion.fusion.tracking.run`) a whole recording, with only the conversions to SI units and
the saturation checks done for many instants at once, and the frames made with the offsets
and gyro bias of each block of instants' start (the instant's, live).

Where it lives (each module one idea; this one gathers the public names):

- :mod:`armfusion.fusion.tracking.settings`: :class:`TrackerSettings`, the flags, statuses,
  counters and the state layout;
- :mod:`armfusion.fusion.tracking.filter`: :class:`Tracker`, the filter, composed of parts that own
  their state: :mod:`~armfusion.fusion.tracking.health` (sensor health),
  :mod:`~armfusion.fusion.tracking.slips` (slips, re-acquisition),
  :mod:`~armfusion.fusion.tracking.observability` (hold, consider sensitivity, joint flags),
  :mod:`~armfusion.fusion.tracking.compass` and :mod:`~armfusion.fusion.tracking.heading` (the heading),
  :mod:`~armfusion.fusion.tracking.process` (process model, still chair),
  :mod:`~armfusion.fusion.tracking.measurement` (measurement model and noise),
  :mod:`~armfusion.fusion.tracking.differentiator` (joint rates, angular acceleration),
  :mod:`~armfusion.fusion.tracking.frames` (the kinematic frame), :mod:`~armfusion.fusion.tracking.initial`
  (first state, ambiguity), :mod:`~armfusion.fusion.tracking.calibrated` (what the config's
  effects say), :mod:`~armfusion.fusion.tracking.innovations`, :mod:`~armfusion.fusion.tracking.snapshot`;
- :mod:`armfusion.fusion.tracking.live` and :mod:`armfusion.fusion.tracking.run`: the live front and a run
  over a recording (:class:`TrackRun`), scored against truth by
  :mod:`armfusion.fusion.tracking.scoring`;
- :mod:`armfusion.fusion.tracking.start`: :func:`start_from_recording`, :func:`warm_up`.
"""

from armfusion.fusion.tracking.differentiator import CausalDifferentiator, causal_fits, causal_poly_fit
from armfusion.fusion.tracking.estimate import Estimate
from armfusion.fusion.tracking.filter import Tracker
from armfusion.fusion.tracking.frames import BaseTurn, Frames, JointMotion, make_frames
from armfusion.fusion.tracking.initial import ImuStill
from armfusion.fusion.tracking.innovations import InnovationLog
from armfusion.fusion.tracking.run import TrackRun
from armfusion.fusion.tracking.scoring import truth_at
from armfusion.fusion.tracking.settings import (
    COUNTERS,
    ENC,
    FLAG_CODE,
    GYRO,
    IMU_ACC,
    JOINT_FLAGS,
    MAG,
    SENSOR_STATUS,
    STATUS_CODE,
    G,
    NotInitialisedError,
    StateLayout,
    TrackerSettings,
)
from armfusion.fusion.tracking.snapshot import TrackerState
from armfusion.fusion.tracking.start import (
    NoStillWindowError,
    Start,
    StartOptions,
    imu_still_from_recording,
    start_from_recording,
    warm_up,
)
from armfusion.fusion.tracking.update import InstantReadings, UpdateResult

__all__ = [
    "COUNTERS", "ENC", "FLAG_CODE", "G", "GYRO", "IMU_ACC", "JOINT_FLAGS", "MAG", "SENSOR_STATUS",
    "STATUS_CODE", "BaseTurn", "CausalDifferentiator", "Estimate", "Frames", "ImuStill", "InnovationLog",
    "InstantReadings", "JointMotion", "NoStillWindowError", "NotInitialisedError", "Start", "StartOptions",
    "StateLayout", "TrackRun", "Tracker", "TrackerSettings", "TrackerState", "UpdateResult", "causal_fits",
    "causal_poly_fit", "imu_still_from_recording", "make_frames", "start_from_recording",
    "truth_at", "warm_up",
]
