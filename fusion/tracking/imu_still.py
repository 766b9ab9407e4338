"""What the IMU said in a still window, read as the tracker reads it
(:func:`imu_still_from_recording`): the gyro's zero-rate offset, the heading and the
Earth-field reference the tracker starts from."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.identification.correction import startup_correction
from armfusion.fusion.startup.results import StartupResult
from armfusion.fusion.tracking.calibrated import undo_map
from armfusion.fusion.tracking.compass import compass_map, compass_unmodelled_rad
from armfusion.fusion.tracking.heading import FieldReference, heading_sigma_rad, tilt_compensated_heading
from armfusion.fusion.tracking.initial import ImuStill
from armfusion.fusion.tracking.settings import GYRO, MAG, TrackerSettings
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, up_from_tilt
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.samples import Recording


def imu_still_from_recording(arm: ArmModel, rec: Recording, t_start_s: float, t_end_s: float,
                             startup: StartupResult, settings: TrackerSettings | None = None,
                             correction=None) -> ImuStill:
    """The gyro bias, initial heading and Earth-field reference from a still window, the
    gyro and the compass read as the tracker reads them (the config's calibrated errors
    undone). ``correction``: the config's
    :class:`armfusion.fusion.identification.identify.StartupCorrection`, when the caller has it (else
    made here when the config has effects)."""
    st = settings or TrackerSettings()
    if correction is None and arm.effects:
        correction = startup_correction(arm)
    sm = stream_models(arm)
    R_0I = arm.imu.R_LS if arm.imu is not None else np.eye(3)
    bias = np.zeros(3)
    bias_sigma = 0.5 * DEG  # no gyro samples: a wide guess
    g = rec.get(GYRO)
    if g is not None:
        w = g.between(t_start_s, t_end_s + 1e-9)
        if len(w) >= 3:
            rate = w.rate_hz or 100.0
            omega = sm[GYRO].from_counts(w.values)
            undo = undo_map(correction, GYRO)
            if undo is not None:  # the config's gyro scale and bias, as the tracker undoes them
                omega = (omega - undo[1]) @ undo[0]
            omega = omega @ R_0I.T
            bias = omega.mean(axis=0)
            noise = st.gyro_noise_dps_per_sqrt_hz * DEG * np.sqrt(rate / 2.0)
            # the window's own scatter where it is above the datasheet's (a vibrating base):
            # the mean of a few shaken samples is no better than they are
            scatter = float(np.max(np.std(omega, axis=0, ddof=1)))
            if scatter < noise * (1.0 + 3.0 / np.sqrt(2.0 * (len(w) - 1))):
                scatter = noise  # within what the datasheet's noise scatters by
            bias_sigma = float(max(scatter / np.sqrt(len(w)), 2e-5))
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
                declination_rad = float(np.radians(arm.magnetic_declination_deg or 0.0))
                field_ref = FieldReference.from_samples(mB, up, declination_rad)
            mean = mB.mean(axis=0)
            yaw = float(tilt_compensated_heading(mean, startup.roll_rad, startup.pitch_rad,
                                                 field_ref.declination_rad))
            sig = heading_sigma_rad(field_ref, st.heading.noise_ut) / np.sqrt(len(w))
            tilt_sig = np.hypot(startup.roll_sigma_rad, startup.pitch_sigma_rad) * np.tan(field_ref.dip_rad)
            iron_sig = compass_unmodelled_rad(arm, field_ref)
            yaw_sigma = float(np.sqrt(sig**2 + tilt_sig**2 + iron_sig**2) + 0.2 * DEG)
    return ImuStill(bias, bias_sigma, yaw, yaw_sigma, field_ref)
