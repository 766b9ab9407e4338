"""MPU-9150 (accelerometer, gyroscope, temperature) and its AK8975 magnetometer, over I2C.

The MPU-9150 is an MPU-6050 die with an AK8975 die in one package; the AK8975 sits
on the MPU's auxiliary I2C bus. With I2C_BYPASS_EN set (INT_PIN_CFG 0x37 bit 1)
and the MPU's own I2C master off (USER_CTRL 0x6A bit 5 clear), the host reaches
the AK8975 directly at 0x0C on the same bus.

MPU-9150 registers used (register map rev. 4.2)::

    0x19 SMPLRT_DIV   sample rate = gyro output rate / (1 + SMPLRT_DIV)
    0x1A CONFIG       bits 2:0 DLPF_CFG (gyro output rate 8 kHz at 0 or 7, else 1 kHz)
    0x1B GYRO_CONFIG  bits 4:3 FS_SEL  (0: ±250 °/s, 131 LSB/(°/s))
    0x1C ACCEL_CONFIG bits 4:3 AFS_SEL (0: ±2 g, 16384 LSB/g)
    0x37 INT_PIN_CFG  bit 1 I2C_BYPASS_EN
    0x3B..0x48        ACCEL_X/Y/Z, TEMP, GYRO_X/Y/Z, big-endian int16
    0x6A USER_CTRL    bit 5 I2C_MST_EN
    0x6B PWR_MGMT_1   bit 7 DEVICE_RESET, bit 6 SLEEP (reset value 0x40), bits 2:0 CLKSEL
    0x75 WHO_AM_I     0x68

AK8975 registers (data sheet)::

    0x00 WIA 0x48   0x02 ST1 (bit 0 DRDY)   0x03..0x08 HXL..HZH (little-endian int16)
    0x09 ST2 (bit 3 HOFL overflow, bit 2 DERR data error)   0x0A CNTL (mode)
    0x10..0x12 ASAX..ASAZ fuse ROM (readable in fuse-ROM access mode, CNTL = 0x0F)

Output (all integer counts, see :class:`ImuSample`): accelerometer and gyroscope
exactly as the registers give them; temperature raw (°C = raw/340 + 35);
magnetometer counts (0.3 µT/LSB) already multiplied by the fuse-ROM sensitivity
adjustment ``(ASA - 128) * 0.5 / 128 + 1``, rounded to the nearest integer, and
remapped into the accelerometer's axes: ``x = AK y, y = AK x, z = -AK z``.

The magnetometer runs in single-measurement mode, pipelined: each :meth:`MPU9150.read`
collects the measurement started by the previous one (ST1 DRDY poll, then one
burst HXL..ST2) and starts the next (CNTL = 0x01), so a read never blocks for the
7.3 ms (9 ms max) a measurement takes. The magnetometer sample's time is the time
the measurement was started (``t_mag_s``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from armfusion.sensors.bus import (
    DEFAULT_RECOVERY,
    DEFAULT_RETRY,
    BusError,
    DeviceConfigError,
    DeviceHealth,
    DeviceNotFoundError,
    I2CRegisters,
    RecoveryPolicy,
    RetryPolicy,
    SMBusLike,
    Status,
    Supervisor,
    hexbytes,
    s16_be,
    s16_le,
)
from armfusion.sensors.device import SupervisedDevice, check_identity, check_read_back
from armfusion.sensors.samples import IMU_STREAMS, Stream

# MPU-9150 registers
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
INT_PIN_CFG = 0x37
INT_STATUS = 0x3A
ACCEL_XOUT_H = 0x3B
USER_CTRL = 0x6A
PWR_MGMT_1 = 0x6B
WHO_AM_I = 0x75

MPU_ADDRESS = 0x68  # AD0 low
MPU_ADDRESS_ALT = 0x69  # AD0 high
WHO_AM_I_VALUE = 0x68
DEVICE_RESET = 0x80
SLEEP = 0x40
CLKSEL_PLL_XGYRO = 0x01
I2C_BYPASS_EN = 0x02
I2C_MST_EN = 0x20

# AK8975 registers
AK_ADDRESS = 0x0C
WIA = 0x00
ST1 = 0x02
HXL = 0x03
ST2 = 0x09
CNTL = 0x0A
ASAX = 0x10
WIA_VALUE = 0x48
DRDY = 0x01
HOFL = 0x08
DERR = 0x04
MODE_POWER_DOWN = 0x00
MODE_SINGLE = 0x01
MODE_FUSE_ROM = 0x0F
#: AK8975: wait at least 100 µs after power-down before setting another mode.
T_MODE_WAIT_S = 100e-6

ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
MAG_UT_PER_LSB = 0.3
TEMP_LSB_PER_C = 340.0
TEMP_OFFSET_C = 35.0


def asa_factor(asa: int) -> float:
    """AK8975 sensitivity adjustment: ``Hadj = H * ((ASA - 128) * 0.5 / 128 + 1)``."""
    return (asa - 128) * 0.5 / 128.0 + 1.0


@dataclass(frozen=True)
class MPU9150Config:
    """What init writes. Defaults: ±2 g, ±250 °/s, DLPF 44/42 Hz, 1 kHz sample rate."""

    dlpf_cfg: int = 3  # CONFIG bits 2:0: 3 -> accel 44 Hz, gyro 42 Hz bandwidth
    smplrt_div: int = 0  # 1 kHz / (1 + 0) with the DLPF on
    gyro_fs_sel: int = 0  # ±250 °/s
    accel_afs_sel: int = 0  # ±2 g
    magnetometer: bool = True
    mag_timeout_s: float = 0.05  # a measurement takes 9 ms at most; after this, NOT_READY
    health_check_every: int = 100  # reads between checks that the MPU was not reset

    def __post_init__(self) -> None:
        for name, value, hi in (
            ("dlpf_cfg", self.dlpf_cfg, 6),
            ("smplrt_div", self.smplrt_div, 255),
            ("gyro_fs_sel", self.gyro_fs_sel, 3),
            ("accel_afs_sel", self.accel_afs_sel, 3),
        ):
            if not 0 <= value <= hi:
                raise ValueError(f"MPU9150Config.{name} must be 0..{hi}, not {value!r}")

    @property
    def sample_rate_hz(self) -> float:
        gyro_rate = 8000.0 if self.dlpf_cfg in (0, 7) else 1000.0
        return gyro_rate / (1 + self.smplrt_div)

    @property
    def accel_lsb_per_g(self) -> float:
        return ACCEL_LSB_PER_G[self.accel_afs_sel]

    @property
    def gyro_lsb_per_dps(self) -> float:
        return GYRO_LSB_PER_DPS[self.gyro_fs_sel]


@dataclass(frozen=True)
class ImuSample:
    """One IMU read. Values are None unless their status is OK.

    ``accel``, ``gyro``: (x, y, z) counts; ``temp``: raw temperature register;
    ``mag``: ASA-adjusted counts in the accelerometer's axes, measured from
    ``t_mag_s``. The magnetometer is ``STALE`` while a measurement is in progress.
    """

    t_s: float
    status: Status
    accel: tuple[int, int, int] | None = None
    temp: int | None = None
    gyro: tuple[int, int, int] | None = None
    mag_status: Status = Status.DISABLED
    mag: tuple[int, int, int] | None = None
    t_mag_s: float | None = None

    @property
    def valid(self) -> bool:
        return self.status is Status.OK

    @property
    def mag_valid(self) -> bool:
        return self.mag_status is Status.OK


class MPU9150(SupervisedDevice):
    """MPU-9150 + AK8975 driver. Build with :meth:`i2c`, then :meth:`init`."""

    def __init__(
        self,
        transport: I2CRegisters,
        config: MPU9150Config = MPU9150Config(),
        *,
        name: str = "imu",
        mag_address: int = AK_ADDRESS,
        retry: RetryPolicy = DEFAULT_RETRY,
        recovery: RecoveryPolicy = DEFAULT_RECOVERY,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        super().__init__(transport, name, retry=retry, recovery=recovery, clock=clock, sleep=sleep)
        self.mag_transport = transport.sibling(mag_address)
        self.mag_transport.where += f" (AK8975 behind the MPU-9150 at 0x{transport.address:02X})"
        self.config = config
        self._mag_sup = Supervisor(
            f"{name}.mag", self.mag_transport.where,
            retry=retry, recovery=recovery, clock=clock, sleep=sleep,
        )
        self._mag_initialised_once = False
        self._asa: tuple[int, int, int] | None = None
        self._mag_trigger_t: float | None = None
        self._reads_since_check = 0

    @classmethod
    def i2c(
        cls, bus_number: int = 1, address: int = MPU_ADDRESS, *, smbus: SMBusLike | None = None,
        **kwargs,
    ) -> MPU9150:
        """On I2C ``bus_number`` at 0x68 (AD0 low) or 0x69 (AD0 high)."""
        if address not in (MPU_ADDRESS, MPU_ADDRESS_ALT):
            raise ValueError(
                f"an MPU-9150 answers at 0x68 (AD0 low) or 0x69 (AD0 high), not 0x{address:02X}"
            )
        return cls(cls._i2c_transport(bus_number, address, smbus), **kwargs)

    # lifecycle ----------------------------------------------------------------------

    @property
    def asa(self) -> tuple[int, int, int] | None:
        """The AK8975 fuse-ROM sensitivity adjustment values read at init."""
        return self._asa

    def mag_health(self) -> DeviceHealth:
        return self._mag_sup.health()

    def init(self) -> None:
        """Identify, reset and configure the MPU-9150, then the AK8975 behind it.

        Raises DeviceNotFoundError / DeviceConfigError with one line when a part is
        missing or does not take its configuration.
        """
        first = not self._initialised_once
        try:
            self._init_mpu()
        except (DeviceNotFoundError, DeviceConfigError) as e:
            self._sup.init_failed(str(e), first=first)
            self._mag_sup.go_offline(str(e))
            raise
        self._initialised_once = True
        self._sup.init_succeeded(first=first)
        self._reads_since_check = 0
        if self.config.magnetometer:
            mag_first = not self._mag_initialised_once
            try:
                self._init_mag()
            except (DeviceNotFoundError, DeviceConfigError) as e:
                self._mag_sup.init_failed(str(e), first=mag_first)
                if first:
                    raise
                return
            self._mag_initialised_once = True
            self._mag_sup.init_succeeded(first=mag_first)

    def _write(self, sup: Supervisor, transport: I2CRegisters, register: int, value: int) -> None:
        sup.call(transport.write, register, value)

    def _init_mpu(self) -> None:
        t, sup, c = self.transport, self._sup, self.config
        check_identity(sup, t, "MPU-9150", WHO_AM_I, "WHO_AM_I", WHO_AM_I_VALUE)
        expected = (
            (SMPLRT_DIV, "SMPLRT_DIV", c.smplrt_div),
            (CONFIG, "CONFIG", c.dlpf_cfg),
            (GYRO_CONFIG, "GYRO_CONFIG", c.gyro_fs_sel << 3),
            (ACCEL_CONFIG, "ACCEL_CONFIG", c.accel_afs_sel << 3),
            (USER_CTRL, "USER_CTRL", 0x00),
            (INT_PIN_CFG, "INT_PIN_CFG", I2C_BYPASS_EN if c.magnetometer else 0x00),
        )
        try:
            self._write(sup, t, PWR_MGMT_1, DEVICE_RESET)  # every register to its reset value
            self._sleep(0.1)
            self._write(sup, t, PWR_MGMT_1, CLKSEL_PLL_XGYRO)  # wake, PLL on the X gyro
            self._sleep(0.05)  # PLL lock and gyro start-up (30 ms typ)
            for reg, _, value in expected:
                self._write(sup, t, reg, value)
            back = sup.call(t.read, SMPLRT_DIV, 4)  # 0x19..0x1C
            pwr = sup.call(t.read, USER_CTRL, 2)  # 0x6A, 0x6B
            pin = sup.call(t.read, INT_PIN_CFG, 1)[0]
        except BusError as e:
            raise DeviceConfigError(f"MPU-9150 on {t.where}: {e.__cause__}") from e
        got = {SMPLRT_DIV: back[0], CONFIG: back[1], GYRO_CONFIG: back[2],
               ACCEL_CONFIG: back[3], USER_CTRL: pwr[0], INT_PIN_CFG: pin}
        check_read_back("MPU-9150", t.where, (
            (reg, name, value, pwr[1] if reg == PWR_MGMT_1 else got[reg])
            for reg, name, value in expected + ((PWR_MGMT_1, "PWR_MGMT_1", CLKSEL_PLL_XGYRO),)))

    def _init_mag(self) -> None:
        t, sup = self.mag_transport, self._mag_sup
        self._mag_trigger_t = None
        check_identity(sup, t, "AK8975", WIA, "WIA", WIA_VALUE)
        try:
            self._write(sup, t, CNTL, MODE_POWER_DOWN)
            self._sleep(T_MODE_WAIT_S)
            self._write(sup, t, CNTL, MODE_FUSE_ROM)
            asa = tuple(sup.call(t.read, ASAX, 3))
            self._write(sup, t, CNTL, MODE_POWER_DOWN)
            self._sleep(T_MODE_WAIT_S)
        except BusError as e:
            raise DeviceConfigError(f"AK8975 on {t.where}: {e.__cause__}") from e
        if asa in ((0, 0, 0), (0xFF, 0xFF, 0xFF)):
            raise DeviceConfigError(
                f"AK8975 on {t.where}: fuse ROM ASA read {hexbytes(asa)}: "
                "not in fuse-ROM access mode?"
            )
        self._asa = asa  # type: ignore[assignment]
        self._asa_factor = np.array([asa_factor(a) for a in asa])

    # reading ------------------------------------------------------------------------

    def read(self) -> ImuSample:
        """One 14-byte burst (accel, temp, gyro) plus the magnetometer step. Never raises."""
        sup = self._sup
        mag_off = Status.OFFLINE if self.config.magnetometer else Status.DISABLED
        if not self._read_begins():
            return ImuSample(self._clock(), Status.OFFLINE, mag_status=mag_off)
        self._reads_since_check += 1
        if self._reads_since_check >= self.config.health_check_every:
            self._reads_since_check = 0
            problem = self._health_check()
            if problem:
                sup.count("invalid")
                sup.count("bad_data")
                sup.go_offline(f"{self.transport.where}: {problem}", retry_now=True)
                self._mag_sup.go_offline("MPU-9150 offline")
                return ImuSample(self._clock(), Status.BAD_DATA, mag_status=mag_off)
        t = self._clock()  # just before the data burst
        try:
            b = sup.call(self.transport.read, ACCEL_XOUT_H, 14)
        except BusError as e:
            sup.count("invalid")
            sup.failed_read(str(e))
            if not sup.online:
                self._mag_sup.go_offline("MPU-9150 offline")
            return ImuSample(t, Status.BUS_ERROR, mag_status=Status.BUS_ERROR)
        w = [s16_be(b[i], b[i + 1]) for i in range(0, 14, 2)]
        sup.count("ok")
        sup.good_read()
        mag_status, mag, t_mag = self._read_mag(t)
        return ImuSample(
            t, Status.OK, (w[0], w[1], w[2]), w[3], (w[4], w[5], w[6]), mag_status, mag, t_mag
        )

    def _health_check(self) -> str:
        """'' when the MPU still holds its configuration; else what is wrong."""
        try:
            user_ctrl, pwr = self._sup.call(self.transport.read, USER_CTRL, 2)
            pin = self._sup.call(self.transport.read, INT_PIN_CFG, 1)[0]
        except BusError as e:
            return str(e)
        want_pin = I2C_BYPASS_EN if self.config.magnetometer else 0x00
        if pwr != CLKSEL_PLL_XGYRO or user_ctrl != 0x00 or pin != want_pin:
            return (f"configuration lost (PWR_MGMT_1 0x{pwr:02X}, USER_CTRL 0x{user_ctrl:02X}, "
                    f"INT_PIN_CFG 0x{pin:02X}): device reset?")
        return ""

    def _trigger_mag(self) -> None:
        self._mag_sup.call(self.mag_transport.write, CNTL, MODE_SINGLE)
        self._mag_trigger_t = self._clock()

    def _read_mag(self, t: float) -> tuple[Status, tuple[int, int, int] | None, float | None]:
        if not self.config.magnetometer:
            return Status.DISABLED, None, None
        sup, tr = self._mag_sup, self.mag_transport
        sup.count("reads")
        if not sup.online:
            if not sup.reinit_due():
                sup.count("invalid")
                return Status.OFFLINE, None, None
            first = not self._mag_initialised_once
            try:
                self._init_mag()
            except (DeviceNotFoundError, DeviceConfigError) as e:
                sup.init_failed(str(e), first=first)
                sup.count("invalid")
                return Status.OFFLINE, None, None
            self._mag_initialised_once = True
            sup.init_succeeded(first=first)
        try:
            if self._mag_trigger_t is None:
                self._trigger_mag()
                sup.count("stale")
                return Status.STALE, None, None
            st1 = sup.call(tr.read, ST1, 1)[0]
            if not st1 & DRDY:
                if t - self._mag_trigger_t <= self.config.mag_timeout_s:
                    sup.count("stale")
                    return Status.STALE, None, None
                sup.count("not_ready")
                sup.count("invalid")
                sup.failed_read(f"{tr.where}: DRDY not set {t - self._mag_trigger_t:.3f} s "
                                "after a single measurement was started")
                # leave single-measurement mode the data sheet's way, then start again
                self._mag_trigger_t = None
                sup.call(tr.write, CNTL, MODE_POWER_DOWN)
                self._sleep(T_MODE_WAIT_S)
                if sup.online:
                    self._trigger_mag()
                return Status.NOT_READY, None, None
            b = sup.call(tr.read, HXL, 7)  # HXL..HZH, ST2: one burst, ST2 read last
            t_mag = self._mag_trigger_t
            self._trigger_mag()
        except BusError as e:
            self._mag_trigger_t = None
            sup.count("invalid")
            sup.failed_read(str(e))
            return Status.BUS_ERROR, None, None
        st2 = b[6]
        sup.good_read()
        if st2 & HOFL:
            sup.count("overflow")
            sup.count("invalid")
            return Status.OVERFLOW, None, t_mag
        if st2 & DERR:
            sup.count("sensor_error")
            sup.count("invalid")
            return Status.SENSOR_ERROR, None, t_mag
        h = np.array([s16_le(b[0], b[1]), s16_le(b[2], b[3]), s16_le(b[4], b[5])], dtype=float)
        adj = np.rint(h * self._asa_factor).astype(int)
        sup.count("ok")
        return Status.OK, (int(adj[1]), int(adj[0]), int(-adj[2])), t_mag


def imu_streams(samples: Sequence[ImuSample]) -> dict[str, Stream]:
    """The valid parts of IMU samples as the raw streams of ``armfusion.sensors.samples``."""
    good = [s for s in samples if s.valid]
    mags = [s for s in samples if s.mag_valid]
    t = np.array([s.t_s for s in good], dtype=np.float64)
    columns = {
        "imu_acc": (t, [s.accel for s in good]),
        "imu_gyro": (t, [s.gyro for s in good]),
        "imu_temp": (t, [(s.temp,) for s in good]),
        "imu_mag": (np.array([s.t_mag_s for s in mags], dtype=np.float64), [s.mag for s in mags]),
    }
    out: dict[str, Stream] = {}
    for name, (ts, values) in columns.items():
        kind, channels = IMU_STREAMS[name]
        v = np.array(values, dtype=np.int64).reshape(-1, len(channels))
        out[name] = Stream(name, kind, ts, v, channels)
    return out
