"""ADXL345 driver against its register-level fake, over I2C and SPI."""

from __future__ import annotations

import errno

import numpy as np
import pytest
from armfusion.sensors.adxl345 import (
    ADXL345,
    ADXL345Config,
    accel_stream,
    rate_code,
    self_test_limits_lsb,
)
from armfusion.sensors.bus import DeviceNotFoundError, SpiRegisters, Status
from armfusion.sensors.fakes import FakeADXL345, FakeSMBus, FakeSpiController, FunctionPhysics, StaticPhysics

#: Data sheet init: standby, DATA_FORMAT, BW_RATE, offsets zeroed, FIFO_CTL, measure
#: (configuration in standby, measure last, as the data sheet advises).
INIT_WRITES_DEFAULT = [
    (0x2D, 0x00), (0x31, 0x00), (0x2C, 0x0A),
    (0x1E, 0x00), (0x1F, 0x00), (0x20, 0x00),
    (0x38, 0x00), (0x2D, 0x08),
]


def period(driver: ADXL345) -> float:
    return 1.0 / driver.config.rate_hz


# --- init ----------------------------------------------------------------------------


def test_i2c_init_checks_devid_then_writes_the_datasheet_sequence(rig):
    rig.adxl_i2c()
    log = list(rig.bus.log)
    assert (log[0].op, log[0].address, log[0].register, log[0].data) == ("read", 0x53, 0x00, (0xE5,))
    assert rig.bus.writes(0x53) == INIT_WRITES_DEFAULT
    # in standby, stale data is flushed (one burst from INT_SOURCE); after measure is set
    # the configuration is read back: BW_RATE..DATA_FORMAT, then FIFO_CTL
    reads = [(x.register, len(x.data)) for x in log if x.op == "read"]
    assert reads[1:] == [(0x30, 8), (0x2C, 6), (0x38, 1)]
    assert rig.fake.violations == []
    assert rig.driver.online


def test_init_writes_follow_the_config(rig):
    cfg = ADXL345Config(range_g=16, full_resolution=True, rate_hz=400, fifo=True, fifo_watermark=20)
    rig.adxl_i2c(config=cfg, address=0x1D)
    assert rig.bus.writes(0x1D) == [
        (0x2D, 0x00), (0x31, 0x0B), (0x2C, 0x0C),
        (0x1E, 0x00), (0x1F, 0x00), (0x20, 0x00),
        (0x38, 0x00), (0x38, 0x80 | 20), (0x2D, 0x08),  # bypass first: empties the FIFO
    ]


def test_spi_framing_mode_and_clock(rig):
    rig.adxl_spi()
    frames = rig.spi.frames(0, 0)
    assert frames[0].mosi == (0x80, 0x00) and frames[0].miso[1] == 0xE5  # read DEVID
    writes = [f.mosi for f in frames if not f.mosi[0] & 0x80]
    assert writes == [tuple(w) for w in INIT_WRITES_DEFAULT]
    assert frames[-2].mosi == (0x80 | 0x40 | 0x2C,) + (0,) * 6  # multi-byte read-back
    assert frames[-1].mosi == (0x80 | 0x38, 0)  # single-byte read: no multi-byte bit
    assert all(f.mode == 3 and f.speed_hz == 1_000_000 for f in frames)
    rig.clock.advance(period(rig.driver))
    s = rig.driver.read()
    assert rig.spi.log[-1].mosi == (0x80 | 0x40 | 0x30,) + (0,) * 8  # one 8-byte burst
    assert s.status is Status.OK


def test_spi_clock_above_5mhz_is_refused():
    with pytest.raises(ValueError, match=r"SPI clock must be 1\.\.5000000 Hz, not 8000000"):
        ADXL345.spi(0, 0, max_speed_hz=8_000_000, spi_factory=lambda: None)


def test_i2c_address_must_be_an_adxl345_address():
    with pytest.raises(ValueError, match=r"0x53 \(ALT ADDRESS low\) or 0x1D \(high\), not 0x54"):
        ADXL345.i2c(1, 0x54, smbus=FakeSMBus(1))


