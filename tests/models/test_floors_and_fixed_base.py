"""A config as a new user writes it: each sensor's unmodelled-error floor from its class
where the ``calibration:`` block gives none (a given 0 kept as 0), ``base: fixed`` for an
arm bolted down, and a joint whose limits span more than a turn reported in its own range."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm, read_yaml, resolve_config_path
from armfusion.models.arm_config import ConfigError, build_arm
from armfusion.models.sensor_description import UNMODELLED_FLOOR
from typer.testing import CliRunner


@pytest.fixture
def ur5_dict():
    return read_yaml(resolve_config_path("ur5_two_imu"))


def test_an_uncalibrated_config_takes_each_sensors_datasheet_floor(ur5_dict, wmra):
    """No calibration block: every link accelerometer gets its class's floor (a custom IMU's
    0.05 g, never 0), and the arm says which floors came from the class."""
    arm = build_arm(ur5_dict, "ur5.yaml")
    cal = arm.calibration
    custom = UNMODELLED_FLOOR["custom"]["accelerometer"]
    assert cal.accel_floor_g("forearm") == cal.accel_floor_g("wrist") == custom
    assert cal.accel_floor_g("forearm") > 0.0
    assert set(cal.floors_by_default) == {"forearm", "wrist"}
    assert "custom accelerometer, 0.05 g" in cal.floors_by_default["forearm"]
    # the shipped WMRA gives its floors: none is a default, each as written
    assert wmra.calibration.floors_by_default == {}
    assert wmra.calibration.accel_floor_g("acc1") == 0.045 and wmra.calibration.mag_unmodelled_ut == 15.0


def test_a_floor_given_even_zero_is_kept(ur5_dict):
    """``accel_unmodelled_g: 0`` (sensors as exact as modelled) is not "not given"; a
    per-sensor floor names one sensor and the other keeps its class's."""
    d = copy.deepcopy(ur5_dict)
    d["calibration"] = {"accel_unmodelled_g": 0.0}
    cal = build_arm(d, "exact.yaml").calibration
    assert (cal.accel_floor_g("forearm"), cal.accel_floor_g("wrist")) == (0.0, 0.0)
    assert cal.floors_by_default == {}
    d["calibration"] = {"accel_unmodelled_g_per_sensor": {"wrist": 0.02}}
    cal = build_arm(d, "one.yaml").calibration
    assert (cal.accel_floor_g("forearm"), cal.accel_floor_g("wrist")) == (0.05, 0.02)
    assert set(cal.floors_by_default) == {"forearm"}
    # --unmodelled-g replaces every floor, the class's too
    assert cal.with_accel_floor(0.01).accel_floor_g("forearm") == 0.01
    assert cal.as_exact().accel_floor_g("forearm") == 0.0


def test_a_base_imu_and_its_compass_get_their_class_floor(wmra_dict):
    """The WMRA's MPU-9150 without a calibration block: its accelerometer's 0.06 g and its
    compass's 15 µT, named; ``--unmodelled-g`` replaces the accelerometer's only."""
    d = copy.deepcopy(wmra_dict)
    del d["calibration"]
    cal = build_arm(d, "bare.yaml").calibration
    assert cal.imu_accel_floor_g == 0.06 and cal.mag_unmodelled_ut == 15.0
    assert cal.accel_floor_g("acc1") == 0.045  # an ADXL345's
    assert {"imu_acc", "imu_mag", "acc1"} <= set(cal.floors_by_default)
    low = cal.with_accel_floor(0.001)
    assert (low.imu_accel_floor_g, low.accel_floor_g("acc3"), low.mag_unmodelled_ut) == (0.001, 0.001, 15.0)


@pytest.fixture
def wmra_dict():
    return read_yaml(resolve_config_path("wmra"))


def test_base_fixed_short_and_long_forms(ur5_dict):
    """``base: fixed`` (tilt read at the first still pose) and the long form with an
    installer's level; half a tilt, a fixed base on a chair: refused by name."""
    assert ur5_dict["base"] == "fixed"
    arm = build_arm(ur5_dict, "ur5.yaml")
    assert arm.fixed_base is not None and arm.fixed_base.roll_rad is None
    d = copy.deepcopy(ur5_dict)
    d["base"] = {"mount": "fixed", "roll_deg": 0.5, "pitch_deg": -0.25, "tilt_sigma_deg": 0.05}
    fb = build_arm(d, "levelled.yaml").fixed_base
    np.testing.assert_allclose(np.degrees([fb.roll_rad, fb.pitch_rad, fb.tilt_sigma_rad]), [0.5, -0.25, 0.05])
    d["base"] = {"mount": "fixed", "roll_deg": 0.5}
    with pytest.raises(ConfigError, match=r"base: .*give both roll_deg and pitch_deg"):
        build_arm(d, "half.yaml")
    d["base"] = "fixed"
    d["chair"] = {"base_from_turning_centre_mm": [0, 0, 0]}
    with pytest.raises(ConfigError, match=r"a bolted base has no base_motion or chair block"):
        build_arm(d, "chair.yaml")
    d = copy.deepcopy(ur5_dict)
    d["base"] = "welded"
    with pytest.raises(ConfigError, match=r"base\.mount"):
        build_arm(d, "welded.yaml")


def test_a_joint_whose_limits_span_more_than_a_turn_runs_on_past_180():
    """A UR joint (±360°) at -188° is reported at -188° (the turn its encoder counts), not
    172°; a joint of the same arm driven past its limit by an estimate is moved by a turn
    back inside; the angle is continuous as it crosses -180°."""
    arm = load_arm("ur5_two_imu")
    enc = np.radians([0.0, -90.0, 90.0, -188.0, -90.0, 0.0])
    est = enc + np.radians([0.1, -0.2, 0.3, 0.4, 0.0, 0.0])
    np.testing.assert_allclose(arm.angles_in_range(est, enc), est, atol=1e-12)
    # the estimate a whole turn off the encoder's turn (a startup's angle wrapped to ±180°)
    wrapped = est + np.radians([0, 0, 0, 360.0, 0, 0])
    np.testing.assert_allclose(arm.angles_in_range(wrapped, enc), est, atol=1e-12)
    sweep = np.radians(np.linspace(-170.0, -200.0, 31))
    qs = np.tile(enc, (31, 1))
    qs[:, 3] = sweep
    out = arm.angles_in_range(qs, qs)
    assert np.all(np.abs(np.diff(np.degrees(out[:, 3]))) < 1.01)
    beyond = np.radians([0.0, 0.0, 0.0, 365.0, 0.0, 0.0])
    assert np.degrees(arm.angles_in_range(beyond, beyond)[3]) == pytest.approx(5.0)


def test_info_says_each_floor_and_where_it_came_from_and_the_fixed_base():
    r = CliRunner().invoke(app, ["info", "--config", "ur5_two_imu", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert [(s["name"], s["unmodelled_g"], s["unmodelled_from"]) for s in d["sensors"]] == [
        ("forearm", 0.05, "class"), ("wrist", 0.05, "class")]
    assert d["base"] == {"mount": "fixed", "tilt_sigma_deg": pytest.approx(1.0), "roll_deg": None,
                         "pitch_deg": None}
    r = CliRunner().invoke(app, ["info", "--config", "wmra", "--json"])
    d = json.loads(r.stdout)
    assert d["base"] == "moving" and {s["unmodelled_from"] for s in d["sensors"]} == {"config"}
