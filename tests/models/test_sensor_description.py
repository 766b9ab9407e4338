"""Sensors described, not assumed: a config's device descriptions (datasheet or its own
``outputs``) become the count models everything downstream reads."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm
from armfusion.models.arm_config import ConfigError, build_arm
from armfusion.models.sensor_models import stream_models

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"


@pytest.fixture
def wmra_dict():
    return yaml.safe_load((CONFIG_DIR / "wmra.yaml").read_text())


def _problems(data) -> list[str]:
    with pytest.raises(ConfigError) as e:
        build_arm(data, "arm.yaml")
    return [str(p) for p in e.value.problems]


def test_datasheet_descriptions_give_the_register_models(wmra):
    sm = stream_models(wmra, 100.0)
    acc, gyro, mag = sm["acc1"], sm["imu_gyro"], sm["imu_mag"]
    assert acc.value_unit == "counts" and acc.gain.tolist() == [256.0] * 3
    assert acc.noise_counts_rms.tolist() == [0.75, 0.75, 1.1]  # LSB rms at 100 Hz, datasheet
    assert (acc.counts_min, acc.counts_max) == (-512, 511)
    assert stream_models(wmra, 400.0)["acc1"].noise_counts_rms.tolist() == [1.5, 1.5, 2.2]
    assert gyro.gain[0] == pytest.approx(131.0 * 180.0 / np.pi)  # 131 LSB per deg/s, in rad/s
    assert gyro.noise_counts_rms[0] == pytest.approx(0.005 * np.sqrt(50.0) * 131.0)
    np.testing.assert_allclose(mag.from_counts(np.array([[10.0, 0.0, -10.0]])), [[3.0, 0.0, -3.0]])


def test_a_sensor_delivering_g_rounded_to_a_hundredth():
    rig = load_arm(CONFIG_DIR / "imu_rig_roll.yaml")
    sm = stream_models(rig, 100.0)
    shaft, gyro = sm["shaft"], sm["shaft_gyro"]
    assert shaft.value_unit == "g" and shaft.step == 0.01
    np.testing.assert_allclose(shaft.from_counts(np.array([[0.07, 0.82, -0.03]])), [[0.07, 0.82, -0.03]])
    # noise: 400 ug/sqrt(Hz) over 50 Hz, and the 0.01 g rounding
    assert shaft.sigma_counts[0] == pytest.approx(np.hypot(400e-6 * np.sqrt(50.0), 0.01 / np.sqrt(12)))
    assert gyro.kind == "link_gyro" and gyro.value_unit == "deg/s"
    np.testing.assert_allclose(gyro.from_counts(np.array([[180.0, 0.0, 0.0]])), [[np.pi, 0.0, 0.0]])
    # the MPU-6050 has no magnetometer: its base IMU gives no compass stream
    assert "imu_mag" not in sm and {"imu_acc", "imu_gyro", "enc"} <= set(sm)
    # simulated readings are rounded to the resolution and stay in g
    rounded = shaft.digitise(np.array([[0.0712, 0.8249, -0.0351]]), None)
    np.testing.assert_allclose(rounded, [[0.07, 0.82, -0.04]])
    assert rounded.dtype == np.float64


def test_outputs_in_other_units_and_a_custom_device(wmra_dict):
    d = copy.deepcopy(wmra_dict)
    d["sensors"][0]["outputs"] = {"accelerometer": {"units": "m/s^2", "resolution": 0.001}}
    d["sensors"][1] = {"name": "acc2", "type": "custom", "kind": "accelerometer", "link": 4,
                       "outputs": {"accelerometer": {"units": "counts", "scale": 1000,
                                                     "limits": [-2048, 2047], "noise_density": 25e-6}}}
    sm = stream_models(build_arm(d, "arm.yaml"), 100.0)
    assert sm["acc1"].gain[0] == pytest.approx(9.80665) and sm["acc1"].value_unit == "m/s^2"
    # the ADXL345's 0.75 LSB noise is 0.75/256 g, now in m/s^2
    assert sm["acc1"].noise_counts_rms[0] == pytest.approx(0.75 / 256 * 9.80665)
    assert sm["acc2"].gain[0] == 1000.0 and (sm["acc2"].counts_min, sm["acc2"].counts_max) == (-2048, 2047)
    assert sm["acc2"].noise_counts_rms[0] == pytest.approx(25e-6 * np.sqrt(50.0) * 1000.0)


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d["sensors"][0].update(outputs={"accelerometer": {"units": "deg/s"}}),
     r"sensors\[0\]: outputs\.accelerometer\.units: deg/s is a unit of angular_rate, not of acceleration"),
    (lambda d: d["sensors"][0].update(outputs={"gyroscope": {"units": "deg/s"}}),
     r"outputs\.gyroscope: an accelerometer has no gyroscope"),
    (lambda d: d["sensors"][0].update(type="custom"), r"a custom sensor needs its kind"),
    (lambda d: d["sensors"][0].update(kind="imu"), r"kind 'imu' does not match the adxl345"),
    (lambda d: d["sensors"][0].update(outputs={"accelerometer": {"units": "counts", "scale": -3}}),
     r"outputs\.accelerometer\.scale: a positive number"),
    (lambda d: d["sensors"][4].update(link=3),
     r"sensors\[4\]\.link: a magnetometer \(mpu9150\) is read only"),
    (lambda d: d["sensors"].append({**d["sensors"][4], "name": "imu2", "type": "mpu6050"}),
     r"more than one IMU on the base"),
])
def test_a_bad_description_is_refused_by_name(wmra_dict, mutate, message):
    d = copy.deepcopy(wmra_dict)
    mutate(d)
    assert any(__import__("re").search(message, p) for p in _problems(d)), _problems(d)


def test_the_simulator_writes_what_the_descriptions_say():
    """A rig whose MPU-6050s deliver g and deg/s rounded to 0.01, with a gyroscope on the
    shaft and no magnetometer: simulated in those units, the shaft's gyro turning with
    the joint, no compass stream."""
    from armfusion.models.simulator import simulate

    rig = load_arm(CONFIG_DIR / "imu_rig_roll.yaml")
    rec, _ = simulate(rig, "excitation", 20.0, seed=4)
    assert "imu_mag" not in rec.streams and rec.get("shaft_gyro").kind == "link_gyro"
    shaft = rec.get("shaft").values
    assert shaft.dtype == np.float64 and np.allclose(shaft * 100, np.rint(shaft * 100))
    gyro = rec.get("shaft_gyro")
    q = rec.get("true_q")
    rate_dps = np.degrees(np.gradient(q.values[:, 0], q.t_s))
    # the shaft's axis is the shaft IMU's x axis (its config's mount): x reads the joint's rate
    x = np.interp(q.t_s, gyro.t_s, gyro.values[:, 0])
    assert np.corrcoef(x, rate_dps)[0, 1] > 0.99  # (the rest: the base's own turning)
    assert np.allclose(gyro.values * 100, np.rint(gyro.values * 100))
