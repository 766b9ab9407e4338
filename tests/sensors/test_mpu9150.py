"""MPU-9150 + AK8975 driver against the register-level fakes on one fake I2C bus."""

from __future__ import annotations

import errno

import numpy as np
import pytest
from armfusion.sensors.bus import DeviceNotFoundError, Status
from armfusion.sensors.fakes import FakeMPU9150, FakeSMBus, FunctionPhysics, StaticPhysics
from armfusion.sensors.mpu9150 import MPU9150, MPU9150Config, asa_factor, imu_streams

#: MPU-9150: reset, wake on the X-gyro PLL, rate divider, DLPF, ±250 °/s, ±2 g,
#: I2C master off, then bypass on (the AK8975 appears on the host's bus).
MPU_INIT_WRITES = [
    (0x6B, 0x80), (0x6B, 0x01), (0x19, 0x00), (0x1A, 0x03),
    (0x1B, 0x00), (0x1C, 0x00), (0x6A, 0x00), (0x37, 0x02),
]
#: AK8975: power-down, fuse-ROM access (ASA read here), power-down.
AK_INIT_WRITES = [(0x0A, 0x00), (0x0A, 0x0F), (0x0A, 0x00)]
TICK = 0.01  # the host reads at 100 Hz


def test_init_sequence_follows_the_register_map_and_the_ak8975_datasheet(rig):
    rig.mpu()
    log = list(rig.bus.log)
    assert (log[0].address, log[0].op, log[0].register, log[0].data) == (0x68, "read", 0x75, (0x68,))
    assert rig.bus.writes(0x68) == MPU_INIT_WRITES
    assert rig.bus.writes(0x0C) == AK_INIT_WRITES
    ak_reads = [(x.register, x.data) for x in log if x.address == 0x0C and x.op == "read"]
    assert ak_reads == [(0x00, (0x48,)), (0x10, (176, 178, 165))]  # WIA, then ASA in fuse mode
    assert rig.driver.asa == (176, 178, 165)
    # 100 ms after the reset, 50 ms for the PLL; ≥ 100 µs after each AK8975 power-down
    assert rig.sleeps[:2] == [0.1, 0.05] and all(s >= 100e-6 for s in rig.sleeps[2:])
    assert rig.fake.violations == [] and rig.ak.violations == []


def test_readings_round_trip_from_physics_to_counts_and_back(rig):
    rng = np.random.default_rng(9150)
    cases = [(rng.uniform(-1.9, 1.9, 3), rng.uniform(-4, 4, 3), rng.uniform(-70, 70, 3),
              rng.uniform(-20, 60)) for _ in range(30)]
    state = {"i": 0}

    def case(t):
        return cases[state["i"]]

    phys = FunctionPhysics(lambda t: case(t)[0], lambda t: case(t)[1], lambda t: case(t)[2],
                           lambda t: case(t)[3])
    drv = rig.mpu(phys)
    cfg = drv.config
    f = np.array([asa_factor(a) for a in drv.asa])
    drv.read()  # starts the first magnetometer measurement
    for i in range(len(cases)):
        state["i"] = i
        rig.clock.advance(TICK)
        s = drv.read()
        assert s.valid and s.mag_valid
        acc, gyro, mag, temp = cases[i]
        # accel and gyro: nearest count, so within half an LSB
        assert np.abs(np.array(s.accel) / cfg.accel_lsb_per_g - acc).max() * 16384 <= 0.5 + 1e-9
        assert np.abs(np.array(s.gyro) / cfg.gyro_lsb_per_dps - np.degrees(gyro)).max() * 131 \
            <= 0.5 + 1e-9
        assert abs((s.temp / 340 + 35) - temp) * 340 <= 0.5 + 1e-9
        # mag: the raw register is quantised in steps of ASA-factor adjusted counts,
        # then rounded again: within one raw LSB (factor, in adjusted counts)
        ak_f = np.array([f[1], f[0], f[2]])  # remapped into the MPU axes
        err = np.abs(np.array(s.mag) * 0.3 - mag) / 0.3
        assert np.all(err <= 0.5 * ak_f + 0.5 + 1e-9) and np.all(err <= np.maximum(ak_f, 1))
        # the measurement it belongs to was started at the previous read
        assert rig.clock.monotonic() - s.t_mag_s < 2 * TICK


