"""FakeADXL345: a register-level ADXL345 (data sheet Rev. E), reached by FakeSMBus or FakeSpiDev.

What it emulates:

* the register file with the data sheet's reset values (DEVID 0xE5, BW_RATE 0x0A,
  INT_SOURCE 0x02, everything else 0x00); reserved (0x01-0x1C) and read-only
  registers ignore writes (noted in ``violations``);
* measurement only in measure mode (POWER_CTL bit 3): samples at the output data
  rate of BW_RATE, the first one period after Measure is set;
* the output format of DATA_FORMAT: 10-bit (256/128/64/32 LSB/g for ±2/4/8/16 g)
  or full resolution (256 LSB/g, 10 to 13 bits), saturating at the format's range,
  right- or left-justified, two's complement little-endian in 0x32-0x37;
* the OFSX/Y/Z offsets (15.6 mg/LSB) and the SELF_TEST force (``self_test_delta_g``);
* INT_SOURCE DATA_READY / Watermark / Overrun, cleared by reading the data;
* the FIFO (FIFO_CTL, FIFO_STATUS): bypass, FIFO (stops when full) and stream
  (keeps the newest 32) modes; trigger mode behaves as stream; reading the data
  registers pops one entry.

Not emulated: tap / activity / free-fall detection, interrupts pins, sleep and
auto-sleep, low-power noise, the 1.1 ms turn-on delay, the 33rd FIFO entry.

Faults: ``faults`` (transactions fail), ``disappear()`` / ``reappear()``,
``devid`` (a wrong part), ``stuck_counts`` (a dead sensor: constant output,
blind to self-test), ``data_ready_never`` (measure mode on but no sample ever).
"""

from __future__ import annotations

import math
import random
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from armfusion.sensors.fakes.physics import PhysicsSource
from armfusion.sensors.fakes.registers import FakeRegisterDevice

DEVID, BW_RATE, POWER_CTL, INT_SOURCE, DATA_FORMAT = 0x00, 0x2C, 0x2D, 0x30, 0x31
OFSX, OFSY, OFSZ = 0x1E, 0x1F, 0x20
DATAX0, DATAZ1, FIFO_CTL, FIFO_STATUS = 0x32, 0x37, 0x38, 0x39
RESET_VALUES = {DEVID: 0xE5, BW_RATE: 0x0A, INT_SOURCE: 0x02}
#: Registers a host may write (0x1D-0x2A, 0x2C-0x2F, 0x31, 0x38).
WRITABLE = frozenset([*range(0x1D, 0x2B), 0x2C, 0x2D, 0x2E, 0x2F, 0x31, 0x38])
OFFSET_G_PER_LSB = 0.0156
FIFO_DEPTH = 32


@dataclass(frozen=True)
class ProducedSample:
    """A sample the fake made: its index since Measure, its time and counts."""

    index: int
    t_s: float
    counts: tuple[int, int, int]


