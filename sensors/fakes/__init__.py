"""Register-level fake devices and buses, so the real drivers run end to end in tests.

* :class:`FakeADXL345`, :class:`FakeMPU9150` (with its :class:`FakeAK8975`):
  emulators fed by a :class:`PhysicsSource`;
* :class:`FakeSMBus` (smbus2.SMBus methods) and :class:`FakeSpiController` /
  :class:`FakeSpiDev` (spidev.SpiDev attributes and ``xfer2``) to reach them;
* :class:`FaultInjector` on every bus and device; :class:`FakeClock` for time;
* :class:`FakeRig`: the WMRA's five sensors wired as in ``armfusion.sensors.sampling``.
"""

from armfusion.sensors.fakes.adxl345 import FakeADXL345, ProducedSample
from armfusion.sensors.fakes.clock import FakeClock
from armfusion.sensors.fakes.faults import FaultInjector
from armfusion.sensors.fakes.mpu9150 import FakeAK8975, FakeMPU9150, ProducedImuSample
from armfusion.sensors.fakes.physics import FunctionPhysics, PhysicsSource, StaticPhysics
from armfusion.sensors.fakes.registers import FakeRegisterDevice, RegisterAccess
from armfusion.sensors.fakes.rig import FakeRig
from armfusion.sensors.fakes.smbus import FakeSMBus, I2CTransaction
from armfusion.sensors.fakes.spidev import FakeSpiController, FakeSpiDev, SpiFrame

__all__ = [
    "FakeADXL345",
    "FakeAK8975",
    "FakeClock",
    "FakeMPU9150",
    "FakeRegisterDevice",
    "FakeRig",
    "FakeSMBus",
    "FakeSpiController",
    "FakeSpiDev",
    "FaultInjector",
    "FunctionPhysics",
    "I2CTransaction",
    "PhysicsSource",
    "ProducedImuSample",
    "ProducedSample",
    "RegisterAccess",
    "SpiFrame",
    "StaticPhysics",
]