def test_magnetometer_axes_are_remapped_into_the_accelerometers(rig):
    drv = rig.mpu(StaticPhysics(magnetic_field=(30.0, 0.0, 0.0)), asa=(128, 128, 128))
    drv.read()
    rig.clock.advance(TICK)
    s = drv.read()
    assert s.mag == (100, 0, 0)
    raw = [x for x in rig.bus.log if x.address == 0x0C and x.register == 0x03][-1].data
    assert raw[:6] == (0, 0, 100, 0, 0, 0)  # the AK8975 saw it on its own y axis
    drv2 = rig.mpu(StaticPhysics(magnetic_field=(0.0, 0.0, 30.0)), asa=(128, 128, 128))
    drv2.read()
    rig.clock.advance(TICK)
    assert drv2.read().mag == (0, 0, 100)  # AK z = -MPU z, undone by the driver


def test_sensitivity_adjustment_recovers_the_field_whatever_the_fuse_values(rig):
    assert asa_factor(128) == 1.0 and asa_factor(0) == 0.5 and asa_factor(255) == pytest.approx(
        1.49609375)
    out = []
    for asa in [(128, 128, 128), (255, 0, 200), (60, 190, 128)]:
        drv = rig.mpu(StaticPhysics(magnetic_field=(21.0, -33.0, 45.0)), asa=asa)
        drv.read()
        rig.clock.advance(TICK)
        out.append(np.array(drv.read().mag))
    truth = np.array([21.0, -33.0, 45.0]) / 0.3
    for m in out:
        assert np.abs(m - truth).max() <= 1.25  # ≤ one raw LSB (factor ≤ 1.5) + rounding


def test_missing_mpu_gives_one_clear_line(rig, clock):
    drv = MPU9150.i2c(1, smbus=FakeSMBus(1, [], clock=clock), **rig.driver_kw())
    with pytest.raises(DeviceNotFoundError,
                       match=r"^no MPU-9150 on I2C bus 1 at 0x68: \[Errno 121\] Remote I/O error$"):
        drv.init()


def test_wrong_who_am_i(rig):
    with pytest.raises(DeviceNotFoundError,
                       match=r"^no MPU-9150 on I2C bus 1 at 0x68: WHO_AM_I read 0x71, expected 0x68$"):
        rig.mpu(who_am_i=0x71)


def test_wrong_wia_names_the_magnetometer(rig):
    drv = rig.mpu(init=False)
    rig.ak.wia = 0x00
    with pytest.raises(DeviceNotFoundError,
                       match=r"^no AK8975 on I2C bus 1 at 0x0C \(AK8975 behind the MPU-9150 at "
                             r"0x68\): WIA read 0x00, expected 0x48$"):
        drv.init()


def test_the_magnetometer_can_be_left_off(rig):
    drv = rig.mpu(config=MPU9150Config(magnetometer=False))
    assert rig.bus.writes(0x68)[-1] == (0x37, 0x00) and rig.bus.writes(0x0C) == []
    rig.clock.advance(TICK)
    s = drv.read()
    assert s.valid and s.mag_status is Status.DISABLED


# --- the fakes behave like the parts ------------------------------------------------


