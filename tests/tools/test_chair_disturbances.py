"""The disturbances the chair's heading benchmark adds are the physics they claim: a dipole's
field, a magnet passed at the moment and distance asked, rough ground that shakes the IMU
without moving it, a clipped magnet that stays."""

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.models.sensor_description import (
    AK8975_UT_PER_LSB,
    MPU9150_ACCEL_LSB_PER_G,
    MPU9150_GYRO_LSB_PER_DPS,
)
from armfusion.models.simulator import simulate

from tools import chair_disturbances as cd


def test_a_dipole_gives_twice_on_its_axis_what_it_gives_on_its_equator_falling_as_the_cube():
    m = np.array([0.0, 0.0, 2.0])
    on_axis = cd.dipole_ut(m, np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.0]]))
    equator = cd.dipole_ut(m, np.array([[0.5, 0.0, 0.0]]))
    np.testing.assert_allclose(on_axis[0], [0.0, 0.0, 2 * 0.1 * 2.0 / 0.5**3])
    np.testing.assert_allclose(equator[0], [0.0, 0.0, -0.1 * 2.0 / 0.5**3])
    np.testing.assert_allclose(on_axis[1], on_axis[0] / 8.0)


@pytest.fixture(scope="module")
def drive():
    arm = load_arm("wmra")
    rec, _ = simulate(arm, "daily-use", 120.0, seed=11)
    return arm, rec, cd.chair_path(arm, 120.0, 11)


def test_the_rebuilt_path_is_the_one_that_drove_the_recording(drive):
    _, rec, sc = drive
    tb = rec.get("true_base")
    rpy, _, _ = sc.base.rpy(tb.t_s)
    np.testing.assert_allclose(rpy, tb.values, atol=1e-9)


def test_the_passed_magnet_is_strongest_where_the_chair_passes_it_and_gone_far_from_it(drive):
    arm, rec, sc = drive
    t_pass = cd.pass_moment(sc, 30.0)
    v, _, _ = sc.base.speed(np.array([t_pass]))
    assert v[0, 0] >= 0.5  # the chair cruises there
    passed, peak_ut = cd.magnet_passed(rec, arm, sc, t_pass, np.array([0.0, 2.0, 0.0]), 0.25)
    m = rec.get("imu_mag")
    added = (passed.get("imu_mag").values - m.values) * AK8975_UT_PER_LSB
    size = np.linalg.norm(added, axis=1)
    # at 0.25 m a 2 A m² dipole gives between 0.1 m/r³ (equator) and twice that (axis)
    assert 0.1 * 2.0 / 0.25**3 * 0.9 <= peak_ut <= 2 * 0.1 * 2.0 / 0.25**3 * 1.1
    assert abs(m.t_s[np.argmax(size)] - t_pass) < 0.5
    far = np.abs(m.t_s - t_pass) > 20.0  # metres away: below the compass's resolution
    assert size[far].max() <= 2 * AK8975_UT_PER_LSB


def test_rough_ground_shakes_the_imu_only_within_its_stretch_and_moves_it_nowhere(drive):
    arm, rec, sc = drive
    shaken = cd.rough_ground(rec, arm, sc, 40.0, 70.0, seed=3, accel_g_rms=0.2, rate_dps_rms=3.0)
    for name, per in (("imu_acc", MPU9150_ACCEL_LSB_PER_G), ("imu_gyro", MPU9150_GYRO_LSB_PER_DPS)):
        s = rec.get(name)
        d = (shaken.get(name).values - s.values) / per
        inside = (s.t_s > 41.0) & (s.t_s < 69.0)
        assert not d[(s.t_s < 40.0) | (s.t_s > 70.0)].any()
        total_rms = np.sqrt(np.mean(np.sum(d[inside] ** 2, axis=1)))
        want = 0.2 if name == "imu_acc" else 3.0 * np.sqrt(2)  # (vertical; roll and pitch each)
        assert total_rms == pytest.approx(want, rel=0.1)
        assert np.abs(d[inside].mean(axis=0)).max() < 0.05 * want  # zero-mean: no tilt, no turn
    np.testing.assert_array_equal(shaken.get("enc").values, rec.get("enc").values)


def test_a_clipped_magnet_adds_its_field_from_its_moment_to_the_end(drive):
    arm, rec, _ = drive
    field = np.array([15.0, -12.0, 8.0])
    clipped = cd.magnet_clipped(rec, 60.0, field)
    m = rec.get("imu_mag")
    added = (clipped.get("imu_mag").values - m.values) * AK8975_UT_PER_LSB
    assert not added[m.t_s < 60.0].any()
    np.testing.assert_allclose(added[m.t_s > 62.0].mean(axis=0), field, atol=AK8975_UT_PER_LSB)