def test_missing_i2c_device_gives_one_clear_line(rig, clock):
    bus = FakeSMBus(1, [], clock=clock)
    drv = ADXL345.i2c(1, 0x53, smbus=bus, **rig.driver_kw())
    with pytest.raises(DeviceNotFoundError,
                       match=r"^no ADXL345 on I2C bus 1 at 0x53: \[Errno 121\] Remote I/O error$"):
        drv.init()
    assert drv.health()["bus_errors"] == 3  # every attempt of the DEVID read


def test_wrong_devid_names_what_was_read(rig):
    with pytest.raises(DeviceNotFoundError,
                       match=r"^no ADXL345 on I2C bus 1 at 0x53: DEVID read 0x00, expected 0xE5$"):
        rig.adxl_i2c(devid=0x00)


def test_absent_spi_device_reads_zero(rig):
    drv = rig.adxl_spi(init=False)
    rig.fake.disappear()
    with pytest.raises(DeviceNotFoundError,
                       match=r"no ADXL345 on SPI bus 0 device 0 \(/dev/spidev0\.0\): DEVID read "
                             r"0x00, expected 0xE5 \(check wiring, chip select, SPI mode 3"):
        drv.init()


@pytest.mark.parametrize("mode, speed", [(0, 5_000_000), (3, 10_000_000)])
def test_wrong_spi_mode_or_clock_reads_garbage(clock, mode, speed):
    fake = FakeADXL345(StaticPhysics(), clock.monotonic)
    spi = FakeSpiController({(0, 0): fake}, clock=clock)
    transport = SpiRegisters.open(spi.SpiDev, 0, 0, mode=mode, max_speed_hz=speed)
    with pytest.raises(DeviceNotFoundError, match=r"DEVID read 0xCB, expected 0xE5"):
        ADXL345(transport, clock=clock.monotonic, sleep=clock.sleep).init()
    assert fake.regs[0x2D] == 0x00  # nothing was written


# --- readings ------------------------------------------------------------------------

FORMATS = [
    ADXL345Config(),  # ±2 g, 10-bit, 256 LSB/g
    ADXL345Config(range_g=4),  # 128 LSB/g
    ADXL345Config(range_g=16, full_resolution=True),  # 256 LSB/g, 13 bits
]


@pytest.mark.parametrize("transport", ["i2c", "spi"])
@pytest.mark.parametrize("cfg", FORMATS, ids=["2g-10bit", "4g-10bit", "16g-fullres"])
def test_counts_round_trip_to_specific_force(rig, transport, cfg):
    rng = np.random.default_rng(345)
    lo, hi = cfg.count_limits
    forces = rng.uniform(0.95 * lo, 0.95 * hi, size=(20, 3)) / cfg.lsb_per_g
    truth: dict[float, np.ndarray] = {}

    def f(t):  # a new random force for each sample, remembered by sample time
        truth[t] = forces[len(truth) % len(forces)]
        return truth[t]

    drv = (rig.adxl_i2c if transport == "i2c" else rig.adxl_spi)(FunctionPhysics(f), cfg)
    for _ in range(20):
        rig.clock.advance(period(drv))
        s = drv.read()
        assert s.status is Status.OK and all(isinstance(c, int) for c in s.counts)
        sample = rig.fake.produced[-1]  # the newest: what a bypass-mode read returns
        back_g = np.array(s.counts) / cfg.lsb_per_g
        # one count is the resolution; the fake rounds to the nearest count (≤ 0.5)
        assert np.all(np.abs(back_g - truth[sample.t_s]) * cfg.lsb_per_g <= 0.5 + 1e-9)


def test_outputs_saturate_at_the_10_bit_range(rig):
    drv = rig.adxl_i2c(StaticPhysics((3.0, -3.0, 1.0)))
    rig.clock.advance(period(drv))
    assert drv.read().counts == (511, -512, 256)