def test_ak8975_is_only_on_the_bus_through_the_bypass(clock):
    mpu = FakeMPU9150(StaticPhysics(), clock.monotonic)
    bus = FakeSMBus(1, [mpu, mpu.ak8975], clock=clock)
    with pytest.raises(OSError, match="Remote I/O error"):
        bus.read_byte_data(0x0C, 0x00)
    bus.write_byte_data(0x68, 0x37, 0x02)
    assert bus.read_byte_data(0x0C, 0x00) == 0x48
    bus.write_byte_data(0x68, 0x6A, 0x20)  # I2C master on: the bypass no longer applies
    with pytest.raises(OSError):
        bus.read_byte_data(0x0C, 0x00)


def test_ak8975_fuse_rom_and_mode_rules(clock):
    mpu = FakeMPU9150(StaticPhysics(), clock.monotonic, asa=(170, 171, 172))
    ak = mpu.ak8975
    bus = FakeSMBus(1, [mpu, ak])  # no clock: transfers take no time here
    bus.write_byte_data(0x68, 0x37, 0x02)
    assert bus.read_i2c_block_data(0x0C, 0x10, 3) == [0, 0, 0]  # not in fuse-ROM mode
    bus.write_byte_data(0x0C, 0x0A, 0x0F)
    assert bus.read_i2c_block_data(0x0C, 0x10, 3) == [170, 171, 172]
    bus.write_byte_data(0x0C, 0x0A, 0x01)  # single measurement without power-down first
    assert "power-down first" in ak.violations[-1]
    bus.write_byte_data(0x0C, 0x0A, 0x00)
    bus.write_byte_data(0x0C, 0x0A, 0x01)  # too soon after power-down
    assert "needs 100 µs" in ak.violations[-1]
    assert bus.read_byte_data(0x0C, 0x02) == 0x00
    clock.advance(0.008)  # a measurement takes 7.3 ms
    assert bus.read_byte_data(0x0C, 0x02) == 0x01  # DRDY
    bus.read_i2c_block_data(0x0C, 0x03, 6)
    assert bus.read_byte_data(0x0C, 0x02) == 0x01
    bus.read_byte_data(0x0C, 0x09)  # reading ST2 ends the read
    assert bus.read_byte_data(0x0C, 0x02) == 0x00


def test_mpu_data_update_only_when_awake(clock):
    mpu = FakeMPU9150(StaticPhysics(), clock.monotonic)
    bus = FakeSMBus(1, [mpu], clock=clock)
    clock.advance(0.1)
    assert bus.read_i2c_block_data(0x68, 0x3B, 6) == [0] * 6  # asleep after reset
    bus.write_byte_data(0x68, 0x6B, 0x01)
    clock.advance(0.002)
    assert bus.read_i2c_block_data(0x68, 0x3B, 6) == [0, 0, 0, 0, 0x40, 0x00]  # +1 g on z


# --- faults --------------------------------------------------------------------------


def test_data_ready_never_set_marks_the_magnetometer_not_ready_only(rig):
    drv = rig.mpu()
    drv.read()
    rig.ak.drdy_never = True
    seen = []
    for _ in range(25):
        rig.clock.advance(TICK)
        seen.append(drv.read())
    assert all(s.valid for s in seen)  # accel, gyro, temperature unaffected
    assert all(s.mag is None for s in seen)
    statuses = [s.mag_status for s in seen]
    # pending for the 50 ms timeout, then NOT_READY; three in a row: offline, re-init later
    first = statuses.index(Status.NOT_READY)
    assert 4 <= first <= 5 and set(statuses[:first]) == {Status.STALE}
    assert Status.OFFLINE in statuses
    h = drv.mag_health()
    assert h["not_ready"] >= 3 and h["offline"] == 1
    assert rig.ak.violations == []
    rig.ak.drdy_never = False
    for _ in range(40):
        rig.clock.advance(TICK)
        s = drv.read()
    assert s.mag_valid and drv.mag_health()["reinits"] >= 1


def test_magnetometer_overflow_invalidates_the_sample(rig):
    drv = rig.mpu()
    drv.read()
    rig.ak.force_overflow = True
    rig.clock.advance(TICK)
    s = drv.read()
    assert s.valid and s.mag_status is Status.OVERFLOW and s.mag is None
    rig.ak.force_overflow = False
    rig.clock.advance(TICK)
    assert drv.read().mag_valid
    assert drv.mag_health()["overflow"] == 1


