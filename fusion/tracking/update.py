"""The records one instant travels through the filter in (see docs/architecture.md, the
tracker's pipeline): :class:`InstantReadings` (what the instant's samples are once admitted,
in SI units and base axes) goes in; :class:`UpdateResult` (the stacked measurement, its
innovation, the gate's and the listeners' verdicts) is what the update's readers (health,
the slip detector, the recalibration alarm, the compass, the observability) take and fill
before the correction applies it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.measurement import AccelReadings, Stack
from armfusion.fusion.tracking.ukf_groups import GroupPlan, Innovation


class MagReading(NamedTuple):
    """One magnetometer sample, admitted."""

    counts: np.ndarray
    """``(3,)`` as the device gave them."""
    field_B_ut: np.ndarray
    """``(3,)`` µT in the base's axes, the config's corrections applied."""


class InstantReadings(NamedTuple):
    """One instant's admitted samples; any None where its sensor has no sample here."""

    q_enc_rad: np.ndarray | None
    """``(n,)`` the encoders' angles (counts / counts per radian)."""
    gyro_B_rad_s: np.ndarray | None
    """``(3,)`` the gyro, base axes."""
    accel: AccelReadings | None
    mag: MagReading | None


@dataclass(slots=True)
class UpdateResult:
    """One update, as its stages fill it: stacked (:meth:`armfusion.fusion.tracking.measurement.Measurements.stack`),
    innovated, gated, then read by the listeners, which set ``accept`` and ``mask``, and
    finally applied (``BatchedUKF.correct(inn, accept, hold, mask)``)."""

    t: float
    frame: Frames | None
    stack: Stack
    k: int
    """The number of accelerometers in the update (their rows come first, 3 each)."""
    still: bool
    """Whether the still chair's zero acceleration is a group of it."""
    plan: GroupPlan
    angle_rows: tuple[int, ...]
    heading_shift_rad: float
    omega_B: np.ndarray | None
    """The base's turn rate for a pivot's acceleration (None: no pivot)."""
    m_B: np.ndarray | None
    """The compass's mean field in base axes (None: no heading row)."""
    mag: tuple | None
    """The compass's ``(count, field, extra variance)`` (None: no heading row)."""
    check: Any = None
    """The compass's field check (:meth:`armfusion.fusion.tracking.compass.Compass.variance`)."""
    inn: Innovation | None = None
    gate: list = field(default_factory=list)
    """Each group's first verdict against its gate."""
    accept: np.ndarray | None = None
    """Each group: applied or not (the gate's, then the listeners' verdicts)."""
    set_off: bool = False
    """The base set off while it was held still: its acceleration was freed, the update innovated again."""
    calm: bool = False
    """The base behaves as modelled (the slip detector and the alarm listen only then)."""
    mask: np.ndarray | None = None
    """The gain mask (the heading's row corrects only the heading's states)."""