def test_sample_time_is_the_clock_at_read(rig):
    drv = rig.adxl_i2c()
    rig.clock.advance(0.0123)
    t_before = rig.clock.monotonic()
    s = drv.read()
    assert s.t_s == t_before and rig.clock.monotonic() > t_before  # the burst took wire time


def test_no_new_data_is_stale_not_repeated(rig):
    drv = rig.adxl_i2c()
    rig.clock.advance(period(drv))
    assert drv.read().status is Status.OK
    s = drv.read()  # same sample period: nothing new
    assert s.status is Status.STALE and s.counts is None
    assert drv.health()["stale"] == 1


def test_overrun_is_reported_when_samples_were_overwritten(rig):
    drv = rig.adxl_i2c()
    rig.clock.advance(3 * period(drv))
    s = drv.read()
    assert s.valid and s.overrun
    assert drv.health()["overruns"] == 1


# --- FIFO ----------------------------------------------------------------------------


def test_fifo_gives_every_sample_in_order(rig):
    ramp = FunctionPhysics(lambda t: (((t * 100) % 400 - 200) / 256, 0.0, 1.0))
    drv = rig.adxl_i2c(ramp, ADXL345Config(fifo=True))
    got = []
    for step in (0.013, 0.055, 0.101, 0.007, 0.2):  # irregular host reads
        rig.clock.advance(step)
        got += drv.read_fifo()
    produced = [p.counts for p in rig.fake.produced]
    assert len(produced) >= 37  # 0.376 s at 100 Hz, and the reads' own wire time
    # every sample in order; those made during the last drain wait in the FIFO
    assert [s.counts for s in got] == produced[:len(got)]
    assert len(produced) - len(got) == len(rig.fake._fifo) <= 2
    t = np.array([s.t_s for s in got])
    assert np.all(np.diff(t) > 0)
    assert not any(s.overrun for s in got)
    rig.fake.data_ready_never = True  # no new samples from here on
    assert len(drv.read_fifo()) == len(produced) - len(got)
    assert drv.read_fifo() == []  # empty FIFO: nothing, not a repeat


def test_fifo_overflow_is_flagged(rig):
    drv = rig.adxl_i2c(config=ADXL345Config(fifo=True))
    rig.clock.advance(40 * period(drv))
    got = drv.read_fifo()
    assert len(got) == 32 and got[0].overrun and not any(s.overrun for s in got[1:])
    assert drv.health()["overruns"] == 1


def test_read_and_read_fifo_refuse_the_wrong_mode(rig):
    drv = rig.adxl_i2c()
    with pytest.raises(RuntimeError, match="configured with fifo=False, use read"):
        drv.read_fifo()


# --- faults --------------------------------------------------------------------------


def test_a_short_nack_burst_is_retried_with_exponential_backoff(rig):
    drv = rig.adxl_i2c()
    rig.clock.advance(period(drv))
    rig.sleeps.clear()
    rig.bus.faults.fail_next(2, errno.EIO)
    s = drv.read()
    assert s.status is Status.OK
    assert rig.sleeps == [0.0005, 0.001]
    h = drv.health()
    assert (h["bus_errors"], h["retries"], h["invalid"]) == (2, 2, 0)


def test_spi_transfer_errors_are_retried(rig):
    drv = rig.adxl_spi()
    rig.clock.advance(period(drv))
    rig.spi.faults.fail_next(2, errno.EIO)  # the spidev ioctl failed twice
    assert drv.read().valid and drv.health()["retries"] == 2


