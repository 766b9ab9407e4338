"""The ADXL345's register map, its settings and the data sheet's tables, and the decoding of
its data registers (ADXL345 data sheet, Rev. E): what :mod:`armfusion.sensors.adxl345`'s
driver writes and reads. (The fake device, :mod:`armfusion.sensors.fakes.adxl345`, keeps its
own copy of the register map: a driver test then checks the driver against the data sheet,
not against itself.)

Register map (ADXL345 data sheet, Rev. E, Table 19) used here::

    0x00 DEVID        R   0xE5
    0x1E-0x20 OFSX/Y/Z R/W offsets, 15.6 mg/LSB (zeroed at init: counts stay raw)
    0x2C BW_RATE      R/W reset 0x0A: bit 4 LOW_POWER, bits 3:0 rate code
    0x2D POWER_CTL    R/W reset 0x00: bit 3 Measure
    0x30 INT_SOURCE   R   bit 7 DATA_READY, bit 1 Watermark, bit 0 Overrun
    0x31 DATA_FORMAT  R/W reset 0x00: bit 7 SELF_TEST, bit 6 SPI (3-wire), bit 3
                          FULL_RES, bit 2 Justify, bits 1:0 range (±2/4/8/16 g)
    0x32-0x37 DATAX0..DATAZ1  R  little-endian two's complement
    0x38 FIFO_CTL     R/W bits 7:6 mode (bypass/FIFO/stream/trigger), 4:0 samples
    0x39 FIFO_STATUS  R   bits 5:0 entries
"""

from __future__ import annotations

from dataclasses import dataclass

from armfusion.sensors.bus import s16_le

# registers
DEVID = 0x00
OFSX, OFSY, OFSZ = 0x1E, 0x1F, 0x20
BW_RATE = 0x2C
POWER_CTL = 0x2D
INT_ENABLE = 0x2E
INT_SOURCE = 0x30
DATA_FORMAT = 0x31
DATAX0 = 0x32
FIFO_CTL = 0x38
FIFO_STATUS = 0x39

DEVID_VALUE = 0xE5
I2C_ADDRESS = 0x53  # ALT ADDRESS (SDO) low
I2C_ADDRESS_ALT = 0x1D  # ALT ADDRESS (SDO) high
SPI_MODE = 3  # CPOL = 1, CPHA = 1
SPI_MAX_SPEED_HZ = 5_000_000  # data sheet limit
SPI_DEFAULT_SPEED_HZ = 1_000_000  # the thesis's rig: cables up the arm, 8 bytes take 72 µs
SPI_READ = 0x80
SPI_MULTI = 0x40

# bits
MEASURE = 0x08
SELF_TEST = 0x80
FULL_RES = 0x08
LOW_POWER = 0x10
DATA_READY = 0x80
WATERMARK = 0x02
OVERRUN = 0x01
FIFO_BYPASS = 0x00
FIFO_STREAM = 0x80
FIFO_DEPTH = 32

RANGE_BITS = {2: 0b00, 4: 0b01, 8: 0b10, 16: 0b11}

#: Self-test output change, LSB at 3.9 mg/LSB, VS = 2.5 V (data sheet Table 15:
#: ±2 g 10-bit or any full-resolution range): (min, max) per axis.
SELF_TEST_LIMITS_2V5_LSB = ((50.0, 540.0), (-540.0, -50.0), (75.0, 875.0))
#: Data sheet Table 14: scale factors of the self-test change (X/Y, Z) per supply.
SELF_TEST_SUPPLY_SCALE = {2.0: (0.64, 0.8), 2.5: (1.0, 1.0), 3.3: (1.77, 1.47), 3.6: (2.11, 1.69)}


#: Data sheet Table 7: output data rate (Hz, as printed) -> BW_RATE rate code.
#: The device's actual rate is 3200 Hz / 2**(15 - code) (0.1 Hz is 0.098 Hz).
RATE_CODES = {3200: 0x0F, 1600: 0x0E, 800: 0x0D, 400: 0x0C, 200: 0x0B, 100: 0x0A, 50: 0x09,
              25: 0x08, 12.5: 0x07, 6.25: 0x06, 3.13: 0x05, 1.56: 0x04, 0.78: 0x03,
              0.39: 0x02, 0.2: 0x01, 0.1: 0x00}


def rate_code(rate_hz: float) -> int:
    """BW_RATE rate code for a data sheet output data rate."""
    if rate_hz not in RATE_CODES:
        allowed = ", ".join(f"{r:g}" for r in RATE_CODES)
        raise ValueError(f"ADXL345 output data rate {rate_hz!r} Hz is not one of {allowed}")
    return RATE_CODES[rate_hz]


