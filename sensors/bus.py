"""Register transports (I2C through smbus2, SPI through spidev), retries and recovery.

The drivers in this package talk to register-mapped devices through a
:class:`RegisterTransport`: ``read(register, n)`` for a burst and ``write(register,
value)`` for one register. Two transports cover the rig:

* :class:`I2CRegisters` over an ``smbus2.SMBus``-like object (``read_byte_data``,
  ``read_i2c_block_data``, ``write_byte_data``): register auto-increment is the
  device's, one ``read_i2c_block_data`` call is one I2C transaction.
* :class:`SpiRegisters` over a ``spidev.SpiDev``-like object (``xfer2``), with the
  read and multi-byte bits of the first byte given per device (ADXL345: 0x80, 0x40).

A :class:`Supervisor` wraps every transaction of one device: a bounded number of
attempts with exponential backoff between them (the sleep is injected, so tests do
not wait), per-device error counters, and the online/offline state that makes a
driver re-initialise a device after it comes back.

Nothing here raises out of a driver's ``read``: transactions that fail after all
attempts raise :class:`BusError` to the driver, which turns it into a sample
marked invalid.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from types import MappingProxyType
from typing import Protocol, TypeVar

T = TypeVar("T")

#: Largest burst smbus2 moves in one ``read_i2c_block_data`` (SMBus block limit).
I2C_BLOCK_MAX = 32


class Status(StrEnum):
    """Why a sample is (or is not) usable. Only ``OK`` carries data."""

    OK = "ok"
    #: The device answered but had no new data since the last read.
    STALE = "stale"
    #: A transaction failed after every retry (NACK, timeout, I/O error).
    BUS_ERROR = "bus_error"
    #: The device answered with something that is not its own state (check byte
    #: wrong, registers back at reset values): garbage on the wire or a reset device.
    BAD_DATA = "bad_data"
    #: The device is known to be unreachable; re-initialisation is retried later.
    OFFLINE = "offline"
    #: Data-ready did not come within its timeout.
    NOT_READY = "not_ready"
    #: The sensor reported an overflow (AK8975 HOFL).
    OVERFLOW = "overflow"
    #: The sensor reported an internal read error (AK8975 DERR).
    SENSOR_ERROR = "sensor_error"
    #: The part is not enabled in this configuration (e.g. magnetometer off).
    DISABLED = "disabled"


class DeviceNotFoundError(RuntimeError):
    """A device did not identify itself at initialisation. The message is one line."""


class DeviceConfigError(RuntimeError):
    """A device did not take its configuration (a register read back wrong)."""


class BusError(OSError):
    """A transaction failed after every attempt; ``__cause__`` is the last OSError."""


# --- what the drivers need from smbus2 and spidev -------------------------------------


class SMBusLike(Protocol):
    """The part of ``smbus2.SMBus`` the drivers use (same names and signatures)."""

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int: ...

    def write_byte_data(
        self, i2c_addr: int, register: int, value: int, force: bool | None = None
    ) -> None: ...

    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]: ...

    def close(self) -> None: ...


class SpiDevLike(Protocol):
    """The part of ``spidev.SpiDev`` the drivers use (same names)."""

    mode: int
    max_speed_hz: int

    def open(self, bus: int, device: int) -> None: ...

    def close(self) -> None: ...

    def xfer2(self, values: list[int], *args: int) -> list[int]: ...


class RegisterTransport(Protocol):
    """Register access to one device. ``where`` names it in messages."""

    where: str

    def read(self, register: int, n: int) -> bytes: ...

    def write(self, register: int, value: int) -> None: ...

    def close(self) -> None: ...


class I2CRegisters:
    """One I2C device's registers over an smbus2-like bus.

    ``read(reg, 1)`` is ``read_byte_data``; ``read(reg, n)`` is one
    ``read_i2c_block_data`` (a repeated-start transaction, so the device's own
    auto-increment gives a coherent burst). ``bus_number`` is only for messages.
    """

    def __init__(self, bus: SMBusLike, address: int, bus_number: int, *, owns_bus: bool = False):
        if not 0x03 <= address <= 0x77:
            raise ValueError(f"I2C address 0x{address:02X} is outside the 7-bit range 0x03-0x77")
        self.bus = bus
        self.address = address
        self.bus_number = bus_number
        self.where = f"I2C bus {bus_number} at 0x{address:02X}"
        self._owns_bus = owns_bus

    def read(self, register: int, n: int) -> bytes:
        if n == 1:
            return bytes([self.bus.read_byte_data(self.address, register) & 0xFF])
        if not 1 <= n <= I2C_BLOCK_MAX:
            raise ValueError(f"an I2C burst is 1..{I2C_BLOCK_MAX} bytes, not {n}")
        data = self.bus.read_i2c_block_data(self.address, register, n)
        if len(data) != n:
            raise BusError(5, f"{self.where}: short read, {len(data)} of {n} bytes")
        return bytes(b & 0xFF for b in data)

    def write(self, register: int, value: int) -> None:
        self.bus.write_byte_data(self.address, register, value & 0xFF)

    def sibling(self, address: int) -> I2CRegisters:
        """Another device on the same bus (the AK8975 behind the MPU-9150)."""
        return I2CRegisters(self.bus, address, self.bus_number)

    def close(self) -> None:
        if self._owns_bus:
            self.bus.close()


class SpiRegisters:
    """One SPI device's registers over a spidev-like handle (4-wire, one chip select).

    Frame: first byte ``register | read_bit (reads) | multi_bit (bursts)``, then one
    byte per register; ``xfer2`` keeps chip select low for the whole frame.
    """

    def __init__(
        self,
        spi: SpiDevLike,
        bus_number: int,
        device: int,
        *,
        read_bit: int = 0x80,
        multi_bit: int = 0x40,
        address_mask: int = 0x3F,
    ):
        self.spi = spi
        self.bus_number = bus_number
        self.device = device
        self.read_bit = read_bit
        self.multi_bit = multi_bit
        self.address_mask = address_mask
        self.where = f"SPI bus {bus_number} device {device} (/dev/spidev{bus_number}.{device})"

    @classmethod
    def open(
        cls,
        spi_factory: Callable[[], SpiDevLike],
        bus_number: int,
        device: int,
        *,
        mode: int,
        max_speed_hz: int,
        **framing: int,
    ) -> SpiRegisters:
        spi = spi_factory()
        spi.open(bus_number, device)
        spi.mode = mode
        spi.max_speed_hz = max_speed_hz
        return cls(spi, bus_number, device, **framing)

    def read(self, register: int, n: int) -> bytes:
        cmd = (register & self.address_mask) | self.read_bit | (self.multi_bit if n > 1 else 0)
        rx = self.spi.xfer2([cmd] + [0x00] * n)
        if len(rx) != n + 1:
            raise BusError(5, f"{self.where}: short transfer, {len(rx)} of {n + 1} bytes")
        return bytes(b & 0xFF for b in rx[1:])

    def write(self, register: int, value: int) -> None:
        self.spi.xfer2([register & self.address_mask, value & 0xFF])

    def close(self) -> None:
        self.spi.close()


def open_smbus(bus_number: int, factory: Callable[[int], SMBusLike] | None = None) -> SMBusLike:
    """``smbus2.SMBus(bus_number)`` (or ``factory``), with one clear line if it fails."""
    if factory is None:
        import smbus2

        factory = smbus2.SMBus
    try:
        return factory(bus_number)
    except OSError as e:
        raise DeviceNotFoundError(
            f"cannot open I2C bus {bus_number} (/dev/i2c-{bus_number}: {e.strerror or e}); "
            "is I2C enabled (dtparam=i2c_arm=on in /boot/config.txt)?"
        ) from e


# --- numbers ---------------------------------------------------------------------------


def s16_le(lo: int, hi: int) -> int:
    """Two's-complement 16-bit from a little-endian byte pair."""
    v = lo | (hi << 8)
    return v - 0x10000 if v & 0x8000 else v


