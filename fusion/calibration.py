"""A calibrated config's sensor corrections as one typed object (:class:`Calibration`) that
applies itself, and the one naming of effects that identification, tracking and the alarm
share: every name is the effect class's own (:data:`armfusion.models.effects.EFFECTS`), so
a renamed effect renames here too.

Per stream, a calibration holds the affine map its sensor-stage effects make of an ideal
reading, ``y = L y_ideal + c`` (SI units, sensor axes), with the offset's slope per °C
where a ``temperature_drift`` is calibrated, and the map moved by each calibrated element's
σ (the correction's own doubt). :meth:`Calibration.ideal` undoes it at a temperature;
:meth:`Calibration.effects_applied` says which of the config's effects the tracker applies
and which it does not, each with why. Identification makes one
(:func:`armfusion.fusion.identification.correction.startup_correction`); the startup and the
tracker apply it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from armfusion.models.effects import Model
from armfusion.models.effects.library import (
    AccelAxes,
    AccelBias,
    AccelScale,
    Backlash,
    BaseMount,
    EncoderScale,
    GyroBias,
    GyroScale,
    JointOffset,
    LinkCompliance,
    MagArmDisturbance,
    MagHardIron,
    MagSoftIron,
    MotionAcceleration,
    MountRotation,
    TemperatureDrift,
    TimeDrift,
    TimeOffset,
)

AffineMap = tuple[np.ndarray, np.ndarray]
"""``(L, c)``: a stream's calibrated errors as an affine map of the ideal reading,
``y = L y_ideal + c``."""

COMPASS_MAP_EFFECTS = (MagSoftIron.name, MagHardIron.name)
"""The compass effects that are a fixed affine map of its reading (the tracker undoes them)."""
GYRO_MAP_EFFECTS = (GyroScale.name, GyroBias.name)
"""The gyro effects the tracker undoes on its readings. Not ``base_mount``: fitted on a parked
chair it is the rotation that best explains gravity in the IMU accelerometer (it trades
against the base's attitude), and applied to the gyro it turned the chair's yaw rate into
tilt rates (the realistic WMRA's j2 0.042 -> 0.088 deg RMS, within 3 sigma 100 -> 97.4 %)."""

_ACCEL_CORRECTED = "each accelerometer's reading corrected"
APPLIED: dict[str, str] = {
    AccelBias.name: _ACCEL_CORRECTED,
    AccelScale.name: _ACCEL_CORRECTED,
    AccelAxes.name: _ACCEL_CORRECTED,
    MountRotation.name: _ACCEL_CORRECTED,
    TemperatureDrift.name: "each accelerometer's reading corrected at its temperature",
    GyroBias.name: "the gyro's reading corrected; the bias state follows what is left and its drift",
    GyroScale.name: "the gyro's reading corrected",
    MagHardIron.name: "the compass's reading corrected",
    MagSoftIron.name: "the compass's reading corrected",
    MagArmDisturbance.name: "the arm's steel's field at the compass, with the joints' angles",
    JointOffset.name: "the joints' zeros: the startup finds them (relative encoders)",
    LinkCompliance.name: "in the kinematics",
    Backlash.name: "in the kinematics",
    EncoderScale.name: "each encoder's counts per radian",
    MotionAcceleration.name: "each sensor's lever arm",
    TimeOffset.name: "each device read at the instant its samples were true",
    BaseMount.name: "the base IMU's accelerometer corrected",
}
"""The config's effects the tracker applies, and where (the code that reads each is named
by ``effect_blocks`` calls with its name in :mod:`armfusion.fusion.tracking.calibrated`,
``setup`` and ``compass``, and by
:func:`armfusion.fusion.identification.correction.startup_correction`)."""
NOT_APPLIED: dict[str, str] = {
    TimeDrift.name: "the tracker reads each device at its constant time offset; the offset's drift is "
                    "not applied",
}
"""The config's effects the tracker does not apply, and why (a drifting time offset's rate)."""
PARTLY_APPLIED: dict[str, str] = {
    BaseMount.name: ("applied to the IMU's accelerometer, not to its gyro and compass (a parked fit's "
                     "mount is gravity's)"),
}
"""Effects applied in part wherever they are, and what is left out."""
IMU_PARTLY_APPLIED: dict[str, str] = {
    TimeOffset.name: "applied to the IMU's accelerometer, not to its gyro and compass",
}
"""Effects applied in part where their target is the base IMU, and what is left out."""
UNKNOWN_EFFECT = "the tracker has no code for this effect: not applied"


def effects_applied(model: Model | None) -> tuple[list[str], list[str]]:
    """The config's effects the tracker applies (their block names, with a word where only
    in part), and those it does not, each with why: what its notes say. An effect the
    tracker does not know (in none of :data:`APPLIED`, :data:`NOT_APPLIED`) is said not
    applied, never assumed to be."""
    if model is None:
        return [], []
    applied, not_applied = [], []
    imu = model.arm.imu.name if model.arm.imu is not None else None
    for e in model.effects:
        if e.name in IMU_PARTLY_APPLIED and e.target == imu:
            applied.append(f"{e.block_name} ({IMU_PARTLY_APPLIED[e.name]})")
        elif e.name in NOT_APPLIED:
            not_applied.append(f"{e.block_name} ({NOT_APPLIED[e.name]})")
        elif e.name in PARTLY_APPLIED:
            applied.append(f"{e.block_name} ({PARTLY_APPLIED[e.name]})")
        elif e.name in APPLIED:
            applied.append(e.block_name)
        else:
            not_applied.append(f"{e.block_name} ({UNKNOWN_EFFECT})")
    return applied, not_applied


@dataclass(frozen=True)
class Calibration:
    """A calibrated config's sensor corrections, per stream, at a reference temperature.

    ``maps[stream]`` is ``(L, c)``: the stream's sensor-stage effects (an accelerometer's
    mount, axes, scale, bias and temperature drift; the compass's soft and hard iron; the
    IMU gyro's scale and bias) as ``y = L y_ideal + c`` at :attr:`temperature_c`;
    :meth:`ideal` inverts it at any temperature.
    """

    model: Model
    """The config's effects, with their values (joint effects included)."""
    temperature_c: float = 25.0
    """The temperature the maps' offsets ``c`` are at, °C."""
    maps: dict[str, AffineMap] = field(default_factory=dict)
    spread: dict[str, list[AffineMap]] = field(default_factory=dict)
    """Per stream, the map with each calibrated element moved by its σ: how uncertain the
    correction itself is, added to each reading's σ (along the reading's own direction)."""
    spread_given_conventions: dict[str, list[AffineMap]] = field(default_factory=dict)
    """The same, given the calibration's joint-zero conventions (``calibration.
    identified.joint_zero_conventions``: the elements it held to fix a gauge, such as the
    frame accelerometer's bias along a still base's only horizontal joint axis): what is
    uncertain in the correction *relative to* the convention every calibrated joint zero
    and mount was fitted in. A tracker that keeps that convention takes this as the doubt
    of its IMU's corrected reading; the convention's own σ is the absolute zero's, in
    :attr:`spread`."""
    offset_per_c: dict[str, np.ndarray] = field(default_factory=dict)
    """Per stream with a calibrated ``temperature_drift``, how its map's offset ``c`` moves per
    °C (its drift through the linear part of the effects after it): ``dc/dT = L_after θ``."""
    _inverse_T: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "_inverse_T", {s: np.linalg.inv(L).T for s, (L, _) in self.maps.items()})

    @property
    def drifts_with_temperature(self) -> bool:
        """Whether any stream's correction depends on the temperature."""
        return bool(self.offset_per_c)

    def undo_map(self, stream: str) -> AffineMap | None:
        """The map that undoes ``stream``'s calibrated errors at :attr:`temperature_c`,
        ``(A, c)``: the ideal sensor's reading is ``(y - c) @ A`` for readings ``y (N, 3)``
        in SI units; None where the calibration has none."""
        m = self.maps.get(stream)
        return None if m is None else (self._inverse_T[stream], np.asarray(m[1], float))

    def offset(self, stream: str, temperature_c=None) -> np.ndarray:
        """``stream``'s offset ``c`` at ``temperature_c`` (scalar: ``(3,)``; ``(N,)``: ``(N, 3)``;
        None: at :attr:`temperature_c`)."""
        c = np.asarray(self.maps[stream][1], float)
        slope = self.offset_per_c.get(stream)
        if slope is None or temperature_c is None:
            return c
        return c + np.multiply.outer(np.asarray(temperature_c, float) - self.temperature_c, slope)

    def ideal(self, stream: str, y_si: np.ndarray, temperature_c=None) -> np.ndarray:
        """What an ideal sensor on its nominal mount would read for ``stream``'s readings
        ``y_si`` (``(3,)`` or ``(N, 3)``, SI units, sensor axes), the calibrated errors
        undone at ``temperature_c`` (°C, scalar or ``(N,)``; None: at :attr:`temperature_c`).
        A stream without a correction is returned as it is."""
        if stream not in self.maps:
            return y_si
        return (y_si - self.offset(stream, temperature_c)) @ self._inverse_T[stream]

    def effects_applied(self) -> tuple[list[str], list[str]]:
        """The config's effects the tracker applies and those it does not, each with why
        (:func:`effects_applied` of :attr:`model`)."""
        return effects_applied(self.model)
