"""The common core of the fake devices: a register file with a log and faults."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Literal

from armfusion.sensors.fakes.faults import FaultInjector


@dataclass(frozen=True)
class RegisterAccess:
    """One register-level access as the device saw it (a burst is one entry)."""

    t_s: float
    op: Literal["read", "write"]
    register: int
    values: tuple[int, ...]


class FakeRegisterDevice:
    """Base of the emulators: ``read_registers`` / ``write_registers`` with the
    device's own auto-increment, a bounded access log, protocol violations noted
    (``violations``: things a real part would not forgive, e.g. writing a
    read-only register or an AK8975 mode change without power-down), a
    :class:`FaultInjector` for transactions addressed to it, and presence
    (``disappear`` / ``reappear``).
    """

    name = "device"

    def __init__(self, clock: Callable[[], float], *, seed: int = 0, log_limit: int = 200_000):
        self.clock = clock
        self.present = True
        self.faults = FaultInjector(seed)
        self.log: deque[RegisterAccess] = deque(maxlen=log_limit)
        self.violations: list[str] = []

    # subclass hooks
    def _advance(self, now: float) -> None: ...

    def _read(self, register: int) -> int:
        raise NotImplementedError

    def _write(self, register: int, value: int, now: float) -> None:
        raise NotImplementedError

    def _after_read(self, registers: list[int], now: float) -> None: ...

    def reset(self) -> None:
        raise NotImplementedError

    # bus side
    def responds(self) -> bool:
        """Whether the device answers on its bus right now."""
        return self.present

    def read_registers(self, start: int, n: int, *, increment: bool = True) -> list[int]:
        now = self.clock()
        self._advance(now)
        regs = [(start + i) & 0xFF if increment else start for i in range(n)]
        values = [self._read(r) & 0xFF for r in regs]
        self._after_read(regs, now)
        self.log.append(RegisterAccess(now, "read", start, tuple(values)))
        return values

    def write_registers(self, start: int, values: Iterable[int], *, increment: bool = True) -> None:
        now = self.clock()
        self._advance(now)
        values = [v & 0xFF for v in values]
        for i, v in enumerate(values):
            self._write((start + i) & 0xFF if increment else start, v, now)
        self.log.append(RegisterAccess(now, "write", start, tuple(values)))

    # test side
    def writes(self) -> list[tuple[int, int]]:
        """Every register write in order, as ``(register, value)``."""
        return [(a.register + i, v) for a in self.log if a.op == "write"
                for i, v in enumerate(a.values)]

    def clear_log(self) -> None:
        self.log.clear()

    def disappear(self) -> None:
        """Unplugged / brown-out: stops answering on the bus."""
        self.present = False

    def reappear(self, *, power_cycled: bool = True) -> None:
        """Back on the bus; a power cycle brings every register back to reset."""
        self.present = True
        if power_cycled:
            self.reset()