def s16_be(hi: int, lo: int) -> int:
    """Two's-complement 16-bit from a big-endian byte pair."""
    return s16_le(lo, hi)


# --- retries, counters and recovery ---------------------------------------------------


@dataclass(frozen=True)
class RetryPolicy:
    """Bounded attempts per transaction with exponential backoff between them.

    With the defaults a failing transaction costs three attempts and 1.5 ms of
    sleep before the driver gives up on this sample (plus whatever the kernel's
    own I2C timeout takes per attempt).
    """

    attempts: int = 3
    backoff_s: float = 0.0005
    factor: float = 2.0
    max_backoff_s: float = 0.01

    def __post_init__(self) -> None:
        if self.attempts < 1:
            raise ValueError(f"RetryPolicy.attempts must be >= 1, got {self.attempts}")
        if self.backoff_s < 0 or self.factor < 1 or self.max_backoff_s < 0:
            raise ValueError("RetryPolicy: backoff_s and max_backoff_s >= 0, factor >= 1")

    def delay_s(self, failed_attempt: int) -> float:
        """Sleep after the ``failed_attempt``-th failure (0-based)."""
        return min(self.backoff_s * self.factor**failed_attempt, self.max_backoff_s)


@dataclass(frozen=True)
class RecoveryPolicy:
    """When a device goes offline, and how often to try re-initialising it.

    ``offline_after`` consecutive failed reads mark the device offline; the first
    re-initialisation is tried ``first_delay_s`` later, then the delay doubles up to
    ``max_delay_s``. While offline, ``read`` costs no bus traffic.
    """

    offline_after: int = 3
    first_delay_s: float = 0.05
    factor: float = 2.0
    max_delay_s: float = 2.0

    def __post_init__(self) -> None:
        if self.offline_after < 1:
            raise ValueError(f"RecoveryPolicy.offline_after must be >= 1, got {self.offline_after}")


