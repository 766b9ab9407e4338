"""FakeRig: the WMRA's sensors as fakes, wired as ``armfusion.sensors.sampling.WMRA_WIRING``.

The real drivers open the rig exactly as they open hardware, with the rig's
factories in place of ``smbus2.SMBus`` and ``spidev.SpiDev``::

    clock = FakeClock()
    rig = FakeRig(clock, physics={"acc1": ..., "imu": ...})
    devices = open_devices(smbus_factory=rig.smbus, spi_factory=rig.spi.SpiDev,
                           clock=clock.monotonic, sleep=clock.sleep)
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

from armfusion.sensors.fakes.adxl345 import FakeADXL345
from armfusion.sensors.fakes.mpu9150 import FakeMPU9150
from armfusion.sensors.fakes.physics import PhysicsSource, StaticPhysics
from armfusion.sensors.fakes.registers import FakeRegisterDevice
from armfusion.sensors.fakes.smbus import FakeSMBus
from armfusion.sensors.fakes.spidev import FakeSpiController
from armfusion.sensors.sampling import WMRA_WIRING, Wiring


class FakeRig:
    """Fake devices on fake buses. ``clock``: a FakeClock, or any object with
    ``monotonic`` (then transfers take no time). ``physics``: per device name;
    missing names get ``StaticPhysics()``."""

    def __init__(
        self,
        clock: object,
        physics: Mapping[str, PhysicsSource] | None = None,
        *,
        wiring: Sequence[Wiring] = WMRA_WIRING,
        seed: int = 0,
    ):
        now: Callable[[], float] = clock.monotonic  # type: ignore[attr-defined]
        physics = dict(physics or {})
        self.devices: dict[str, FakeRegisterDevice] = {}
        self.i2c: dict[int, FakeSMBus] = {}
        spi_ports: dict[tuple[int, int], FakeRegisterDevice] = {}
        for i, w in enumerate(wiring):
            src = physics.get(w.name, StaticPhysics())
            dev: FakeRegisterDevice
            if w.part == "adxl345":
                dev = FakeADXL345(src, now, i2c_address=w.address if w.bus == "i2c" else 0x53,
                                  seed=seed + 100 * i, name=w.name)
            else:
                dev = FakeMPU9150(src, now, address=w.address, seed=seed + 100 * i)
            self.devices[w.name] = dev
            if w.bus == "spi":
                spi_ports[(w.bus_number, w.address)] = dev
            else:
                bus = self.i2c.setdefault(
                    w.bus_number, FakeSMBus(w.bus_number, clock=clock, seed=seed + 17 * w.bus_number))
                bus.attach(dev)
                if isinstance(dev, FakeMPU9150):
                    bus.attach(dev.ak8975)
        self.spi = FakeSpiController(spi_ports, clock=clock, seed=seed + 7)

    def smbus(self, bus_number: int) -> FakeSMBus:
        """The ``smbus2.SMBus(bus_number)`` stand-in (the same object every call)."""
        if bus_number not in self.i2c:
            raise FileNotFoundError(2, "No such file or directory", f"/dev/i2c-{bus_number}")
        bus = self.i2c[bus_number]
        bus.open(bus_number)
        return bus

    def __getitem__(self, name: str) -> FakeRegisterDevice:
        return self.devices[name]
