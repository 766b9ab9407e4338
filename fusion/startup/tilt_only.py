"""The startup of an arm with no joints (an IMU alone): the base's tilt from its IMU.

:func:`base_tilt_only` is what :func:`armfusion.fusion.startup.solve.solve_still` gives for
such an arm: no joint, no branch, only the base's roll and pitch with their sigmas.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from armfusion.fusion.startup.readings import StillReadings
from armfusion.fusion.startup.results import StartupInputError, StartupResult
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import tilt_from_up


def base_tilt_only(arm: ArmModel, readings: StillReadings, st: StartupSettings,
                   method: str) -> StartupResult:
    """An arm with no joints (an IMU alone): the base's roll and pitch from its IMU's
    averaged reading in closed form (:func:`armfusion.models.rotations.tilt_from_up`, as the joint
    solve starts from), their covariance from the reading's sigma (its noise over the
    window, as the joint solve takes the IMU's: what the IMU accelerometer is off by is
    the tracker's ``imu_bias`` state, whose prior is the config's unmodelled error) through
    the same direction's Jacobian, times the safety factor. No joint, no branch."""
    if readings.imu_mean_g is None or arm.imu is None:
        raise StartupInputError("an arm with no joints is started from its base IMU, and the still "
                                "window has no IMU accelerometer reading")
    f = np.asarray(readings.imu_mean_g, float)
    norm = float(np.linalg.norm(f))
    if not norm > 0.0:
        raise StartupInputError("the IMU accelerometer's still reading is zero: no tilt to read")
    R_0I = arm.imu.R_LS
    up = R_0I @ (f / norm)
    roll, pitch = (float(a) for a in tilt_from_up(up))
    # d up / d (roll, pitch), base axes; the reading's per-axis sigma turned into them
    sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
    J = np.array([[0.0, -cp], [cr * cp, -sr * sp], [-sr * cp, -cr * sp]])
    sig_I = np.asarray(readings.imu_sigma_g, float) / norm
    C_up = R_0I @ np.diag(sig_I**2) @ R_0I.T
    info = J.T @ np.linalg.inv(C_up) @ J  # J is normal to up: the norm's own error drops out
    cov = np.linalg.inv(info) * st.sigma_safety_factor**2
    resid = f / norm - R_0I.T @ up  # zero: the direction is read exactly; kept for the record
    result = StartupResult(
        joints=(), roll_rad=roll, pitch_rad=pitch,
        roll_sigma_rad=float(np.sqrt(cov[0, 0])), pitch_sigma_rad=float(np.sqrt(cov[1, 1])),
        residual_rms_g=float(np.sqrt(np.mean(resid**2))), chi2_per_dof=0.0,
        q_rad=np.zeros(0), covariance=cov, branches_rad=np.zeros((1, 0)), method=method,
        t_start_s=readings.t_start_s, t_end_s=readings.t_end_s,
        candidates_rad=np.zeros((1, 0)), candidates_covariance=cov[None],
        notes=("no joints: the base tilt from the IMU accelerometer alone",))
    sig_deg = np.degrees([result.roll_sigma_rad, result.pitch_sigma_rad])
    return replace(result, summary=(f"no joints; base roll {np.degrees(roll):.2f} deg, pitch "
                                    f"{np.degrees(pitch):.2f} deg (sigma {sig_deg[0]:.3f}, "
                                    f"{sig_deg[1]:.3f} deg)"))
