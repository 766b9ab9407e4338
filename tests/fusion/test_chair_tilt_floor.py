"""A chair's tilt, and the heading that leans on it, are never claimed better known than its
accelerometers' lasting errors allow: the realistic WMRA (every effect of the library drawn
at datasheet-typical magnitudes) tracked with the shipped, uncalibrated config, whose 45 mg
floors say how far its sensors may be off."""

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.tracker import start_from_recording
from armfusion.models.simulator import angle_truth, simulate
from armfusion.sensors.samples import Recording


@pytest.fixture(scope="module")
def uncalibrated_drive():
    arm = load_arm("wmra")
    _, drawn = simulate(arm, "renk-maneuver", 5.0, seed=1, realistic=True)  # the drawn sensor errors
    rec, truth = simulate(arm, "daily-use", 200.0, seed=11, effects=drawn["effects"])
    tq = angle_truth(rec.get("true_q"), truth, arm.joint_names)
    rec = Recording({**rec.streams, "true_q": tq}, rec.meta)
    tr, _ = start_from_recording(arm, rec)
    return rec, tr.run(rec)


def test_the_reported_tilt_covers_a_tilt_the_uncalibrated_imu_puts_degrees_off(uncalibrated_drive):
    rec, run = uncalibrated_drive
    tb = rec.get("true_base")
    k = np.searchsorted(tb.t_s, run.t_s + 1e-9) - 1
    err = np.degrees(run.rpy_rad[:, :2] - tb.values[k, :2])
    sig = np.degrees(run.rpy_sigma_rad[:, :2])
    assert np.abs(err).max() > 1.0  # the drawn errors do put the tilt off
    # floors 45 mg on four links and the IMU: 45 mg / sqrt(5), 1.15° at least
    assert np.median(sig) > 1.1
    assert np.mean(np.abs(err) <= 3 * sig) >= 0.99


def test_the_heading_that_leans_on_that_tilt_says_so(uncalibrated_drive):
    _, run = uncalibrated_drive
    ye, ys = np.degrees(run.yaw_error_rad), np.degrees(run.rpy_sigma_rad[:, 2])
    late = run.t_s >= 60.0  # the compass fused (its iron learnt from the first turns)
    assert np.sqrt(np.mean(ye[late] ** 2)) > 3.0  # the uncalibrated compass is degrees off
    assert np.mean(np.abs(ye[late]) <= 3 * ys[late]) >= 0.95
