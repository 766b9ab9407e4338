"""Count models: datasheet gains, zeros, noise, rounding and saturation of every stream."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.models.effects import Model
from armfusion.models.motion import MotionState
from armfusion.models.sensor_models import (
    ADXL345_LSB_PER_G,
    AK8975_UT_PER_LSB,
    EARTH_FIELD_TAMPA_UT,
    MPU9150_ACCEL_LSB_PER_G,
    MPU9150_GYRO_LSB_PER_DPS,
    stream_models,
)


def test_wmra_streams_and_their_columns(wmra):
    sm = stream_models(wmra)
    assert list(sm) == ["acc1", "acc2", "acc3", "acc4", "imu_acc", "imu_gyro", "imu_mag", "imu_temp", "enc"]
    assert sm["acc3"].channels == ("acc3_x", "acc3_y", "acc3_z")
    assert sm["enc"].channels == tuple(f"enc{i}" for i in range(1, 8))
    np.testing.assert_allclose(sm["enc"].gain, wmra.counts_per_rad)


def test_adxl345_reads_256_counts_per_g_and_saturates_at_10_bits(wmra):
    m = stream_models(wmra)["acc1"]
    counts = m.digitise(m.to_counts(np.array([[0.0, 0.5, 1.0], [3.0, -3.0, 1.999]])), None)
    np.testing.assert_array_equal(counts, [[0, 128, 256], [511, -512, 512 - 1]])
    assert ADXL345_LSB_PER_G == 256.0


@pytest.mark.parametrize("rate_hz", [100.0, 400.0])
def test_adxl345_noise_is_the_datasheet_rms_at_the_rate(wmra, rng, rate_hz):
    m = stream_models(wmra, rate_hz)["acc2"]
    c = m.digitise(np.full((40000, 3), 10.3), rng) - 10.3
    expect = np.array([0.75, 0.75, 1.1]) * np.sqrt(rate_hz / 100.0)
    # rounding adds 1/12 LSB² of variance; 40,000 samples give the rms to about 0.5 %
    np.testing.assert_allclose(c.std(axis=0), np.sqrt(expect**2 + 1 / 12), rtol=0.03)


def test_imu_counts_follow_the_mpu9150_and_ak8975_datasheets(wmra):
    """Level and still, heading north: accel z = 16384, gyro 0, compass = Earth's field
    in 0.3 µT steps, temperature register (T - 35)·340."""
    model = Model(wmra)
    state = MotionState.static(wmra.ready_pose_rad, temperature_c=30.0)
    p = model.predict(state)
    np.testing.assert_allclose(p["imu_acc"][0], [0, 0, MPU9150_ACCEL_LSB_PER_G], atol=1e-9)
    np.testing.assert_allclose(p["imu_gyro"][0], 0, atol=1e-12)
    np.testing.assert_allclose(p["imu_mag"][0], EARTH_FIELD_TAMPA_UT / AK8975_UT_PER_LSB, atol=1e-9)
    assert p["imu_temp"][0, 0] == pytest.approx((30.0 - 35.0) * 340.0)
    # a chair turning at 10 °/s about its vertical axis reads 1310 counts on gyro z
    turning = state.replace(omega_B_rad_s=np.array([[0, 0, np.radians(10)]]))
    assert model.predict(turning, streams=["imu_gyro"])["imu_gyro"][0, 2] == pytest.approx(
        10 * MPU9150_GYRO_LSB_PER_DPS)


def test_imu_noise_at_100_hz(wmra, rng):
    sm = stream_models(wmra, 100.0)
    # 400 µg/√Hz over 50 Hz: 2.8 mg = 46 LSB; 0.005 °/s/√Hz over 50 Hz: 4.6 LSB
    assert sm["imu_acc"].noise_counts_rms[0] == pytest.approx(46.3, abs=0.1)
    assert sm["imu_gyro"].noise_counts_rms[0] == pytest.approx(4.63, abs=0.01)
    assert sm["enc"].noise_counts_rms.max() == 0.0
    assert sm["enc"].sigma_counts[0] == pytest.approx(np.sqrt(1 / 12))


def test_counts_back_to_physical_values(wmra, rng):
    for m in stream_models(wmra).values():
        v = rng.normal(0, 0.3, (10, m.size))
        np.testing.assert_allclose(m.from_counts(m.to_counts(v)), v, atol=1e-12)


def test_the_articles_analog_triax_reads_volts_through_a_14_bit_adc(crs):
    m = stream_models(crs)["triax"]
    # 2.5 V at 0 g, 1.25 V/g, 819.2 counts/V: 1 g reads 3.75 V = 3072 counts
    np.testing.assert_allclose(m.to_counts(np.array([[0.0, 1.0, -1.0]])), [[2048, 3072, 1024]])
    np.testing.assert_allclose(m.noise_counts_rms, np.array([0.0134, 0.0136, 0.0146]) * 819.2)
