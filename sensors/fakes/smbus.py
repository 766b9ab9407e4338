"""FakeSMBus: an smbus2.SMBus stand-in routing by I2C address to fake devices."""

from __future__ import annotations

import errno as errno_mod
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Literal, Protocol

from armfusion.sensors.fakes.faults import FaultInjector, os_error

I2C_SMBUS_BLOCK_MAX = 32


class FakeI2CDevice(Protocol):
    address: int
    faults: FaultInjector

    def responds(self) -> bool: ...

    def read_registers(self, start: int, n: int, *, increment: bool = True) -> list[int]: ...

    def write_registers(self, start: int, values: Iterable[int], *,
                        increment: bool = True) -> None: ...


@dataclass(frozen=True)
class I2CTransaction:
    """One smbus call as the bus saw it; ``errno`` set when it failed."""

    t_s: float
    bus: int
    address: int
    op: Literal["read", "write"]
    register: int
    data: tuple[int, ...]
    errno: int | None = None


class FakeSMBus:
    """Same methods and signatures as the ``smbus2.SMBus`` calls the drivers make.

    ``devices`` answer at their ``address`` while ``responds()``; an address with
    no device NACKs with ``nack_errno`` (EREMOTEIO, what the Raspberry Pi's
    i2c-bcm2835 reports). ``faults`` fails transactions on the whole bus (a NACK
    burst, random failures, a stuck bus); each device also has its own. With a
    ``clock`` that has ``advance`` (FakeClock), every transaction takes its wire
    time at ``bitrate_hz`` (9 bits per byte; 100 kHz, the Pi's default). ``log`` holds every transaction.
    """

    def __init__(
        self,
        bus: int | None = 1,
        devices: Iterable[FakeI2CDevice] = (),
        *,
        clock: object | None = None,
        bitrate_hz: float = 100_000.0,
        nack_errno: int = errno_mod.EREMOTEIO,
        seed: int = 0,
        log_limit: int = 200_000,
    ):
        self.bus_number = bus
        self.devices: list[FakeI2CDevice] = list(devices)
        self._advance: Callable[[float], None] | None = getattr(clock, "advance", None)
        self._now: Callable[[], float] = getattr(clock, "monotonic", None) or (lambda: 0.0)
        self.bitrate_hz = bitrate_hz
        self.nack_errno = nack_errno
        self.faults = FaultInjector(seed)
        self.log: deque[I2CTransaction] = deque(maxlen=log_limit)
        self.closed = bus is None

    # smbus2 surface ----------------------------------------------------------------

    def open(self, bus: int) -> None:
        self.bus_number = bus
        self.closed = False

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> FakeSMBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        return self._xfer(i2c_addr, "read", register, 4,
                          lambda d: d.read_registers(register, 1))[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int,
                        force: bool | None = None) -> None:
        self._xfer(i2c_addr, "write", register, 3,
                   lambda d: d.write_registers(register, [value]) or [value & 0xFF])

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int,
                            force: bool | None = None) -> list[int]:
        if length > I2C_SMBUS_BLOCK_MAX:
            raise ValueError(f"Desired block length over {I2C_SMBUS_BLOCK_MAX} bytes")
        return self._xfer(i2c_addr, "read", register, 3 + length,
                          lambda d: d.read_registers(register, length))

    def write_i2c_block_data(self, i2c_addr: int, register: int, data: list[int],
                             force: bool | None = None) -> None:
        if len(data) > I2C_SMBUS_BLOCK_MAX:
            raise ValueError(f"Data length cannot exceed {I2C_SMBUS_BLOCK_MAX} bytes")
        self._xfer(i2c_addr, "write", register, 2 + len(data),
                   lambda d: d.write_registers(register, data) or [v & 0xFF for v in data])

    # helpers -----------------------------------------------------------------------

    def attach(self, *devices: FakeI2CDevice) -> None:
        self.devices.extend(devices)

    def _xfer(self, addr: int, op: Literal["read", "write"], register: int, n_bytes: int,
              fn: Callable[[FakeI2CDevice], list[int]]) -> list[int]:
        t = self._now()
        try:
            if self.closed:
                raise os_error(errno_mod.EBADF)
            self.faults.check()
            here = [d for d in self.devices if d.address == addr and d.responds()]
            if not here:
                raise os_error(self.nack_errno)
            if len(here) > 1:
                raise os_error(errno_mod.EIO)  # two parts driving one address
            here[0].faults.check()
            data = fn(here[0])
        except OSError as e:
            self.log.append(I2CTransaction(t, self.bus_number or -1, addr, op, register, (),
                                           e.errno))
            raise
        finally:
            if self._advance is not None:
                self._advance((9 * n_bytes + 2) / self.bitrate_hz)
        self.log.append(I2CTransaction(t, self.bus_number or -1, addr, op, register,
                                       tuple(data)))
        return data

    def writes(self, address: int) -> list[tuple[int, int]]:
        """Successful register writes to ``address`` in order, as ``(register, value)``."""
        return [(x.register + i, v) for x in self.log
                if x.address == address and x.op == "write" and x.errno is None
                for i, v in enumerate(x.data)]
