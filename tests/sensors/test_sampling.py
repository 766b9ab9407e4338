"""The sampling loop over the whole fake rig: four ADXL345 (two SPI, two I2C) and the IMU."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from armfusion.sensors.adxl345 import ADXL345Config, accel_stream
from armfusion.sensors.bus import DeviceNotFoundError, Status
from armfusion.sensors.fakes import FakeClock, FakeRig, FunctionPhysics
from armfusion.sensors.mpu9150 import imu_streams
from armfusion.sensors.sampling import (
    WMRA_WIRING,
    Collector,
    SamplingLoop,
    Wiring,
    close_all,
    open_devices,
    readers_for,
)

RATE_HZ = 100.0
ACCS = ("acc1", "acc2", "acc3", "acc4")


def ramp_physics() -> dict[str, FunctionPhysics]:
    """Every sample distinct: x ramps one count (1/256 g) per 10 ms, y names the device;
    the IMU's gyro z ramps one count per 1 ms (its sample period)."""
    out = {
        name: FunctionPhysics(
            lambda t, i=i: ((((t * 100.0) % 800.0) - 400.0) / 256.0, 0.1 * i, 1.0))
        for i, name in enumerate(ACCS)
    }
    out["imu"] = FunctionPhysics(
        angular_rate_rad_s=lambda t: (0.0, 0.0, np.radians((((t * 1000.0) % 60000.0) - 30000.0)
                                                           / 131.0)))
    return out


def open_rig(clock: FakeClock, adxl_config: ADXL345Config):
    rig = FakeRig(clock, ramp_physics(), seed=3)
    devices = open_devices(smbus_factory=rig.smbus, spi_factory=rig.spi.SpiDev,
                           adxl_config=adxl_config, clock=clock.monotonic, sleep=clock.sleep)
    return rig, devices


def test_five_seconds_at_100_hz_from_the_whole_rig_without_loss_or_duplicates():
    # the host oversleeps by up to 2 ms (seeded), as a Linux process does
    clock = FakeClock(sleep_jitter_s=0.002, seed=11)
    rig, devices = open_rig(clock, ADXL345Config(rate_hz=100, fifo=True))
    # two accelerometers behind SPI chip selects, two on I2C with the IMU
    assert list(rig.spi.ports.values()) == [rig["acc1"], rig["acc2"]]
    assert rig.i2c[1].devices[:2] == [rig["acc3"], rig["acc4"]]
    sink = Collector()
    loop = SamplingLoop(readers_for(devices), RATE_HZ, sink=sink, clock=clock.monotonic,
                        wait=clock.sleep)
    report = loop.run(threading.Event(), duration_s=5.0)

    assert report.ticks == 500 and report.missed_ticks == 0
    # absolute deadlines: a tick is late by the oversleep only, never by accumulated drift
    assert report.lateness_max_s <= 0.002 + 1e-9
    period = 1.0 / RATE_HZ
    for name in ACCS:
        got = sink.results[name]
        produced = list(rig[name].produced)
        assert all(s.status is Status.OK and not s.overrun for s in got), name
        # every sample the device made, once, in order (the ramp makes each one distinct)
        assert [s.counts for s in got] == [p.counts for p in produced], name
        assert len({s.counts for s in got}) == len(got)
        assert abs(len(got) - 500) <= 2  # 5 s at 100 Hz
        assert len({s.counts[1] for s in got}) == 1  # nothing from another device
        lag = np.array([s.t_s for s in got]) - np.array([p.t_s for p in produced])
        assert np.all(lag >= 0) and np.all(lag < period + 1e-6)  # FIFO back-dating
        accel_stream(name, got)  # times strictly increase: a valid raw stream
    imu = sink.results["imu"]
    assert len(imu) == 500 and all(s.valid for s in imu)
    index_of = {p.gyro[2]: p for p in rig["imu"].produced}
    matched = [index_of[s.gyro[2]] for s in imu]
    idx = np.array([p.index for p in matched])
    assert np.all(np.diff(idx) > 0)  # never the same IMU sample twice
    newest_lag = np.array([s.t_s - p.t_s for s, p in zip(imu, matched, strict=True)])
    assert np.all((newest_lag >= 0) & (newest_lag < 0.001 + 1e-9))  # the newest at read time
    mags = [s for s in imu if s.mag_valid]
    # every completed AK8975 measurement delivered once; a read that comes less than the
    # 7.3 ms measurement time after the trigger (jitter) is STALE and the measurement
    # arrives one tick later: most ticks still carry a fresh magnetometer sample
    assert {s.mag_status for s in imu} == {Status.OK, Status.STALE}
    assert len(mags) == rig["imu"].ak8975.measurements >= 450
    assert np.all(np.diff([s.t_mag_s for s in mags]) > 0)
    streams = imu_streams(imu)
    assert len(streams["imu_gyro"]) == 500
    for dev in devices.values():
        h = dev.health()
        assert h.online and h["invalid"] == 0 and h["bus_errors"] == 0, h.summary()
    for name, t in report.readers.items():
        assert t.reads == 500 and t.read_time_mean_s > 0, name  # wire time on the fake buses
    assert "500 ticks at 100 Hz" in report.summary()
    assert len(rig.spi.frames(0, 1)) > 1000 and rig.i2c[1].log[-1].errno is None


