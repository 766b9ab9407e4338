"""FakeSpiDev: a spidev.SpiDev stand-in with the ADXL345's SPI framing.

A :class:`FakeSpiController` holds the chip selects (``(bus, device)`` ->
fake device), the controller-wide ``faults`` and the frame ``log``; its
:meth:`FakeSpiController.SpiDev` is the factory a driver uses in place of
``spidev.SpiDev``. Framing (ADXL345 4-wire SPI): first byte = register address
(bits 5:0) | 0x40 multi-byte | 0x80 read; then one byte per register. Without the
multi-byte bit the address does not advance.

Like a real part, the device answers garbage when the host gets the link wrong:
in a mode other than 3 (CPOL = CPHA = 1) or above 5 MHz the command is not
executed for writes and the read bytes arrive shifted by one bit. A device that
is absent (unplugged, ``disappear()``) leaves MISO at ``absent_fill`` (0x00).
"""

from __future__ import annotations

import errno as errno_mod
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from armfusion.sensors.fakes.faults import FaultInjector, os_error
from armfusion.sensors.fakes.registers import FakeRegisterDevice

MAX_SPEED_HZ = 5_000_000
REQUIRED_MODE = 3


@dataclass(frozen=True)
class SpiFrame:
    t_s: float
    bus: int
    device: int
    mosi: tuple[int, ...]
    miso: tuple[int, ...]
    mode: int
    speed_hz: int
    errno: int | None = None


class FakeSpiController:
    """Chip selects wired to fake devices; shared faults and frame log."""

    def __init__(
        self,
        ports: Mapping[tuple[int, int], FakeRegisterDevice],
        *,
        clock: object | None = None,
        absent_fill: int = 0x00,
        seed: int = 0,
        log_limit: int = 200_000,
    ):
        self.ports = dict(ports)
        self._advance: Callable[[float], None] | None = getattr(clock, "advance", None)
        self._now: Callable[[], float] = getattr(clock, "monotonic", None) or (lambda: 0.0)
        self.absent_fill = absent_fill
        self.faults = FaultInjector(seed)
        self.log: deque[SpiFrame] = deque(maxlen=log_limit)

    def now(self) -> float:
        """The clock's time (0 without a clock), s."""
        return self._now()

    def spend(self, seconds: float) -> None:
        """Advance the clock (when it can be advanced) by a transfer's ``seconds``."""
        if self._advance is not None:
            self._advance(seconds)

    def SpiDev(self) -> FakeSpiDev:  # noqa: N802 - mirrors spidev.SpiDev
        return FakeSpiDev(self)

    def frames(self, bus: int, device: int) -> list[SpiFrame]:
        return [f for f in self.log if (f.bus, f.device) == (bus, device)]


class FakeSpiDev:
    """Attributes and methods of ``spidev.SpiDev`` that matter on a 4-wire link."""

    def __init__(self, controller: FakeSpiController):
        self._c = controller
        self._port: tuple[int, int] | None = None
        self.mode = 0
        self.max_speed_hz = 125_000_000
        self.bits_per_word = 8
        self.lsbfirst = False
        self.cshigh = False
        self.threewire = False
        self.no_cs = False
        self.loop = False

    def open(self, bus: int, device: int) -> None:
        if (bus, device) not in self._c.ports:
            raise FileNotFoundError(errno_mod.ENOENT, "No such file or directory")
        self._port = (bus, device)

    def close(self) -> None:
        self._port = None

    def fileno(self) -> int:
        return -1 if self._port is None else 1000 + 10 * self._port[0] + self._port[1]

    def xfer2(self, values: list[int], speed_hz: int = 0, delay_usecs: int = 0,
              bits_per_word: int = 0) -> list[int]:
        c = self._c
        t = c.now()
        speed = speed_hz or self.max_speed_hz
        mosi = [v & 0xFF for v in values]
        bus, dev = self._port if self._port is not None else (-1, -1)
        try:
            if self._port is None:
                raise os_error(errno_mod.EBADF)
            c.faults.check()
            device = c.ports[self._port]
            if not device.present:
                miso = [c.absent_fill] * len(mosi)
            else:
                device.faults.check()
                miso = self._frame(device, mosi, garbage=self.mode != REQUIRED_MODE
                                   or speed > MAX_SPEED_HZ or self.bits_per_word != 8
                                   or self.lsbfirst or self.cshigh or self.threewire)
        except OSError as e:
            c.log.append(SpiFrame(t, bus, dev, tuple(mosi), (), self.mode, speed, e.errno))
            raise
        finally:
            c.spend(len(mosi) * 8 / speed + 5e-6 + delay_usecs * 1e-6)
        c.log.append(SpiFrame(t, bus, dev, tuple(mosi), tuple(miso), self.mode, speed))
        return miso

    @staticmethod
    def _frame(device: FakeRegisterDevice, mosi: list[int], *, garbage: bool) -> list[int]:
        if not mosi:
            return []
        cmd, payload = mosi[0], mosi[1:]
        register, read, multi = cmd & 0x3F, bool(cmd & 0x80), bool(cmd & 0x40)
        if not read:
            if payload and not garbage:
                device.write_registers(register, payload, increment=multi)
            return [0x00] * len(mosi)
        data = device.read_registers(register, len(payload), increment=multi) if payload else []
        rx = [0x00] + data
        if garbage:  # sampled on the wrong edge: every bit one place late
            rx = [((rx[i] << 1) | (rx[i + 1] >> 7 if i + 1 < len(rx) else 1)) & 0xFF
                  for i in range(len(rx))]
        return rx
