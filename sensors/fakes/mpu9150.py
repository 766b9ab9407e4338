"""FakeMPU9150 and FakeAK8975: register-level emulators on one FakeSMBus.

FakeMPU9150 (register map rev. 4.2): reset values (PWR_MGMT_1 0x40 = asleep,
WHO_AM_I 0x68, the rest 0x00); DEVICE_RESET; data registers updated only while
awake, at the sample rate ``gyro output rate / (1 + SMPLRT_DIV)`` (8 kHz with
DLPF_CFG 0 or 7, else 1 kHz); big-endian accel (16384/8192/4096/2048 LSB/g),
temperature (raw = (T - 35) * 340), gyro (131/65.5/32.8/16.4 LSB per °/s),
saturating at int16; INT_STATUS DATA_RDY cleared on read; the bypass switch
(INT_PIN_CFG bit 1 with USER_CTRL I2C_MST_EN clear) that puts the AK8975 on the
host's bus. Not emulated: the digital low-pass filter itself (values are the
physics at the sample instants), self-test, FIFO, I2C master, interrupts pins.

FakeAK8975 (data sheet): WIA 0x48; visible on the bus only through the bypass of
its FakeMPU9150; CNTL modes power-down, single measurement and fuse-ROM access
(self-test mode is not emulated); a mode change other than to power-down needs
power-down first and 100 µs of wait (otherwise noted in ``violations`` and, for
the missing power-down, ignored); a single measurement takes
``measurement_time_s`` (7.3 ms typ), sets ST1 DRDY and returns to power-down;
reading ST2 clears DRDY; ASAX..ASAZ readable only in fuse-ROM mode; counts at
0.3 µT/LSB divided by the ASA factor (so the driver's adjustment gives the field
back), 13-bit ±4095, ST2 HOFL when an axis saturates or |Hx|+|Hy|+|Hz| > 2400 µT.
Its axes: x = MPU y, y = MPU x, z = -MPU z; the physics source gives the field in
the MPU's (accelerometer's) axes.

Faults: ``faults``, ``disappear()`` (an unplugged MPU-9150 takes its AK8975 with
it), ``who_am_i`` / ``wia`` (wrong part), ``drdy_never``, ``force_overflow``,
``force_data_error``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from armfusion.sensors.fakes.physics import PhysicsSource
from armfusion.sensors.fakes.registers import FakeRegisterDevice

SMPLRT_DIV, CONFIG, GYRO_CONFIG, ACCEL_CONFIG = 0x19, 0x1A, 0x1B, 0x1C
INT_PIN_CFG, INT_ENABLE, INT_STATUS, ACCEL_XOUT_H = 0x37, 0x38, 0x3A, 0x3B
USER_CTRL, PWR_MGMT_1, PWR_MGMT_2, WHO_AM_I = 0x6A, 0x6B, 0x6C, 0x75
MPU_READ_ONLY = frozenset([INT_STATUS, *range(0x3B, 0x61), 0x72, 0x73, WHO_AM_I])
ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)

WIA, INFO, ST1, HXL, ST2, CNTL, ASTC, I2CDIS, ASAX = 0x00, 0x01, 0x02, 0x03, 0x09, 0x0A, 0x0C, \
    0x0F, 0x10
AK_WRITABLE = frozenset([CNTL, ASTC, I2CDIS])
UT_PER_LSB = 0.3
T_MODE_WAIT_S = 100e-6


def _s16(v: float) -> int:
    return int(min(max(round(v), -32768), 32767))


@dataclass(frozen=True)
class ProducedImuSample:
    index: int
    t_s: float
    accel: tuple[int, int, int]
    temp: int
    gyro: tuple[int, int, int]


class FakeMPU9150(FakeRegisterDevice):
    """One emulated MPU-9150 with its AK8975 (``.ak8975``); attach both to a FakeSMBus."""

    name = "MPU-9150"

    def __init__(
        self,
        physics: PhysicsSource,
        clock: Callable[[], float],
        *,
        address: int = 0x68,
        who_am_i: int = 0x68,
        asa: tuple[int, int, int] = (176, 178, 165),
        seed: int = 0,
    ):
        super().__init__(clock, seed=seed)
        self.physics = physics
        self.address = address
        self.who_am_i = who_am_i
        self.produced: deque[ProducedImuSample] = deque(maxlen=200_000)
        self.resets = 0
        self.reset()
        self.ak8975 = FakeAK8975(physics, clock, host=self, asa=asa, seed=seed + 1)

    def reset(self) -> None:
        self.regs = bytearray(0x80)
        self.regs[PWR_MGMT_1] = 0x40
        self._t_wake = 0.0
        self._k = -1
        self._data_ready = False

    @property
    def awake(self) -> bool:
        return not self.regs[PWR_MGMT_1] & 0x40

    @property
    def bypass_enabled(self) -> bool:
        return bool(self.regs[INT_PIN_CFG] & 0x02) and not self.regs[USER_CTRL] & 0x20

    @property
    def sample_rate_hz(self) -> float:
        dlpf = self.regs[CONFIG] & 0x07
        return (8000.0 if dlpf in (0, 7) else 1000.0) / (1 + self.regs[SMPLRT_DIV])

    def _advance(self, now: float) -> None:
        if not self.awake:
            return
        period = 1.0 / self.sample_rate_hz
        k = math.floor((now - self._t_wake) / period + 1e-9) - 1  # first sample one period in
        if k > self._k and k >= 0:
            self._k = k
            self._make_sample(k, self._t_wake + (k + 1) * period)

    def _make_sample(self, k: int, t: float) -> None:
        afs = (self.regs[ACCEL_CONFIG] >> 3) & 3
        fs = (self.regs[GYRO_CONFIG] >> 3) & 3
        a = self.physics.specific_force_g(t) * ACCEL_LSB_PER_G[afs]
        w = np.degrees(self.physics.angular_rate_rad_s(t)) * GYRO_LSB_PER_DPS[fs]
        temp = _s16((self.physics.temperature_c(t) - 35.0) * 340.0)
        accel = (_s16(a[0]), _s16(a[1]), _s16(a[2]))
        gyro = (_s16(w[0]), _s16(w[1]), _s16(w[2]))
        self.produced.append(ProducedImuSample(k, t, accel, temp, gyro))
        for i, v in enumerate((*accel, temp, *gyro)):
            self.regs[ACCEL_XOUT_H + 2 * i] = (v >> 8) & 0xFF
            self.regs[ACCEL_XOUT_H + 2 * i + 1] = v & 0xFF
        self._data_ready = True

    def _read(self, register: int) -> int:
        if register == WHO_AM_I:
            return self.who_am_i
        if register == INT_STATUS:
            return 0x01 if self._data_ready else 0x00
        return self.regs[register] if register < len(self.regs) else 0x00

    def _after_read(self, registers: list[int], now: float) -> None:
        if INT_STATUS in registers:
            self._data_ready = False

    def _write(self, register: int, value: int, now: float) -> None:
        if register in MPU_READ_ONLY or register >= len(self.regs):
            self.violations.append(f"write 0x{value:02X} to read-only 0x{register:02X}")
            return
        if register == PWR_MGMT_1 and value & 0x80:
            self.resets += 1
            self.reset()
            return
        was_awake = self.awake
        self.regs[register] = value & (0xF8 if register == USER_CTRL else 0xFF)
        if register == PWR_MGMT_1 and self.awake and not was_awake:
            self._t_wake, self._k = now, -1
        elif register in (SMPLRT_DIV, CONFIG) and self.awake:
            self._t_wake, self._k = now, -1


class FakeAK8975(FakeRegisterDevice):
    """The AK8975 die of a FakeMPU9150 (or stand-alone with ``host=None``)."""

    name = "AK8975"

    def __init__(
        self,
        physics: PhysicsSource,
        clock: Callable[[], float],
        *,
        host: FakeMPU9150 | None = None,
        address: int = 0x0C,
        asa: tuple[int, int, int] = (176, 178, 165),
        measurement_time_s: float = 7.3e-3,
        seed: int = 0,
    ):
        super().__init__(clock, seed=seed)
        self.physics = physics
        self.host = host
        self.address = address
        self.asa = tuple(asa)
        self.wia = 0x48
        self.measurement_time_s = measurement_time_s
        self.drdy_never = False
        self.force_overflow = False
        self.force_data_error = False
        self.measurements = 0
        self.reset()

    def reset(self) -> None:
        self.regs = bytearray(0x13)
        self._mode = 0
        self._t_power_down = -math.inf
        self._t_trigger: float | None = None

    def responds(self) -> bool:
        if not self.present:
            return False
        return self.host is None or (self.host.present and self.host.bypass_enabled)

    @property
    def factors(self) -> np.ndarray:
        return np.array([(a - 128) * 0.5 / 128 + 1 for a in self.asa])

    def raw_for(self, field_mpu_uT: np.ndarray) -> tuple[tuple[int, int, int], bool]:
        """Raw AK8975 counts (its own axes) and HOFL for a field in the MPU's axes."""
        m = np.asarray(field_mpu_uT, dtype=float)
        ak = np.array([m[1], m[0], -m[2]])
        raw = np.rint(ak / UT_PER_LSB / self.factors)
        overflow = bool(np.any(np.abs(raw) > 4095) or np.sum(np.abs(ak)) > 2400.0)
        raw = np.clip(raw, -4095, 4095).astype(int)
        return (int(raw[0]), int(raw[1]), int(raw[2])), overflow or self.force_overflow

    def _advance(self, now: float) -> None:
        if self._t_trigger is None or self.drdy_never:
            return
        if now - self._t_trigger < self.measurement_time_s:
            return
        raw, overflow = self.raw_for(self.physics.magnetic_field_uT(self._t_trigger))
        for i, v in enumerate(raw):
            self.regs[HXL + 2 * i] = v & 0xFF
            self.regs[HXL + 2 * i + 1] = (v >> 8) & 0xFF
        self.regs[ST2] = (0x08 if overflow else 0) | (0x04 if self.force_data_error else 0)
        self.regs[ST1] = 0x01
        self.measurements += 1
        self._mode = 0  # back to power-down by itself when the measurement ends
        self._t_power_down = self._t_trigger + self.measurement_time_s
        self._t_trigger = None

    def _read(self, register: int) -> int:
        if register == WIA:
            return self.wia
        if ASAX <= register <= ASAX + 2:
            return self.asa[register - ASAX] if self._mode == 0x0F else 0x00
        if register == CNTL:
            return self._mode
        return self.regs[register] if register < len(self.regs) else 0x00

    def _after_read(self, registers: list[int], now: float) -> None:
        if ST2 in registers:
            self.regs[ST1] = 0x00

    def _write(self, register: int, value: int, now: float) -> None:
        if register not in AK_WRITABLE:
            self.violations.append(f"write 0x{value:02X} to read-only 0x{register:02X}")
            return
        if register != CNTL:
            self.regs[register] = value
            return
        mode = value & 0x0F
        if mode not in (0x00, 0x01, 0x08, 0x0F):
            self.violations.append(f"CNTL 0x{value:02X}: not a mode")
            return
        if mode == 0:
            self._mode = 0
            self._t_trigger = None
            self._t_power_down = now
            return
        if self._mode != 0:
            self.violations.append(
                f"CNTL 0x{value:02X} while in mode 0x{self._mode:X}: power-down first")
            return
        if now - self._t_power_down < T_MODE_WAIT_S:
            self.violations.append(
                f"CNTL 0x{value:02X} {1e6 * (now - self._t_power_down):.0f} µs after power-down "
                "(needs 100 µs)")
        self._mode = mode
        if mode == 0x01:
            self._t_trigger = now
            self.regs[ST1] = 0x00