def test_latest_value_mode_accounts_for_every_lost_sample():
    """Bypass mode at ODR = loop rate with a jittery host loses samples: each loss
    must be flagged (Overrun) on the next sample, and no sample may come twice."""
    clock = FakeClock(sleep_jitter_s=0.008, seed=5)  # a loaded Pi
    rig, devices = open_rig(clock, ADXL345Config(rate_hz=100))
    sink = Collector()
    SamplingLoop(readers_for(devices), RATE_HZ, sink=sink, clock=clock.monotonic,
                 wait=clock.sleep).run(threading.Event(), duration_s=3.0)
    lost = {}
    for name in ACCS:
        got = sink.results[name]
        ok = [s for s in got if s.valid]
        assert {s.status for s in got} <= {Status.OK, Status.STALE}
        by_counts = {p.counts: p.index for p in rig[name].produced}
        idx = np.array([by_counts[s.counts] for s in ok])
        assert np.all(np.diff(idx) >= 1)  # no duplicates
        gap = np.diff(idx) > 1
        flagged = np.array([s.overrun for s in ok[1:]])
        assert np.array_equal(gap, flagged), name
        lost[name] = int(np.sum(np.diff(idx) - 1))
        assert devices[name].health()["overruns"] >= int(gap.sum())
    # whether jitter costs samples depends on the device's phase against the loop's
    # deadlines; over four devices it did here (and the SPI pair, read early in the
    # tick, lost none)
    assert sum(lost.values()) > 0 and lost["acc1"] == 0


def test_stop_event_ends_a_real_time_run_promptly():
    calls = []
    loop = SamplingLoop({"x": lambda: calls.append(time.monotonic())}, RATE_HZ)
    stop = threading.Event()
    timer = threading.Timer(0.2, stop.set)
    t0 = time.monotonic()
    timer.start()
    report = loop.run(stop)
    elapsed = time.monotonic() - t0
    timer.join()
    assert 0.2 <= elapsed < 1.0
    assert 15 <= report.ticks + report.missed_ticks <= 60 and len(calls) == report.ticks


def test_a_stalled_read_skips_ticks_instead_of_bursting():
    clock = FakeClock()
    ticks = []

    def slow():
        ticks.append(clock.monotonic())
        if len(ticks) == 10:
            clock.advance(0.035)  # a 35 ms stall (a bus timeout)

    report = SamplingLoop({"slow": slow}, RATE_HZ, clock=clock.monotonic,
                          wait=clock.sleep).run(threading.Event(), max_ticks=20)
    assert report.missed_ticks == 2
    t = np.array(ticks) - ticks[0]
    # tick 9 ends at 125 ms: ticks 10 and 11 are gone, tick 12 (due at 120 ms) is read
    # at once, and the loop is back on its 10 ms grid from tick 13 on
    assert t[10] == pytest.approx(0.125)
    assert t[11:] == pytest.approx(0.13 + 0.01 * np.arange(len(t) - 11))


