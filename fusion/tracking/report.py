"""What a tracker reports, by value (:class:`Reports`): the estimate at the last fused
instant (:class:`armfusion.fusion.tracking.estimate.Estimate`), the heading's status, the gyro's scale
as the filter holds it, the sensors' counters, NIS and warnings, the innovations kept. It
reads the tracker's parts (health, the compass, the observability, the ambiguous joints, the
combinations); the filter, the time, the encoders' angles and the flags come with each call."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.combos import JointTiltCombinations
from armfusion.fusion.tracking.compass import CALIBRATING, GYRO_ONLY, STATUS_CODE, Compass
from armfusion.fusion.tracking.estimate import HEADING_STATUS, Estimate
from armfusion.fusion.tracking.health import SensorHealth, sensor_warnings
from armfusion.fusion.tracking.initial import Ambiguity
from armfusion.fusion.tracking.innovations import InnovationLog
from armfusion.fusion.tracking.observability import Observability
from armfusion.fusion.tracking.process import attitude_sigma_rad
from armfusion.fusion.tracking.settings import (
    IMU_ACC,
    JOINT_FLAGS,
    MAG,
    S_ABSENT,
    S_DEAD,
    S_STALE,
    StateLayout,
    TrackerSettings,
)
from armfusion.fusion.tracking.ukf import BatchedUKF
from armfusion.models.arm import ArmModel


class ReportedParts(NamedTuple):
    """The parts of a started tracker that its reports read (each owns its state; the
    reports never write it)."""

    health: SensorHealth
    compass: Compass
    observability: Observability
    ambiguity: Ambiguity
    """The joints with rival branches, and how far apart those lie."""
    combinations: JointTiltCombinations


class Reports:
    """A started tracker's reports (see the module's docstring), with the named statuses and
    flags kept until their codes change."""

    def __init__(self, arm: ArmModel, settings: TrackerSettings, layout: StateLayout,
                 accel_streams: tuple[str, ...], unmodelled_g: np.ndarray, mag_index: int | None,
                 gyro_scale_sigma: float, parts: ReportedParts):
        self.arm, self.settings, self.layout = arm, settings, layout
        self.accel_streams, self.unmodelled_g = accel_streams, unmodelled_g
        self.gyro_scale_sigma = gyro_scale_sigma
        self.health, self.compass, self.observability = parts.health, parts.compass, parts.observability
        self.ambiguity, self.combinations = parts.ambiguity, parts.combinations
        self.mag_index = mag_index
        """The magnetometer's index among the tracker's sensors (None without an IMU)."""
        self.has_imu = mag_index is not None
        self.attitude_index = np.array([layout.roll, layout.pitch, layout.yaw])
        self.named = (None, None, (), ())
        """(status codes, flags, their names), kept while the codes are the same arrays."""

    def estimate(self, t: float, ukf: BatchedUKF, q_enc: np.ndarray, flags: np.ndarray) -> Estimate:
        """The estimate at ``t``, the last fused instant."""
        L, n, obs = self.layout, self.arm.n_joints, self.observability
        x, sig = ukf.x, ukf.sigma.copy()
        sig[:n] = np.sqrt(sig[:n] ** 2 + obs.sys_var)  # the calibration's own uncertainty
        ai = self.attitude_index
        amb = self.ambiguity
        if amb.joints.any():  # the sigma of a joint with rival branches covers them
            sig[:n] = np.maximum(sig[:n], amb.half_gap)
        named, codes = self.named, self.health.status_codes
        if named[0] is not codes or named[1] is not flags:
            # (both arrays are replaced, never written in place, when the flags are updated)
            self.named = named = (codes, flags, self.health.named_statuses(),
                                  tuple(JOINT_FLAGS[f] for f in flags.tolist()))
        compass = self.compass
        return Estimate(
            t_s=t, q_rad=_ro(self.arm.angles_in_range(q_enc + x[:n], q_enc)),
            sigma_rad=_ro(sig[:n]),
            flags=named[3],
            roll_rad=float(x[L.roll]), pitch_rad=float(x[L.pitch]), yaw_rad=float(x[L.yaw]),
            attitude_sigma_rad=_ro(attitude_sigma_rad(x[ai], ukf.covariance[np.ix_(ai, ai)]
                                                      + np.diag(np.r_[obs.tilt_var, 0.0]),
                                                      compass.heading_floor_var)),
            gyro_bias_rad_s=_ro(x[L.bias]),
            axis_to_vertical_deg=_ro(obs.axis_deg), sensors=named[2],
            magnetic_disturbance=compass.flags[0], magnetic_recovery=compass.flags[1],
            joint_names=self.arm.joint_names, heading_status=HEADING_STATUS[self.heading_status_code()],
            true_north=self.arm.magnetic_declination_deg is not None,
            combinations=self.combinations.now(ukf, q_enc, flags, t),
        )

    def gyro_scale(self, ukf: BatchedUKF | None) -> dict | None:
        """The gyro's scale error about the base's z axis as the filter holds it (fraction: it
        reads ``1 + value`` times the true rate) with its sigma and the config's (the prior),
        beyond what the config's own ``gyro_scale`` undoes; None where it is not a state (the
        config knows it exactly, or there is no gyro) or the filter has not started."""
        L = self.layout
        if L.scale < 0 or ukf is None:
            return None
        x, P = ukf.mean, ukf.covariance
        return {"value": float(x[L.scale]), "sigma": float(np.sqrt(P[L.scale, L.scale])),
                "prior_sigma": self.gyro_scale_sigma}

    def heading_status_code(self) -> int:
        """The heading's status (an index into :data:`~armfusion.fusion.tracking.estimate.HEADING_STATUS`):
        the compass's, or ``gyro_only`` where the magnetometer has gone quiet (stale, dead or
        absent) since it last said otherwise."""
        code = STATUS_CODE[self.compass.status]
        mi = self.mag_index
        if mi is not None and code != STATUS_CODE[CALIBRATING] and \
                self.health.status_codes[mi] in (S_STALE, S_DEAD, S_ABSENT):
            return STATUS_CODE[GYRO_ONLY]
        return code

    def sensor_warnings(self) -> list[str]:
        """The accelerometers rejected (or left out as implausible) more often than
        ``settings.warn_rejected_share`` of their samples so far, each with why
        (:func:`armfusion.fusion.tracking.health.sensor_warnings`)."""
        floors = dict(zip(self.accel_streams, self.unmodelled_g.tolist(), strict=True))
        if IMU_ACC in floors:
            floors[IMU_ACC] = self.arm.calibration.imu_accel_floor_g
        return sensor_warnings(self.health.counters(), self.nis_stats(), floors,
                               dict(self.arm.calibration.floors_by_default), self.settings)

    def innovations(self, sensor: str) -> InnovationLog:
        """The innovations kept for ``sensor`` (a link accelerometer, ``imu_acc``, ``imu_mag``):
        every one that was tested against the gate, accepted or not."""
        if sensor == MAG and self.has_imu:
            return self.compass.ring.log(sensor)
        if sensor not in self.accel_streams:
            kept = list(self.accel_streams) + ([MAG] if self.has_imu else [])
            raise KeyError(f"no innovations for {sensor!r}; kept for {kept}")
        return self.health.ring.log(sensor)

    def nis_stats(self) -> dict[str, tuple[float, int, int]]:
        """Per sensor: (mean NIS, count, degrees of freedom) over its healthy samples."""
        out = self.health.nis_stats()
        if self.has_imu:
            m = self.compass.ring
            out[MAG] = (m.nis_sum / m.nis_count if m.nis_count else float("nan"), m.nis_count, 1)
        return out


def _ro(a) -> np.ndarray:
    v = np.array(a, dtype=float)
    v.setflags(write=False)
    return v
