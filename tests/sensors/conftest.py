"""Fixtures for the driver tests: a fake clock, fake buses with fake devices on them."""

from __future__ import annotations

import pytest
from armfusion.sensors.adxl345 import ADXL345, ADXL345Config
from armfusion.sensors.bus import RecoveryPolicy, RetryPolicy
from armfusion.sensors.fakes import (
    FakeADXL345,
    FakeClock,
    FakeMPU9150,
    FakeSMBus,
    FakeSpiController,
    StaticPhysics,
)
from armfusion.sensors.mpu9150 import MPU9150, MPU9150Config

#: Retry/recovery used in the tests: the defaults, spelled out so tests can reason.
RETRY = RetryPolicy(attempts=3, backoff_s=0.0005, factor=2.0, max_backoff_s=0.01)
RECOVERY = RecoveryPolicy(offline_after=3, first_delay_s=0.05, factor=2.0, max_delay_s=2.0)


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock(start_s=1000.0)


class Rig:
    """One fake device on a fake bus, and the driver to it, all on one FakeClock."""

    def __init__(self, clock: FakeClock):
        self.clock = clock

    def adxl_i2c(self, physics=None, config=None, *, address=0x53, init=True,
                 **fake_kw):
        self.fake = FakeADXL345(physics or StaticPhysics(), self.clock.monotonic,
                                i2c_address=address, **fake_kw)
        self.bus = FakeSMBus(1, [self.fake], clock=self.clock)
        self.driver = ADXL345.i2c(1, address, smbus=self.bus, config=config or ADXL345Config(),
                                  **self.driver_kw())
        if init:
            self.driver.init()
        return self.driver

    def adxl_spi(self, physics=None, config=None, *, init=True, **fake_kw):
        self.fake = FakeADXL345(physics or StaticPhysics(), self.clock.monotonic, **fake_kw)
        self.spi = FakeSpiController({(0, 0): self.fake}, clock=self.clock)
        self.driver = ADXL345.spi(0, 0, spi_factory=self.spi.SpiDev,
                                  config=config or ADXL345Config(),
                                  **self.driver_kw())
        if init:
            self.driver.init()
        return self.driver

    def mpu(self, physics=None, config=None, *, init=True, **fake_kw):
        self.fake = FakeMPU9150(physics or StaticPhysics(), self.clock.monotonic, **fake_kw)
        self.ak = self.fake.ak8975
        self.bus = FakeSMBus(1, [self.fake, self.ak], clock=self.clock)
        self.driver = MPU9150.i2c(1, smbus=self.bus, config=config or MPU9150Config(),
                                  **self.driver_kw())
        if init:
            self.driver.init()
        return self.driver

    def driver_kw(self) -> dict:
        self.sleeps: list[float] = []

        def sleep(dt: float) -> None:
            self.sleeps.append(dt)
            self.clock.sleep(dt)

        return dict(clock=self.clock.monotonic, sleep=sleep, retry=RETRY, recovery=RECOVERY)


@pytest.fixture
def rig(clock: FakeClock) -> Rig:
    return Rig(clock)
