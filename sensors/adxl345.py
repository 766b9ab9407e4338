"""ADXL345 3-axis accelerometer over I2C (smbus2) or 4-wire SPI (spidev).

One driver, two transports (:mod:`armfusion.sensors.bus`). It returns raw counts exactly as
the device gives them, stamped with the host's monotonic clock; conversion to g
is a model step (the only place this module uses g is the self-test limits).

The register map, the configuration (:class:`ADXL345Config`) and the data sheet's tables
are :mod:`armfusion.sensors.adxl345_registers`.

Reads (see docs/reference/drivers.md for the reasons):

* :meth:`ADXL345.read` (FIFO bypass): one 8-byte burst from INT_SOURCE (0x30):
  INT_SOURCE says whether the data are new (DATA_READY) and whether a sample was
  overwritten unread (Overrun); DATA_FORMAT (0x31) is a check byte that must echo
  the configured value (a reset device, a floating MISO or a wrong SPI mode gives
  something else); 0x32-0x37 are X, Y, Z from one sample.
* :meth:`ADXL345.read_fifo` (stream mode): one 2-byte burst FIFO_CTL (check byte)
  + FIFO_STATUS, then one 6-byte burst from 0x32 per entry. Nothing is lost while
  the host reads at least once per 32 samples.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from armfusion.sensors.adxl345_registers import (
    BW_RATE,
    DATA_FORMAT,
    DATA_READY,
    DATAX0,
    DEFAULT_CONFIG,
    DEVID,
    DEVID_VALUE,
    FIFO_BYPASS,
    FIFO_CTL,
    FIFO_DEPTH,
    FULL_RES,
    I2C_ADDRESS,
    I2C_ADDRESS_ALT,
    INT_SOURCE,
    MEASURE,
    OFSX,
    OFSY,
    OFSZ,
    OVERRUN,
    POWER_CTL,
    RANGE_BITS,
    SELF_TEST,
    SPI_DEFAULT_SPEED_HZ,
    SPI_MAX_SPEED_HZ,
    SPI_MODE,
    SPI_MULTI,
    SPI_READ,
    ADXL345Config,
    rate_code,
    self_test_limits_lsb,
    self_test_verdict,
    xyz_counts,
)
from armfusion.sensors.bus import (
    DEFAULT_RECOVERY,
    DEFAULT_RETRY,
    BusError,
    DeviceConfigError,
    DeviceNotFoundError,
    RecoveryPolicy,
    RegisterTransport,
    RetryPolicy,
    SMBusLike,
    SpiDevLike,
    SpiRegisters,
    Status,
)
from armfusion.sensors.device import SupervisedDevice, check_identity, check_read_back
from armfusion.sensors.samples import Stream, accel_columns

__all__ = [
    "FIFO_DEPTH", "I2C_ADDRESS", "I2C_ADDRESS_ALT", "ADXL345", "ADXL345Config", "AccelSample",
    "SelfTestResult", "accel_stream", "rate_code", "self_test_limits_lsb",
]


@dataclass(frozen=True)
class AccelSample:
    """One reading: ``counts`` (x, y, z) only when ``status`` is OK, else None.

    ``overrun`` is True when the device reports that at least one sample was
    overwritten before this one was read (bypass) or the FIFO was full (stream).
    """

    t_s: float
    counts: tuple[int, int, int] | None
    status: Status
    overrun: bool = False

    @property
    def valid(self) -> bool:
        return self.status is Status.OK


@dataclass(frozen=True)
class SelfTestResult:
    """Outcome of :meth:`ADXL345.self_test`. ``delta_lsb`` at 3.9 mg/LSB."""

    passed: bool
    delta_lsb: tuple[float, float, float] | None
    limits_lsb: tuple[tuple[float, float], ...]
    supply_v: float
    message: str


class ADXL345(SupervisedDevice):
    """ADXL345 driver. Build with :meth:`i2c` / :meth:`spi`, then :meth:`init`.

    ``clock`` stamps samples and drives timeouts (default ``time.monotonic``);
    ``sleep`` is used for retry backoff and self-test waits (default ``time.sleep``).
    """

    def __init__(
        self,
        transport: RegisterTransport,
        config: ADXL345Config = DEFAULT_CONFIG,
        *,
        name: str = "adxl345",
        retry: RetryPolicy = DEFAULT_RETRY,
        recovery: RecoveryPolicy = DEFAULT_RECOVERY,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        super().__init__(transport, name, retry=retry, recovery=recovery, clock=clock, sleep=sleep)
        self.config = config
        self._expected_format = config.data_format
        self._expected_fifo_ctl = config.fifo_ctl
        self._last_fresh_s = 0.0
        self._last_t_s = float("-inf")

    # construction -------------------------------------------------------------------

    @classmethod
    def i2c(
        cls,
        bus_number: int = 1,
        address: int = I2C_ADDRESS,
        *,
        smbus: SMBusLike | None = None,
        **kwargs,
    ) -> ADXL345:
        """On I2C ``bus_number`` at 0x53 (SDO low) or 0x1D (SDO high).

        ``smbus``: an open smbus2.SMBus-like bus (shared by every device on it);
        by default ``smbus2.SMBus(bus_number)`` is opened and closed with the driver.
        """
        if address not in (I2C_ADDRESS, I2C_ADDRESS_ALT):
            raise ValueError(
                f"an ADXL345 answers at 0x53 (ALT ADDRESS low) or 0x1D (high), not 0x{address:02X}"
            )
        return cls(cls._i2c_transport(bus_number, address, smbus), **kwargs)

    @classmethod
    def spi(
        cls,
        bus_number: int = 0,
        device: int = 0,
        *,
        max_speed_hz: int = SPI_DEFAULT_SPEED_HZ,
        spi_factory: Callable[[], SpiDevLike] | None = None,
        **kwargs,
    ) -> ADXL345:
        """On ``/dev/spidev<bus_number>.<device>``: mode 3, clock <= 5 MHz (default 1 MHz)."""
        if not 0 < max_speed_hz <= SPI_MAX_SPEED_HZ:
            raise ValueError(
                f"ADXL345 SPI clock must be 1..{SPI_MAX_SPEED_HZ} Hz, not {max_speed_hz}"
            )
        if spi_factory is None:
            import spidev

            spi_factory = spidev.SpiDev
        try:
            transport = SpiRegisters.open(
                spi_factory,
                bus_number,
                device,
                mode=SPI_MODE,
                max_speed_hz=max_speed_hz,
                read_bit=SPI_READ,
                multi_bit=SPI_MULTI,
            )
        except OSError as e:
            raise DeviceNotFoundError(
                f"no ADXL345 on SPI bus {bus_number} device {device}: cannot open "
                f"/dev/spidev{bus_number}.{device} ({e.strerror or e}); is SPI enabled "
                "(dtparam=spi=on in /boot/config.txt)?"
            ) from e
        return cls(transport, **kwargs)

    # lifecycle ----------------------------------------------------------------------

    def init(self) -> None:
        """Identify the device and configure it; raise with one clear line if absent."""
        first = not self._initialised_once
        try:
            self._identify()
            self._configure()
        except (DeviceNotFoundError, DeviceConfigError) as e:
            self._sup.init_failed(str(e), first=first)
            raise
        self._initialised_once = True
        self._sup.init_succeeded(first=first)

    def _identify(self) -> None:
        hint = ""
        if isinstance(self.transport, SpiRegisters):
            hint = " (check wiring, chip select, SPI mode 3 and clock <= 5 MHz)"
        check_identity(self._sup, self.transport, "ADXL345", DEVID, "DEVID", DEVID_VALUE, hint)

    def _write(self, register: int, value: int) -> None:
        self._sup.call(self.transport.write, register, value)

    def _configure(
        self, *, bw_rate: int | None = None, data_format: int | None = None, fifo_ctl: int | None = None
    ) -> None:
        """Standby, format, rate, zero offsets, FIFO, flush old data, measure; read back."""
        c = self.config
        bw_rate = c.bw_rate if bw_rate is None else bw_rate
        data_format = c.data_format if data_format is None else data_format
        fifo_ctl = c.fifo_ctl if fifo_ctl is None else fifo_ctl
        try:
            self._write(POWER_CTL, 0x00)  # standby while configuring (data sheet advice)
            self._write(DATA_FORMAT, data_format)
            self._write(BW_RATE, bw_rate)
            for reg in (OFSX, OFSY, OFSZ):
                self._write(reg, 0x00)
            self._write(FIFO_CTL, FIFO_BYPASS)  # entering bypass empties the FIFO
            if fifo_ctl != FIFO_BYPASS:
                self._write(FIFO_CTL, fifo_ctl)
            # drop a sample left from before (DATA_READY, Overrun): it is not this config's
            self._sup.call(self.transport.read, INT_SOURCE, 8)
            self._write(POWER_CTL, MEASURE)
            back = self._sup.call(self.transport.read, BW_RATE, 6)  # 0x2C..0x31
            fifo_back = self._sup.call(self.transport.read, FIFO_CTL, 1)[0]
        except BusError as e:
            raise DeviceConfigError(f"ADXL345 on {self.transport.where}: {e.__cause__}") from e
        check_read_back("ADXL345", self.transport.where, (
            (BW_RATE, "BW_RATE", bw_rate, back[0]),
            (POWER_CTL, "POWER_CTL", MEASURE, back[1]),
            (DATA_FORMAT, "DATA_FORMAT", data_format, back[5]),
            (FIFO_CTL, "FIFO_CTL", fifo_ctl, fifo_back),
        ))
        self._expected_format = data_format
        self._expected_fifo_ctl = fifo_ctl
        self._last_fresh_s = self._clock()

    # reading ------------------------------------------------------------------------

    def read(self) -> AccelSample:
        """The newest sample (FIFO bypass). Never raises on bus or device faults."""
        if self.config.fifo:
            raise RuntimeError(f"{self.name}: configured with fifo=True, use read_fifo()")
        if not self._read_begins():
            return AccelSample(self._clock(), None, Status.OFFLINE)
        t = self._clock()
        try:
            raw = self._sup.call(self.transport.read, INT_SOURCE, 8)
        except BusError as e:
            return self._bus_error(t, e)
        if raw[1] != self._expected_format:
            return self._bad_data(t, f"DATA_FORMAT read 0x{raw[1]:02X}, expected "
                                     f"0x{self._expected_format:02X}")
        if not raw[0] & DATA_READY:
            return self._no_new_data(t)
        counts = xyz_counts(raw, 2)
        overrun = bool(raw[0] & OVERRUN)
        return self._fresh(t, counts, overrun)

    def read_fifo(self) -> list[AccelSample]:
        """Every sample queued in the FIFO (stream mode), oldest first; [] if none yet.

        Timestamps: the newest entry gets the read time, older ones are spaced back
        by the output data period (then kept strictly increasing across calls).
        A failure gives a one-element list with the invalid sample.
        """
        if not self.config.fifo:
            raise RuntimeError(f"{self.name}: configured with fifo=False, use read()")
        if not self._read_begins():
            return [AccelSample(self._clock(), None, Status.OFFLINE)]
        sup = self._sup
        t = self._clock()
        try:
            ctl, status = sup.call(self.transport.read, FIFO_CTL, 2)
        except BusError as e:
            return [self._bus_error(t, e)]
        entries = status & 0x3F
        if ctl != self._expected_fifo_ctl or entries > FIFO_DEPTH + 1:
            return [self._bad_data(t, f"FIFO_CTL read 0x{ctl:02X}, expected "
                                      f"0x{self._expected_fifo_ctl:02X}, entries {entries}")]
        if entries == 0:
            s = self._no_new_data(t)
            return [] if s.status is Status.STALE else [s]
        overrun = entries >= FIFO_DEPTH
        if overrun:
            sup.count("overruns")
        period = 1.0 / self.config.output_rate_hz
        out: list[AccelSample] = []
        for i in range(entries):
            try:
                b = sup.call(self.transport.read, DATAX0, 6)
            except BusError as e:
                out.append(self._bus_error(t, e))
                break
            counts = xyz_counts(b)
            ti = max(t - (entries - 1 - i) * period, self._last_t_s + 1e-6)
            self._last_t_s = ti
            out.append(AccelSample(ti, counts, Status.OK, overrun=overrun and i == 0))
            sup.count("ok")
        if out and out[0].valid:
            self._last_fresh_s = t
            sup.good_read()
        return out

    def _fresh(self, t: float, counts: tuple[int, int, int], overrun: bool) -> AccelSample:
        sup = self._sup
        if overrun:
            sup.count("overruns")
        sup.count("ok")
        sup.good_read()
        self._last_fresh_s = t
        self._last_t_s = t
        return AccelSample(t, counts, Status.OK, overrun)

    def _bus_error(self, t: float, e: BusError) -> AccelSample:
        self._sup.count("invalid")
        self._sup.failed_read(str(e))
        return AccelSample(t, None, Status.BUS_ERROR)

    def _no_new_data(self, t: float) -> AccelSample:
        sup = self._sup
        if t - self._last_fresh_s > self.config.stale_timeout:
            sup.count("not_ready")
            sup.count("invalid")
            sup.failed_read(
                f"{self.transport.where}: no new data for {t - self._last_fresh_s:.3f} s"
            )
            self._last_fresh_s = t  # one NOT_READY per timeout, not one per read
            return AccelSample(t, None, Status.NOT_READY)
        sup.count("stale")
        return AccelSample(t, None, Status.STALE)

    def _bad_data(self, t: float, what: str) -> AccelSample:
        sup = self._sup
        sup.count("bad_data")
        sup.count("invalid")
        sup.go_offline(f"{self.transport.where}: {what}", retry_now=True)
        return AccelSample(t, None, Status.BAD_DATA)

    # self-test ----------------------------------------------------------------------

    def self_test(self, n_average: int = 16, settle_samples: int = 4) -> SelfTestResult:
        """Data sheet self-test: output change with SELF_TEST set, against Table 15.

        Runs in full resolution, ±16 g (room for the whole shift; AN-1077), at the
        configured rate if it is 100..800 Hz (the data sheet's valid rates), else
        100 Hz, normal power, FIFO bypassed; ``n_average`` samples each with the
        self-test force off and on, after ``settle_samples`` are discarded. Restores
        the configuration afterwards. Limits: Table 15 scaled by Table 14 for
        ``config.supply_v``. A dead, stuck or disconnected sensor fails.
        """
        limits = self_test_limits_lsb(self.config.supply_v)
        vs = self.config.supply_v
        where = self.transport.where
        rate = self.config.rate_hz if 100 <= self.config.rate_hz <= 800 else 100.0
        fmt_off = FULL_RES | RANGE_BITS[16]
        fmt_on = fmt_off | SELF_TEST
        try:
            if not self._sup.online:
                self.init()
            self._configure(bw_rate=rate_code(rate), data_format=fmt_off, fifo_ctl=FIFO_BYPASS)
            off = self._average(n_average, settle_samples, rate, fmt_off)
            self._write(DATA_FORMAT, fmt_on)
            self._expected_format = fmt_on
            on = self._average(n_average, settle_samples, rate, fmt_on)
            self._write(DATA_FORMAT, fmt_off)
            self._configure()
        except (BusError, DeviceNotFoundError, DeviceConfigError, TimeoutError) as e:
            self._sup.count("self_test_failures")
            self._sup.go_offline(str(e), retry_now=True)
            return SelfTestResult(False, None, limits, vs, f"ADXL345 on {where}: self-test "
                                                          f"FAILED: {e}")
        delta = tuple(float(a - b) for a, b in zip(on, off, strict=True))
        passed, msg = self_test_verdict(where, vs, limits, delta)
        if not passed:
            self._sup.count("self_test_failures")
        return SelfTestResult(passed, delta, limits, vs, msg)  # type: ignore[arg-type]

    def _average(self, n: int, settle: int, rate_hz: float, fmt: int) -> np.ndarray:
        period = 1.0 / rate_hz
        got: list[tuple[int, int, int]] = []
        deadline = self._clock() + (n + settle + 10) * period * 3 + 0.1
        while len(got) < n + settle:
            raw = self._sup.call(self.transport.read, INT_SOURCE, 8)
            if raw[1] != fmt:
                raise DeviceConfigError(f"DATA_FORMAT read 0x{raw[1]:02X}, expected 0x{fmt:02X}")
            if raw[0] & DATA_READY:
                got.append(xyz_counts(raw, 2))
                continue
            if self._clock() > deadline:
                raise TimeoutError(f"no data (DATA_READY never set) after {len(got)} samples")
            self._sleep(period / 2)
        return np.mean(np.array(got[settle:], dtype=np.float64), axis=0)


def accel_stream(name: str, samples: Sequence[AccelSample]) -> Stream:
    """The valid samples as a raw ``accel`` stream named ``name`` (invalid ones dropped)."""
    good = [s for s in samples if s.valid]
    t = np.array([s.t_s for s in good], dtype=np.float64)
    v = np.array([s.counts for s in good], dtype=np.int64).reshape(-1, 3)
    return Stream(name, "accel", t, v, accel_columns(name))