class FakeADXL345(FakeRegisterDevice):
    """One emulated ADXL345; ``physics.specific_force_g(t)`` is in its own axes."""

    name = "ADXL345"

    def __init__(
        self,
        physics: PhysicsSource,
        clock: Callable[[], float],
        *,
        i2c_address: int = 0x53,
        devid: int = 0xE5,
        self_test_delta_g: tuple[float, float, float] = (1.9, -1.9, 2.7),
        noise_lsb: float = 0.0,
        seed: int = 0,
        name: str = "ADXL345",
    ):
        super().__init__(clock, seed=seed)
        self.physics = physics
        self.address = i2c_address
        self.devid = devid
        self.self_test_delta_g = np.asarray(self_test_delta_g, dtype=float)
        self.noise_lsb = noise_lsb
        self._noise = random.Random(seed + 7919)
        self.name = name
        self.stuck_counts: tuple[int, int, int] | None = None
        self.data_ready_never = False
        self.produced: deque[ProducedSample] = deque(maxlen=200_000)
        self.reset()

    def reset(self) -> None:
        self.regs = bytearray(0x40)
        for r, v in RESET_VALUES.items():
            self.regs[r] = v
        self._out = bytes(6)  # data registers 0x32..0x37
        self._fifo: deque[bytes] = deque()
        self._data_ready = False
        self._overrun = False
        self._t0 = 0.0  # start of the sample schedule
        self._k = 0  # samples made since _t0
        self._measuring = False

    # time --------------------------------------------------------------------------

    @property
    def rate_hz(self) -> float:
        return 3200.0 / 2 ** (15 - (self.regs[BW_RATE] & 0x0F))

    @property
    def fifo_mode(self) -> int:
        return self.regs[FIFO_CTL] >> 6

    def _restart_schedule(self, now: float) -> None:
        self._t0 = now
        self._k = 0

    def _advance(self, now: float) -> None:
        if not self._measuring or self.data_ready_never:
            return
        period = 1.0 / self.rate_hz
        k_now = math.floor((now - self._t0) / period + 1e-9)
        new = k_now - self._k
        if new <= 0:
            return
        keep = 1 if self.fifo_mode == 0 else FIFO_DEPTH + 1
        if new > keep:
            self._overrun = True
        for k in range(max(self._k + 1, k_now - keep + 1), k_now + 1):
            self._store(self._sample(k, self._t0 + k * period))
        self._k = k_now

    def _store(self, word: bytes) -> None:
        if self.fifo_mode == 0:  # bypass
            if self._data_ready:
                self._overrun = True
            self._out = word
            self._data_ready = True
            return
        if len(self._fifo) >= FIFO_DEPTH:
            self._overrun = True
            if self.fifo_mode == 1:  # FIFO mode stops collecting when full
                return
            self._fifo.popleft()  # stream / trigger keep the newest
        self._fifo.append(word)
        if len(self._fifo) == 1:
            self._out = self._fifo[0]

    # physics -> counts -------------------------------------------------------------

    def format_(self) -> tuple[float, int, bool]:
        """(LSB per g, output bits, left-justified) for the current DATA_FORMAT."""
        fmt = self.regs[DATA_FORMAT]
        rng = fmt & 0x03
        full = bool(fmt & 0x08)
        lsb_per_g = 256.0 if full else 256.0 / (1 << rng)
        bits = 10 + rng if full else 10
        return lsb_per_g, bits, bool(fmt & 0x04)

    def counts_for(self, specific_force_g: np.ndarray) -> tuple[int, int, int]:
        """Counts for a specific force (g) in the current format, offsets, self-test."""
        if self.stuck_counts is not None:
            return self.stuck_counts
        f = np.asarray(specific_force_g, dtype=float)
        if self.regs[DATA_FORMAT] & 0x80:
            f = f + self.self_test_delta_g
        ofs = np.array([self.regs[r] - 256 if self.regs[r] & 0x80 else self.regs[r]
                        for r in (OFSX, OFSY, OFSZ)], dtype=float)
        f = f + ofs * OFFSET_G_PER_LSB
        lsb_per_g, bits, _ = self.format_()
        c = f * lsb_per_g
        if self.noise_lsb:
            c = c + np.array([self._noise.gauss(0.0, self.noise_lsb) for _ in range(3)])
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        c = np.clip(np.rint(c), lo, hi).astype(int)
        return int(c[0]), int(c[1]), int(c[2])

    def _sample(self, k: int, t: float) -> bytes:
        counts = self.counts_for(self.physics.specific_force_g(t))
        self.produced.append(ProducedSample(k, t, counts))
        _, bits, left = self.format_()
        out = bytearray()
        for c in counts:
            word = (c << (16 - bits)) & 0xFFFF if left else c & 0xFFFF
            out += bytes([word & 0xFF, word >> 8])
        return bytes(out)

    # registers ---------------------------------------------------------------------

    def _read(self, register: int) -> int:
        if register == DEVID:
            return self.devid
        if register == INT_SOURCE:
            entries = len(self._fifo) if self.fifo_mode else 0
            ready = bool(self._fifo) if self.fifo_mode else self._data_ready
            watermark = entries >= (self.regs[FIFO_CTL] & 0x1F)
            return (0x80 if ready else 0) | (0x02 if watermark else 0) | (
                0x01 if self._overrun else 0)
        if DATAX0 <= register <= DATAZ1:
            return self._out[register - DATAX0]
        if register == FIFO_STATUS:
            return min(len(self._fifo), FIFO_DEPTH) if self.fifo_mode else 0
        if register < len(self.regs):
            return self.regs[register]
        return 0x00

    def _after_read(self, registers: list[int], now: float) -> None:
        if not any(DATAX0 <= r <= DATAZ1 for r in registers):
            return
        if self.fifo_mode == 0:
            self._data_ready = False
            self._overrun = False
            return
        if self._fifo:
            self._fifo.popleft()
            if self._fifo:
                self._out = self._fifo[0]
        if len(self._fifo) < FIFO_DEPTH:
            self._overrun = False

    def _write(self, register: int, value: int, now: float) -> None:
        if register not in WRITABLE:
            self.violations.append(f"write 0x{value:02X} to read-only/reserved 0x{register:02X}")
            return
        old = self.regs[register]
        self.regs[register] = value
        if register == POWER_CTL:
            measuring = bool(value & 0x08)
            if measuring and not self._measuring:
                self._restart_schedule(now)
            self._measuring = measuring
        elif register == BW_RATE and old != value:
            self._restart_schedule(now)
        elif register == FIFO_CTL and (old >> 6) != (value >> 6):
            self._fifo.clear()
            self._overrun = False
            self._data_ready = False
