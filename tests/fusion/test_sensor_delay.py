"""A sensor part's declared delay (``delay_s`` in its description: a filter's group delay, or
half a period for a part that delivers its period's mean): refused when it is no delay, drawn
by the simulator, and made up for by the tracker, which turns the attitude over each
interval by the gyro rate at the interval's midpoint, and turns a late accelerometer's
gravity and a late compass's field to their stamps by the sensor's turn over the delay."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.filter import Tracker
from armfusion.fusion.tracking.frames import BaseTurn, JointMotion, make_frames
from armfusion.fusion.tracking.process import gyro_newer_weight
from armfusion.fusion.tracking.start import delay_notes
from armfusion.models.arm_config import ConfigError
from armfusion.models.rotations import GRAVITY_MPS2, exp_so3, up_from_tilt
from armfusion.models.sensor_models import stream_models
from armfusion.models.simulator import SimulationOptions, simulate

from tests.fusion.test_base_pivot import _swung_trial
from tests.fusion.test_base_velocity import _inclination_rmse_deg


def _config_with_gyro_delay(tmp_path: Path, base: str, delay_s, name: str = "c.yaml") -> Path:
    cfg = yaml.safe_load(Path(load_arm(base).source).read_text())
    imu = next(s for s in cfg["sensors"] if s["link"] == 0)
    imu.setdefault("outputs", {}).setdefault("gyroscope", {})["delay_s"] = delay_s
    out = tmp_path / name
    out.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return out


def test_the_newer_sample_s_weight_follows_the_delay():
    assert gyro_newer_weight(0.0, 100.0) == 0.5  # instantaneous samples: the midpoint rule
    assert gyro_newer_weight(0.0025, 200.0) == 1.0  # a period's mean: the newer sample alone
    assert gyro_newer_weight(0.0048, 100.0) == pytest.approx(0.98)  # an MPU-9150 at DLPF 3
    assert gyro_newer_weight(0.02, 100.0) == 1.0  # beyond half a period: capped


@pytest.mark.parametrize("delay", [-0.001, 1.5, True, "2 ms"])
def test_a_delay_that_is_no_filter_s_is_refused_naming_the_key(tmp_path, delay):
    with pytest.raises(ConfigError, match=r"outputs\.gyroscope\.delay_s: seconds, >= 0 and below 1"):
        load_arm(_config_with_gyro_delay(tmp_path, "wmra", delay))


def test_the_simulator_draws_the_declared_delay(tmp_path):
    delayed = load_arm(_config_with_gyro_delay(tmp_path, "wmra", 0.005))
    plain = load_arm("wmra")
    a, _ = simulate(delayed, "daily-use", 40.0, seed=2, options=SimulationOptions(noise=False))
    b, _ = simulate(plain, "daily-use", 40.0, seed=2, options=SimulationOptions(noise=False))
    ga, gb = a.get("imu_gyro"), b.get("imu_gyro")
    # half a sample late: the delayed stream is the plain one read 5 ms earlier (between
    # samples, within the counts' rounding); the other streams are unchanged
    mid = 0.5 * (gb.values[1:].astype(float) + gb.values[:-1].astype(float))
    moving = np.abs(np.diff(gb.values.astype(float), axis=0)).max(1) > 20  # turning, counts
    assert moving.sum() > 100
    err_delayed = np.abs(ga.values[1:][moving] - mid[moving]).max()
    err_plain = np.abs(gb.values[1:][moving] - mid[moving]).max()
    assert err_delayed <= 2.0 < err_plain
    assert np.array_equal(a.get("imu_acc").values, b.get("imu_acc").values)
    notes = delay_notes(delayed)
    assert notes == ["the gyroscope's delay (5 ms) made up for (up to half a sample period): the attitude "
                     "turns by the rate at each interval's midpoint"]


def test_a_gyro_that_delivers_period_means_keeps_the_tilt_only_when_its_delay_is_declared(tmp_path):
    # at 200 Hz, each gyro sample the rate half a period (2.5 ms) before its stamp: what a
    # part that delivers its period's mean reads (measured 0.40 deg declared, 0.77 not; 0.62
    # and 0.88 with a speed spread of 1 m/s per axis; 0.34 and 0.75 before the hand's gyro
    # scale error was the tilt's noise, which leans on the accelerometer more and so on the
    # gyro's timing less)
    trial = _swung_trial(tmp_path / "means.hdf5", gyro_delay_s=0.0025)
    declared = _config_with_gyro_delay(tmp_path, "broad_imu", 0.0025, "declared.yaml")
    instant = _config_with_gyro_delay(tmp_path, "broad_imu", 0.0, "instant.yaml")
    with_delay = _inclination_rmse_deg(declared, trial, 13.0)
    without = _inclination_rmse_deg(instant, trial, 13.0)
    assert with_delay < 0.7 * without, (with_delay, without)


def test_a_late_accelerometer_is_turned_to_its_stamp():
    arm = load_arm("broad_imu")
    d = stream_models(arm)["imu_acc"].delay_s
    assert d == 0.00175  # half broad_imu's period: a decimating part's
    tr = Tracker(arm)
    w = np.radians([300.0, -200.0, 100.0])  # a hand turning the sensor fast
    none = np.zeros((1, 0))  # (an arm with no joints)
    frame = tr.measurements.with_noise(make_frames(arm, tr.accel_names, JointMotion(none, none, none),
                                                   np.zeros(0), BaseTurn(w[None], np.zeros((1, 3)))).take(0))
    # the specific force at the stamp (gravity up, and an acceleration steady in the world),
    # in the sensor's axes; the reading is it as it was d earlier, in the axes of then
    f_now = up_from_tilt(0.3, -0.2) + np.array([0.5, -0.3, 0.2]) / GRAVITY_MPS2
    f_read = exp_so3(w * d) @ f_now
    sel = np.array([0])
    acc = tr.measurements.readings(sel, np.zeros((1, 3)), f_read[None])
    f = tr.measurements.stack(acc, frame, False, False).f_g[0]
    # read as it came the reading is 11 mg off (|ω| d g); turned, to second order in ω d
    assert np.linalg.norm(f_read - f_now) > 0.01
    np.testing.assert_allclose(f, f_now, atol=1e-4)


def test_the_track_notes_say_which_delays_are_made_up_for():
    notes = delay_notes(load_arm("broad_imu"))
    assert notes[0].startswith("the gyroscope's delay (1.75 ms) made up for")
    assert notes[1] == ("delays made up for by turning each reading to its stamp with its sensor's turn "
                        "rate: imu_acc 1.75 ms, imu_mag 13 ms")
    assert len(notes) == 2