DEFAULT_RETRY = RetryPolicy()
DEFAULT_RECOVERY = RecoveryPolicy()


@dataclass(frozen=True)
class DeviceHealth:
    """A snapshot of one device's state and error counters."""

    name: str
    where: str
    online: bool
    counters: Mapping[str, int]
    last_error: str

    def __getitem__(self, key: str) -> int:
        return self.counters.get(key, 0)

    def summary(self) -> str:
        state = "online" if self.online else "OFFLINE"
        counts = ", ".join(f"{k} {v}" for k, v in sorted(self.counters.items()) if v)
        tail = f"; last error: {self.last_error}" if self.last_error else ""
        return f"{self.name} ({self.where}): {state}; {counts or 'no events'}{tail}"


class Supervisor:
    """Retries, error counters and the online/offline state of one device.

    Counter names used by the drivers (all start at 0):
    ``reads`` (read calls), ``ok``, ``stale``, ``invalid`` (samples marked not OK,
    stale excluded), ``bus_errors`` (failed transaction attempts), ``retries``,
    ``offline`` (times the device was marked offline), ``reinits`` (successful
    re-initialisations after that), ``reinit_failures``, and device-specific ones
    (``overruns``, ``not_ready``, ``bad_data``, ``mag_*``…).
    """

    def __init__(
        self,
        name: str,
        where: str,
        *,
        retry: RetryPolicy = DEFAULT_RETRY,
        recovery: RecoveryPolicy = DEFAULT_RECOVERY,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.name = name
        self.where = where
        self.retry = retry
        self.recovery = recovery
        self.clock = clock
        self.sleep = sleep
        self.counters: Counter[str] = Counter()
        self.online = False
        self.last_error = ""
        self._consecutive_failures = 0
        self._delay_s = recovery.first_delay_s
        self._next_attempt_s = float("-inf")

    def call(self, fn: Callable[..., T], *args: object) -> T:
        """Run one transaction, retrying OSError with backoff; BusError when all fail."""
        last: OSError | None = None
        for attempt in range(self.retry.attempts):
            try:
                return fn(*args)
            except OSError as e:
                last = e
                self.counters["bus_errors"] += 1
                self.last_error = f"{self.where}: {e}"
                if attempt + 1 < self.retry.attempts:
                    self.counters["retries"] += 1
                    self.sleep(self.retry.delay_s(attempt))
        assert last is not None
        raise BusError(last.errno or 5, f"{self.where}: {last}") from last

    def count(self, key: str, n: int = 1) -> None:
        self.counters[key] += n

    def note(self, message: str) -> None:
        self.last_error = message

    def good_read(self) -> None:
        self._consecutive_failures = 0

    def failed_read(self, reason: str, *, immediately: bool = False) -> None:
        """A read gave no usable sample; after ``offline_after`` in a row, go offline."""
        self.last_error = reason
        self._consecutive_failures += 1
        if immediately or self._consecutive_failures >= self.recovery.offline_after:
            self.go_offline(reason)

    def go_offline(self, reason: str, *, retry_now: bool = False) -> None:
        if self.online:
            self.counters["offline"] += 1
        self.online = False
        self.last_error = reason
        self._consecutive_failures = 0
        if retry_now:
            self._next_attempt_s = self.clock()
        else:
            self._schedule_next()

    def _schedule_next(self) -> None:
        self._next_attempt_s = self.clock() + self._delay_s
        self._delay_s = min(self._delay_s * self.recovery.factor, self.recovery.max_delay_s)

    def reinit_due(self) -> bool:
        return not self.online and self.clock() >= self._next_attempt_s

    def init_succeeded(self, *, first: bool) -> None:
        if not first:
            self.counters["reinits"] += 1
        self.online = True
        self._consecutive_failures = 0
        self._delay_s = self.recovery.first_delay_s

    def init_failed(self, reason: str, *, first: bool) -> None:
        if not first:
            self.counters["reinit_failures"] += 1
        self.online = False
        self.last_error = reason
        self._schedule_next()

    def health(self) -> DeviceHealth:
        return DeviceHealth(
            self.name,
            self.where,
            self.online,
            MappingProxyType(dict(self.counters)),
            self.last_error,
        )


def hexbytes(values: Sequence[int]) -> str:
    return " ".join(f"0x{v:02X}" for v in values)