def test_stuck_bus_marks_samples_goes_offline_backs_off_and_recovers(rig):
    drv = rig.adxl_i2c()
    rig.bus.faults.stick(errno.ETIMEDOUT)
    statuses = []
    for _ in range(5):
        rig.clock.advance(period(drv))
        statuses.append(drv.read().status)
    assert statuses == [Status.BUS_ERROR] * 3 + [Status.OFFLINE] * 2
    h = drv.health()
    assert not h.online and h["offline"] == 1 and h["invalid"] == 5
    assert "[Errno 110] Connection timed out" in h.last_error
    n_log = len(rig.bus.log)
    drv.read()  # offline, re-init not due yet (first after 50 ms): no bus traffic
    assert len(rig.bus.log) == n_log
    rig.clock.advance(0.05)
    assert drv.read().status is Status.OFFLINE  # re-init tried and failed
    assert drv.health()["reinit_failures"] == 1 and len(rig.bus.log) > n_log
    n_log = len(rig.bus.log)
    rig.clock.advance(0.06)  # next try only 100 ms later: backoff doubled
    drv.read()
    assert len(rig.bus.log) == n_log
    rig.bus.faults.clear()
    rig.clock.advance(0.05)
    assert drv.read().status is Status.STALE  # re-initialised; first sample one period on
    rig.clock.advance(period(drv))
    assert drv.read().counts == (0, 0, 256)
    assert drv.health()["reinits"] == 1 and drv.online


def test_device_that_disappears_and_comes_back_is_reinitialised(rig):
    drv = rig.adxl_i2c(StaticPhysics((0.0, 0.5, 0.5)))
    rig.fake.disappear()
    for _ in range(4):
        rig.clock.advance(period(drv))
        assert not drv.read().valid
    rig.fake.reappear(power_cycled=True)  # back with reset registers (standby)
    rig.bus.log.clear()
    rig.clock.advance(0.2)  # past the re-init delay
    statuses = [drv.read().status]
    rig.clock.advance(period(drv))
    s = drv.read()
    statuses.append(s.status)
    assert statuses == [Status.STALE, Status.OK] and s.counts == (0, 128, 128)
    assert rig.bus.writes(0x53) == INIT_WRITES_DEFAULT
    assert drv.health()["reinits"] == 1 and drv.online


def test_spi_device_reset_is_caught_by_the_check_byte(rig):
    cfg = ADXL345Config(full_resolution=True)  # DATA_FORMAT 0x08: a reset reads 0x00
    drv = rig.adxl_spi(config=cfg)
    rig.clock.advance(period(drv))
    assert drv.read().valid
    rig.fake.reset()  # brown-out: SPI cannot NACK, registers are back to reset
    rig.clock.advance(period(drv))
    assert drv.read().status is Status.BAD_DATA
    s = drv.read()  # re-initialised at once
    rig.clock.advance(period(drv))
    assert s.status is Status.STALE and drv.read().valid
    assert drv.health()["bad_data"] == 1 and drv.health()["reinits"] == 1


def test_spi_device_reset_to_same_format_is_caught_by_missing_data(rig):
    drv = rig.adxl_spi()  # DATA_FORMAT 0x00 equals its reset value
    rig.clock.advance(period(drv))
    assert drv.read().valid
    rig.fake.reset()  # standby: DATA_READY never comes
    seen = []
    for _ in range(80):
        rig.clock.advance(period(drv))
        seen.append(drv.read().status)
    assert Status.NOT_READY in seen and seen[-1] is Status.OK
    assert drv.health()["reinits"] == 1


def test_data_ready_never_set_gives_not_ready_not_invented_data(rig):
    drv = rig.adxl_i2c()
    rig.fake.data_ready_never = True
    seen = []
    for _ in range(30):
        rig.clock.advance(period(drv))
        seen.append(drv.read())
    assert all(s.counts is None for s in seen)
    assert {s.status for s in seen} == {Status.STALE, Status.NOT_READY}
    assert drv.health()["not_ready"] >= 1


