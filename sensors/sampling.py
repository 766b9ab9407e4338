"""A rate-controlled sampling loop over the drivers, with read-time and jitter statistics.

:class:`SamplingLoop` calls each reader once per tick, in a fixed order, on
absolute deadlines ``t0 + k / rate_hz`` (so read time does not accumulate into
drift), and hands every result to a sink. If it falls more than a whole period
behind (a stalled bus, a descheduled process) it skips the missed ticks and counts
them, rather than reading in a burst that would only return stale data. It stops
when the ``stop`` event is set, after ``duration_s`` or after ``max_ticks``;
waiting is done with ``stop.wait`` by default, so setting the event ends a run
within one wait.

Timestamps: each driver stamps its samples with its own clock at read time
(``time.monotonic`` unless injected). The loop measures, per reader, the read
time (call duration) and the jitter of its read start times against the nominal
period.

:data:`WMRA_WIRING` and :func:`open_devices` assemble the rig's drivers
(see docs/drivers.md for the wiring table).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from armfusion.sensors.adxl345 import ADXL345, ADXL345Config
from armfusion.sensors.bus import (
    DeviceConfigError,
    DeviceNotFoundError,
    SMBusLike,
    SpiDevLike,
    open_smbus,
)
from armfusion.sensors.mpu9150 import MPU9150, MPU9150Config


class RunningStats:
    """Count, mean, standard deviation, min and max without keeping the values."""

    __slots__ = ("n", "mean", "_m2", "min", "max")

    def __init__(self) -> None:
        self.n = 0
        self.mean = 0.0
        self._m2 = 0.0
        self.min = math.inf
        self.max = -math.inf

    def add(self, x: float) -> None:
        self.n += 1
        d = x - self.mean
        self.mean += d / self.n
        self._m2 += d * (x - self.mean)
        self.min = min(self.min, x)
        self.max = max(self.max, x)

    @property
    def std(self) -> float:
        return math.sqrt(self._m2 / (self.n - 1)) if self.n > 1 else 0.0


@dataclass(frozen=True)
class ReadTiming:
    """One reader's timing over a run (seconds).

    ``jitter_*``: deviation of the interval between consecutive read starts from
    the nominal period (times the number of ticks between them).
    """

    reads: int
    errors: int
    read_time_mean_s: float
    read_time_std_s: float
    read_time_max_s: float
    jitter_std_s: float
    jitter_max_abs_s: float

    def summary(self) -> str:
        return (f"{self.reads} reads, read time {1e3 * self.read_time_mean_s:.3f} ms mean / "
                f"{1e3 * self.read_time_max_s:.3f} ms max, jitter {1e3 * self.jitter_std_s:.3f} "
                f"ms std / {1e3 * self.jitter_max_abs_s:.3f} ms max"
                + (f", {self.errors} errors" if self.errors else ""))


@dataclass(frozen=True)
class LoopReport:
    rate_hz: float
    ticks: int
    missed_ticks: int
    duration_s: float
    lateness_mean_s: float
    lateness_max_s: float
    readers: Mapping[str, ReadTiming]

    def summary(self) -> str:
        lines = [
            f"{self.ticks} ticks at {self.rate_hz:g} Hz over {self.duration_s:.3f} s, "
            f"{self.missed_ticks} missed; tick lateness {1e3 * self.lateness_mean_s:.3f} ms mean"
            f" / {1e3 * self.lateness_max_s:.3f} ms max"
        ]
        lines += [f"  {name}: {t.summary()}" for name, t in self.readers.items()]
        return "\n".join(lines)


class _ReaderStats:
    def __init__(self) -> None:
        self.read_time = RunningStats()
        self.jitter = RunningStats()
        self.jitter_max_abs = 0.0
        self.errors = 0
        self._last: tuple[int, float] | None = None

    def add(self, tick: int, t_start: float, dt: float, period: float) -> None:
        self.read_time.add(dt)
        if self._last is not None:
            k0, t0 = self._last
            dev = (t_start - t0) - (tick - k0) * period
            self.jitter.add(dev)
            self.jitter_max_abs = max(self.jitter_max_abs, abs(dev))
        self._last = (tick, t_start)

    def timing(self) -> ReadTiming:
        r = self.read_time
        return ReadTiming(r.n, self.errors, r.mean if r.n else 0.0, r.std,
                          r.max if r.n else 0.0, self.jitter.std, self.jitter_max_abs)


Sink = Callable[[str, Any], None]


class Collector:
    """A sink that keeps every result per reader name (lists flattened)."""

    def __init__(self) -> None:
        self.results: dict[str, list[Any]] = {}

    def __call__(self, name: str, result: Any) -> None:
        bucket = self.results.setdefault(name, [])
        if isinstance(result, list):
            bucket.extend(result)
        else:
            bucket.append(result)


class SamplingLoop:
    """Read every reader once per tick at ``rate_hz``.

    ``readers``: name -> zero-argument callable (``adxl.read``, ``adxl.read_fifo``,
    ``imu.read``, ``encoders.poll``…), called in this order. ``sink(name, result)``
    receives each result. ``clock`` and ``wait`` are injectable (a FakeClock's
    ``monotonic`` and ``sleep`` in tests); by default ``time.monotonic`` and the
    stop event's ``wait``. An OSError escaping a reader is counted and the loop
    goes on; any other exception is a bug and propagates.
    """

    def __init__(
        self,
        readers: Mapping[str, Callable[[], Any]],
        rate_hz: float,
        *,
        sink: Sink | None = None,
        clock: Callable[[], float] = time.monotonic,
        wait: Callable[[float], Any] | None = None,
    ):
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
        if not readers:
            raise ValueError("SamplingLoop needs at least one reader")
        self.readers = dict(readers)
        self.rate_hz = float(rate_hz)
        self.sink = sink
        self.clock = clock
        self.wait = wait

    def run(
        self,
        stop: threading.Event,
        *,
        duration_s: float | None = None,
        max_ticks: int | None = None,
    ) -> LoopReport:
        period = 1.0 / self.rate_hz
        wait = self.wait or stop.wait
        stats = {name: _ReaderStats() for name in self.readers}
        lateness = RunningStats()
        t0 = self.clock()
        k = 0
        ticks = missed = 0
        while not stop.is_set():
            if max_ticks is not None and ticks >= max_ticks:
                break
            deadline = t0 + k * period
            if duration_s is not None and deadline - t0 >= duration_s - 1e-9:
                break
            now = self.clock()
            if now < deadline:
                wait(deadline - now)
                if stop.is_set():
                    break
                now = self.clock()
            late = now - deadline
            if late >= period:  # fell behind by whole ticks: skip them, count them
                skip = int(late // period)
                missed += skip
                k += skip
                deadline = t0 + k * period
                late = now - deadline
            lateness.add(late)
            for name, read in self.readers.items():
                t_a = self.clock()
                try:
                    result = read()
                except OSError:
                    stats[name].errors += 1
                    result = None
                t_b = self.clock()
                stats[name].add(k, t_a, t_b - t_a, period)
                if self.sink is not None and result is not None:
                    self.sink(name, result)
            ticks += 1
            k += 1
        return LoopReport(
            self.rate_hz, ticks, missed, self.clock() - t0,
            lateness.mean if lateness.n else 0.0, lateness.max if lateness.n else 0.0,
            {name: s.timing() for name, s in stats.items()},
        )


# --- the rig ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Wiring:
    """Where one device is attached: I2C bus and address, or SPI bus and chip select."""

    name: str
    part: Literal["adxl345", "mpu9150"]
    bus: Literal["i2c", "spi"]
    bus_number: int
    address: int  # I2C 7-bit address, or SPI chip select (spidev device number)

    @classmethod
    def from_bus(cls, name: str, part: str, bus: Mapping[str, Any]) -> Wiring:
        """From an arm config's sensor ``bus`` section: ``{kind: spi, bus: 0,
        chip_select: 0}`` or ``{kind: i2c, bus: 1, address: 0x53}``."""
        kind = bus.get("kind")
        if kind == "spi":
            return cls(name, part, "spi", int(bus["bus"]), int(bus["chip_select"]))  # type: ignore[arg-type]
        if kind == "i2c":
            return cls(name, part, "i2c", int(bus["bus"]), int(bus["address"]))  # type: ignore[arg-type]
        raise ValueError(f"sensor {name!r}: bus kind {kind!r} is neither 'spi' nor 'i2c'")

    @property
    def where(self) -> str:
        if self.bus == "i2c":
            return f"I2C bus {self.bus_number} at 0x{self.address:02X}"
        return f"SPI bus {self.bus_number} CE{self.address}"


#: The WMRA rig, as in config/wmra.yaml (docs/drivers.md): two ADXL345 on SPI0
#: (CE0, CE1; the ones nearest the base, as in the thesis), two on I2C1 (SDO low
#: 0x53, SDO high 0x1D), the MPU-9150 on I2C1 at 0x68 (AD0 low), its AK8975 at 0x0C
#: through the bypass. Build other rigs with ``Wiring.from_bus`` from a config.
WMRA_WIRING: tuple[Wiring, ...] = (
    Wiring("acc1", "adxl345", "spi", 0, 0),
    Wiring("acc2", "adxl345", "spi", 0, 1),
    Wiring("acc3", "adxl345", "i2c", 1, 0x53),
    Wiring("acc4", "adxl345", "i2c", 1, 0x1D),
    Wiring("imu", "mpu9150", "i2c", 1, 0x68),
)


def open_devices(
    wiring: Sequence[Wiring] = WMRA_WIRING,
    *,
    smbus_factory: Callable[[int], SMBusLike] | None = None,
    spi_factory: Callable[[], SpiDevLike] | None = None,
    adxl_config: ADXL345Config | None = None,
    mpu_config: MPU9150Config | None = None,
    require_all: bool = True,
    **driver_kwargs: Any,
) -> dict[str, ADXL345 | MPU9150]:
    """Open and initialise every device of ``wiring``; one SMBus per I2C bus number.

    A bus that cannot be opened (no /dev/i2c-N or /dev/spidevB.D) always raises.

    ``smbus_factory(bus_number)`` defaults to ``smbus2.SMBus``, ``spi_factory`` to
    ``spidev.SpiDev``. ``driver_kwargs`` (``clock``, ``sleep``, ``retry``,
    ``recovery``) go to every driver. With ``require_all`` a device that does not
    answer raises DeviceNotFoundError listing every missing device, one line each;
    without it, such a device is returned offline and re-initialisation is retried
    by its ``read`` on the recovery schedule. Close with :func:`close_all`.
    """
    adxl_config = adxl_config or ADXL345Config()
    mpu_config = mpu_config or MPU9150Config()
    for w in wiring:
        if (w.part, w.bus) not in (("adxl345", "spi"), ("adxl345", "i2c"), ("mpu9150", "i2c")):
            raise ValueError(f"{w.name}: no driver for a {w.part} on {w.bus}")
    buses: dict[int, SMBusLike] = {}
    devices: dict[str, ADXL345 | MPU9150] = {}
    problems: list[str] = []
    cannot_open = False
    # the IMU first: its reset takes 150 ms, which would otherwise fill the FIFOs of the
    # accelerometers initialised before it (the first tick would then run long)
    for w in sorted(wiring, key=lambda w: w.part != "mpu9150"):
        dev: ADXL345 | MPU9150
        try:
            if w.bus == "i2c" and w.bus_number not in buses:
                buses[w.bus_number] = open_smbus(w.bus_number, smbus_factory)
            if w.bus == "spi":
                dev = ADXL345.spi(w.bus_number, w.address, spi_factory=spi_factory,
                                  config=adxl_config, name=w.name, **driver_kwargs)
            elif w.part == "adxl345":
                dev = ADXL345.i2c(w.bus_number, w.address, smbus=buses[w.bus_number],
                                  config=adxl_config, name=w.name, **driver_kwargs)
            else:
                dev = MPU9150.i2c(w.bus_number, w.address, smbus=buses[w.bus_number],
                                  config=mpu_config, name=w.name, **driver_kwargs)
        except DeviceNotFoundError as e:  # no /dev node: the Pi's setup, not the device
            problems.append(f"{w.name}: {e}")
            cannot_open = True
            continue
        try:
            dev.init()
        except (DeviceNotFoundError, DeviceConfigError) as e:
            problems.append(f"{w.name}: {e}")
        devices[w.name] = dev
    if problems and (require_all or cannot_open):
        close_all(devices)
        for bus in buses.values():
            bus.close()
        raise DeviceNotFoundError("\n".join(problems))
    return {w.name: devices[w.name] for w in wiring}


def close_all(devices: Mapping[str, ADXL345 | MPU9150]) -> None:
    """Close every device and, once each, the I2C buses they share."""
    shared: dict[int, SMBusLike] = {}
    for dev in devices.values():
        dev.close()
        bus = getattr(dev.transport, "bus", None)
        if bus is not None:
            shared[id(bus)] = bus
    for bus in shared.values():
        bus.close()


def readers_for(devices: Mapping[str, ADXL345 | MPU9150]) -> dict[str, Callable[[], Any]]:
    """The read callable of each device: ``read_fifo`` for FIFO-mode ADXL345s."""
    out: dict[str, Callable[[], Any]] = {}
    for name, dev in devices.items():
        if isinstance(dev, ADXL345) and dev.config.fifo:
            out[name] = dev.read_fifo
        else:
            out[name] = dev.read
    return out