def test_a_field_beyond_the_range_overflows_by_itself(rig):
    drv = rig.mpu(StaticPhysics(magnetic_field=(0.0, 1500.0, 0.0)))
    drv.read()
    rig.clock.advance(TICK)
    assert drv.read().mag_status is Status.OVERFLOW


def test_data_error_invalidates_the_sample(rig):
    drv = rig.mpu()
    drv.read()
    rig.ak.force_data_error = True
    rig.clock.advance(TICK)
    assert drv.read().mag_status is Status.SENSOR_ERROR


def test_nack_burst_is_retried(rig):
    drv = rig.mpu()
    rig.clock.advance(TICK)
    rig.bus.faults.fail_next(2, errno.EIO)
    assert drv.read().valid
    assert drv.health()["retries"] == 2


def test_unplugged_imu_comes_back_reinitialised_with_its_magnetometer(rig):
    drv = rig.mpu(StaticPhysics(specific_force=(0.0, -1.0, 0.0)))
    for _ in range(3):
        rig.clock.advance(TICK)
        drv.read()
    rig.fake.disappear()
    statuses = []
    for _ in range(5):
        rig.clock.advance(TICK)
        s = drv.read()
        statuses.append((s.status, s.mag_status))
        assert s.accel is None and s.mag is None
    assert statuses[:3] == [(Status.BUS_ERROR, Status.BUS_ERROR)] * 3
    assert statuses[3:] == [(Status.OFFLINE, Status.OFFLINE)] * 2
    rig.fake.reappear(power_cycled=True)  # asleep, bypass off: the AK8975 is hidden again
    rig.bus.log.clear()
    for _ in range(10):
        rig.clock.advance(TICK)
        s = drv.read()
    assert s.valid and s.accel == (0, -16384, 0) and s.mag_valid
    assert rig.bus.writes(0x68) == MPU_INIT_WRITES
    assert rig.bus.writes(0x0C)[:3] == AK_INIT_WRITES
    assert drv.health()["reinits"] == 1 and rig.fake.resets == 2


def test_silent_reset_is_caught_by_the_health_check(rig):
    drv = rig.mpu(config=MPU9150Config(health_check_every=10))
    for _ in range(3):
        rig.clock.advance(TICK)
        drv.read()
    rig.fake.reset()  # brown-out without a NACK: asleep, bypass off
    seen = []
    for _ in range(12):
        rig.clock.advance(TICK)
        seen.append(drv.read().status)
    assert Status.BAD_DATA in seen and seen[-1] is Status.OK
    assert drv.health()["reinits"] == 1


def test_stuck_bus_never_raises(rig):
    drv = rig.mpu()
    rig.bus.faults.stick(errno.ETIMEDOUT)
    for _ in range(50):
        rig.clock.advance(TICK)
        s = drv.read()
        assert not s.valid and s.accel is None
    rig.bus.faults.clear()
    for _ in range(80):
        rig.clock.advance(TICK)
        s = drv.read()
    assert s.valid and s.mag_valid


def test_long_run_keeps_to_the_ak8975_protocol_and_streams_convert(rig):
    drv = rig.mpu()
    samples = []
    for _ in range(200):
        rig.clock.advance(TICK)
        samples.append(drv.read())
    assert rig.ak.violations == [] and rig.fake.violations == []
    streams = imu_streams(samples)
    assert set(streams) == {"imu_acc", "imu_gyro", "imu_mag", "imu_temp"}
    assert len(streams["imu_acc"]) == 200 and len(streams["imu_mag"]) == 199
    assert np.all(streams["imu_temp"].values == -3400)  # 25 °C
    assert rig.ak.measurements == 199  # one single measurement per read, the last one running