def test_random_failures_never_crash_and_are_all_accounted_for(rig):
    drv = rig.adxl_i2c(StaticPhysics((0.25, 0.0, 1.0)))
    rig.bus.faults.fail_randomly(0.4, errno.EIO)  # seeded
    seen = []
    for _ in range(300):
        rig.clock.advance(period(drv))
        seen.append(drv.read())
    ok = [s for s in seen if s.valid]
    assert ok and all(s.counts == (64, 0, 256) for s in ok)
    h = drv.health()
    assert h["ok"] == len(ok)
    assert h["invalid"] == sum(s.status in (Status.BUS_ERROR, Status.OFFLINE, Status.BAD_DATA)
                               for s in seen)
    assert h["bus_errors"] == rig.bus.faults.injected


# --- self-test -----------------------------------------------------------------------


def test_self_test_limits_are_table_15_scaled_for_the_supply():
    assert self_test_limits_lsb(2.5) == ((50, 540), (-540, -50), (75, 875))
    lim = self_test_limits_lsb(3.3)  # Table 14: ×1.77 (x, y), ×1.47 (z)
    assert lim[0] == pytest.approx((88.5, 955.8)) and lim[2] == pytest.approx((110.25, 1286.25))
    with pytest.raises(ValueError, match=r"tabulated for VS in \[2\.0, 2\.5, 3\.3, 3\.6\] V"):
        self_test_limits_lsb(3.0)


def test_self_test_passes_on_a_healthy_sensor_and_restores_the_config(rig):
    drv = rig.adxl_i2c(StaticPhysics((0.0, 0.0, 1.0)))
    rig.bus.log.clear()
    r = drv.self_test()
    assert r.passed, r.message
    assert r.delta_lsb == pytest.approx((1.9 * 256, -1.9 * 256, 2.7 * 256), abs=1)
    writes = rig.bus.writes(0x53)
    # full resolution ±16 g at 100 Hz normal power, self-test on, off, then the config again
    assert writes[:8] == [(0x2D, 0), (0x31, 0x0B), (0x2C, 0x0A), (0x1E, 0), (0x1F, 0),
                          (0x20, 0), (0x38, 0), (0x2D, 0x08)]
    assert writes[8:10] == [(0x31, 0x8B), (0x31, 0x0B)]  # self-test on, off
    assert writes[10:] == INIT_WRITES_DEFAULT
    rig.clock.advance(period(drv))
    assert drv.read().counts == (0, 0, 256)


def test_self_test_fails_on_a_stuck_sensor(rig):
    drv = rig.adxl_i2c()
    rig.fake.stuck_counts = (0, 0, 256)
    r = drv.self_test()
    assert not r.passed
    assert r.message.startswith("ADXL345 on I2C bus 1 at 0x53: self-test FAILED (VS = 3.3 V")
    assert "x change +0.0 LSB outside [88.5, 955.8]" in r.message


def test_self_test_fails_on_a_dead_sensor(rig):
    drv = rig.adxl_i2c()
    rig.fake.data_ready_never = True
    r = drv.self_test()
    assert not r.passed and "no data (DATA_READY never set)" in r.message


# --- plumbing ------------------------------------------------------------------------


def test_rate_codes_follow_the_datasheet():
    assert [rate_code(r) for r in (3200, 800, 100, 25, 0.1)] == [0x0F, 0x0D, 0x0A, 0x08, 0x00]
    assert ADXL345Config(rate_hz=0.1).output_rate_hz == 3200 / 2**15
    with pytest.raises(ValueError, match=r"output data rate 120 Hz is not one of 3200, 1600"):
        ADXL345Config(rate_hz=120)


def test_accel_stream_keeps_only_valid_samples(rig):
    drv = rig.adxl_i2c()
    samples = []
    for _ in range(5):
        rig.clock.advance(period(drv))
        samples += [drv.read(), drv.read()]  # every second one is stale
    st = accel_stream("acc1", samples)
    n_ok = sum(s.valid for s in samples)
    assert 5 <= n_ok < 10  # some reads came within one sample period: stale, dropped
    assert st.kind == "accel" and st.channels == ("acc1_x", "acc1_y", "acc1_z")
    assert st.values.shape == (n_ok, 3) and np.all(st.values == [0, 0, 256])