def self_test_limits_lsb(supply_v: float) -> tuple[tuple[float, float], ...]:
    """(min, max) self-test change per axis in LSB (3.9 mg/LSB) for a supply voltage."""
    if supply_v not in SELF_TEST_SUPPLY_SCALE:
        raise ValueError(
            f"self-test limits are tabulated for VS in {sorted(SELF_TEST_SUPPLY_SCALE)} V, "
            f"not {supply_v!r}"
        )
    sxy, sz = SELF_TEST_SUPPLY_SCALE[supply_v]
    scales = (sxy, sxy, sz)
    return tuple((lo * s, hi * s) for (lo, hi), s in zip(SELF_TEST_LIMITS_2V5_LSB, scales, strict=True))


@dataclass(frozen=True)
class ADXL345Config:
    """What init writes. Defaults: ±2 g, 10-bit (256 LSB/g nominal), 100 Hz, no FIFO."""

    range_g: int = 2
    full_resolution: bool = False
    rate_hz: float = 100.0
    fifo: bool = False  # stream mode, read with read_fifo()
    fifo_watermark: int = 16  # FIFO_CTL samples bits (only the watermark flag uses it)
    supply_v: float = 3.3  # VS, chooses the self-test limits
    stale_timeout_s: float | None = None  # no new data for this long -> NOT_READY

    def __post_init__(self) -> None:
        if self.range_g not in RANGE_BITS:
            raise ValueError(f"ADXL345 range_g must be one of 2, 4, 8, 16, not {self.range_g!r}")
        rate_code(self.rate_hz)
        if not 0 <= self.fifo_watermark <= 31:
            raise ValueError(f"fifo_watermark must be 0..31, not {self.fifo_watermark}")
        self_test_limits_lsb(self.supply_v)

    @property
    def bw_rate(self) -> int:
        return rate_code(self.rate_hz)

    @property
    def data_format(self) -> int:
        return (FULL_RES if self.full_resolution else 0) | RANGE_BITS[self.range_g]

    @property
    def fifo_ctl(self) -> int:
        return (FIFO_STREAM | self.fifo_watermark) if self.fifo else FIFO_BYPASS

    @property
    def output_rate_hz(self) -> float:
        """The device's actual output data rate, 3200 Hz / 2**(15 - code)."""
        return 3200.0 / 2 ** (15 - self.bw_rate)

    @property
    def lsb_per_g(self) -> float:
        """Nominal sensitivity: 256 LSB/g in full resolution or ±2 g 10-bit."""
        return 256.0 if self.full_resolution else 256.0 * 2 / self.range_g

    @property
    def count_limits(self) -> tuple[int, int]:
        """Output range in counts (10-bit, or 10..13 bits in full resolution)."""
        bits = 10 + (RANGE_BITS[self.range_g] if self.full_resolution else 0)
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1

    @property
    def stale_timeout(self) -> float:
        if self.stale_timeout_s is not None:
            return self.stale_timeout_s
        return 10.0 / self.output_rate_hz + 0.05


DEFAULT_CONFIG = ADXL345Config()
"""±2 g, 10-bit, 100 Hz, no FIFO, a 3.3 V supply."""


def xyz_counts(raw: bytes | list[int], start: int = 0) -> tuple[int, int, int]:
    """X, Y, Z counts from the six data-register bytes at ``raw[start:start + 6]`` (DATAX0..
    DATAZ1: little-endian two's complement)."""
    return (s16_le(raw[start], raw[start + 1]), s16_le(raw[start + 2], raw[start + 3]),
            s16_le(raw[start + 4], raw[start + 5]))


def self_test_verdict(where: str, supply_v: float, limits: tuple[tuple[float, float], ...],
                      delta_lsb: tuple[float, ...]) -> tuple[bool, str]:
    """Whether a self-test's output change ``delta_lsb`` (x, y, z) is within ``limits``, and
    the line that says so (each axis outside named with its limits)."""
    bad = [
        f"{ax} change {d:+.1f} LSB outside [{lo:.1f}, {hi:.1f}]"
        for ax, d, (lo, hi) in zip("xyz", delta_lsb, limits, strict=True)
        if not lo <= d <= hi
    ]
    if bad:
        return False, f"ADXL345 on {where}: self-test FAILED (VS = {supply_v} V limits): " + "; ".join(bad)
    return True, (f"ADXL345 on {where}: self-test passed, change "
                  + ", ".join(f"{ax} {d:+.1f}" for ax, d in zip("xyz", delta_lsb, strict=True))
                  + f" LSB (VS = {supply_v} V limits)")