def test_an_oserror_escaping_a_reader_is_counted_and_the_loop_goes_on():
    clock = FakeClock()
    n = {"i": 0}

    def flaky():
        n["i"] += 1
        if n["i"] % 3 == 0:
            raise OSError(5, "Input/output error")
        return n["i"]

    sink = Collector()
    report = SamplingLoop({"f": flaky}, RATE_HZ, sink=sink, clock=clock.monotonic,
                          wait=clock.sleep).run(threading.Event(), max_ticks=9)
    assert report.readers["f"].errors == 3 and sink.results["f"] == [1, 2, 4, 5, 7, 8]


def test_a_missing_device_at_startup_is_named(clock):
    rig = FakeRig(clock)
    rig["acc3"].disappear()
    with pytest.raises(DeviceNotFoundError,
                       match=r"^acc3: no ADXL345 on I2C bus 1 at 0x53: \[Errno 121\]"):
        open_devices(smbus_factory=rig.smbus, spi_factory=rig.spi.SpiDev,
                     clock=clock.monotonic, sleep=clock.sleep)
    devices = open_devices(smbus_factory=rig.smbus, spi_factory=rig.spi.SpiDev,
                           require_all=False, clock=clock.monotonic, sleep=clock.sleep)
    assert not devices["acc3"].online and devices["acc4"].online
    clock.advance(0.01)
    assert devices["acc3"].read().status is Status.OFFLINE
    rig["acc3"].reappear()
    clock.advance(0.1)
    devices["acc3"].read()
    clock.advance(0.01)
    assert devices["acc3"].read().valid


def test_wiring_matches_the_wmra_config():
    import pathlib

    import yaml

    cfg = yaml.safe_load((pathlib.Path(__file__).parents[2] / "config" / "wmra.yaml").read_text())
    assert tuple(Wiring.from_bus(s["name"], s["type"], s["bus"]) for s in cfg["sensors"]) == \
        WMRA_WIRING


def test_wiring_table_matches_the_rig():
    assert [(w.name, w.bus, w.bus_number, w.address) for w in WMRA_WIRING] == [
        ("acc1", "spi", 0, 0), ("acc2", "spi", 0, 1),
        ("acc3", "i2c", 1, 0x53), ("acc4", "i2c", 1, 0x1D), ("imu", "i2c", 1, 0x68),
    ]


def test_a_bus_that_cannot_be_opened_says_what_to_enable(clock):
    rig = FakeRig(clock)
    wiring = (*WMRA_WIRING, Wiring("acc5", "adxl345", "spi", 0, 2), Wiring("acc6", "adxl345",
                                                                          "i2c", 3, 0x53))
    with pytest.raises(DeviceNotFoundError) as e:
        open_devices(wiring, smbus_factory=rig.smbus, spi_factory=rig.spi.SpiDev,
                     require_all=False, clock=clock.monotonic, sleep=clock.sleep)
    assert str(e.value).splitlines() == [
        "acc5: no ADXL345 on SPI bus 0 device 2: cannot open /dev/spidev0.2 (No such file or "
        "directory); is SPI enabled (dtparam=spi=on in /boot/config.txt)?",
        "acc6: cannot open I2C bus 3 (/dev/i2c-3: No such file or directory); is I2C enabled "
        "(dtparam=i2c_arm=on in /boot/config.txt)?",
    ]
    assert rig.i2c[1].closed  # what was opened is closed again


def test_close_all_closes_each_shared_bus_once(clock):
    rig = FakeRig(clock)
    devices = open_devices(smbus_factory=rig.smbus, spi_factory=rig.spi.SpiDev,
                           clock=clock.monotonic, sleep=clock.sleep)
    close_all(devices)
    assert rig.i2c[1].closed
    assert devices["acc3"].read().status is Status.BUS_ERROR  # closed fd: EBADF, no crash
