"""The one-joint IMU rig's configs and the choice among them: the config whose model fits a
trial's first stretch best. Shared by ``tools/bench_real_rig.py`` and ``tools/rig_peers.py``
(both import it; it imports neither)."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.identify import data_from_recording
from armfusion.fusion.workbench.diagnose import diagnose
from armfusion.models.effects import model_from_arm
from armfusion.sensors.samples import Recording

RIG_CONFIGS = ("imu_rig_roll", "imu_rig_pitch", "imu_rig_yaw")
WINDOW = 10
"""Samples per fit point of the ladder (0.1 s at 100 Hz)."""


def choose_config(rec: Recording, first_s: float) -> tuple[str, dict[str, float]]:
    """The rig config whose model (no effects) fits the trial's first ``first_s`` best."""
    t0 = rec.t_start_s
    part = rec.between(t0, t0 + first_s)
    fits = {}
    for name in RIG_CONFIGS:
        arm = load_arm(name)
        data = data_from_recording(arm, part, window=WINDOW, q_ref_rad=np.zeros(arm.n_joints))
        fits[name] = diagnose(model_from_arm(arm), data).rms_ratio
    return min(fits, key=fits.get), fits
