"""What the register-level drivers (:mod:`armfusion.sensors.adxl345`, :mod:`armfusion.sensors.mpu9150`) share:
a device behind a :class:`~armfusion.sensors.bus.Supervisor` (retries, counters, online or
offline) that is brought back by re-initialising it when the supervisor says it is due,
and the two checks of an ``init``: the part answers with its identity register, and the
configuration reads back as written. Each failure is one line naming the part and where
it is.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import Self

from armfusion.sensors.bus import (
    DEFAULT_RECOVERY,
    DEFAULT_RETRY,
    BusError,
    DeviceConfigError,
    DeviceHealth,
    DeviceNotFoundError,
    I2CRegisters,
    RecoveryPolicy,
    RegisterTransport,
    RetryPolicy,
    SMBusLike,
    Supervisor,
    open_smbus,
)


class SupervisedDevice:
    """A driver of one device on ``transport``: its :class:`~armfusion.sensors.bus.Supervisor`, its
    health, ``with`` support, and re-initialisation when it went offline (a subclass
    writes :meth:`init`).

    ``clock`` stamps samples and drives timeouts (default ``time.monotonic``); ``sleep``
    is used for retry backoff and the devices' waits (default ``time.sleep``).
    """

    def __init__(
        self,
        transport: RegisterTransport,
        name: str,
        *,
        retry: RetryPolicy = DEFAULT_RETRY,
        recovery: RecoveryPolicy = DEFAULT_RECOVERY,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.transport = transport
        self.name = name
        self._clock = clock
        self._sleep = sleep
        self._sup = Supervisor(
            name, transport.where, retry=retry, recovery=recovery, clock=clock, sleep=sleep
        )
        self._initialised_once = False

    @staticmethod
    def _i2c_transport(bus_number: int, address: int, smbus: SMBusLike | None) -> I2CRegisters:
        """The device's registers at ``address`` on ``smbus`` (an open smbus2.SMBus-like bus
        shared by every device on it), else on ``smbus2.SMBus(bus_number)``, opened here and
        closed with the driver."""
        owns = smbus is None
        if smbus is None:
            smbus = open_smbus(bus_number)
        return I2CRegisters(smbus, address, bus_number, owns_bus=owns)

    def init(self) -> None:
        raise NotImplementedError

    @property
    def online(self) -> bool:
        return self._sup.online

    def health(self) -> DeviceHealth:
        return self._sup.health()

    def close(self) -> None:
        self.transport.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _reinit_if_due(self) -> bool:
        """True when the device is online (possibly just re-initialised)."""
        if self._sup.online:
            return True
        if not self._sup.reinit_due():
            return False
        try:
            self.init()
        except (DeviceNotFoundError, DeviceConfigError):
            return False
        return True

    def _read_begins(self) -> bool:
        """Count a read; False (and the read counted invalid) when the device is offline
        and not brought back now."""
        self._sup.count("reads")
        if self._reinit_if_due():
            return True
        self._sup.count("invalid")
        return False


def check_identity(sup: Supervisor, transport: RegisterTransport, part: str, register: int,
                   register_name: str, expected: int, hint: str = "") -> None:
    """Raise :class:`~armfusion.sensors.bus.DeviceNotFoundError` unless the identity register reads
    ``expected`` (``hint``: what to check, after the message)."""
    try:
        got = sup.call(transport.read, register, 1)[0]
    except BusError as e:
        raise DeviceNotFoundError(f"no {part} on {transport.where}: {e.__cause__}") from e
    if got != expected:
        raise DeviceNotFoundError(
            f"no {part} on {transport.where}: {register_name} read 0x{got:02X}, "
            f"expected 0x{expected:02X}{hint}"
        )


def check_read_back(part: str, where: str, registers: Iterable[tuple[int, str, int, int]]) -> None:
    """Raise :class:`~armfusion.sensors.bus.DeviceConfigError` at the first register of
    ``(register, name, written, read back)`` that did not take its value."""
    for reg, name, want, got in registers:
        if want != got:
            raise DeviceConfigError(
                f"{part} on {where}: {name} (0x{reg:02X}) read back 0x{got:02X} "
                f"after writing 0x{want:02X}"
            )
