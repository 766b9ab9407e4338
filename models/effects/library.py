"""The library of physical effects: what makes a real arm and its sensors differ from the
config, each as a small object with one parameter block, a vectorised ``apply`` and its
analytic Jacobians. Units are in the parameter keys; every identity is zero.

The effects live by family: :mod:`armfusion.models.effects.accelerometer` (the accelerometers' own
errors), :mod:`armfusion.models.effects.frames` (where sensors sit, when they sample),
:mod:`armfusion.models.effects.joints`, :mod:`armfusion.models.effects.imu` (gyro, magnetometer, the arm's
disturbance of the compass); the shapes several share (an offset, a scale error, a frame
rotation) are :mod:`armfusion.models.effects.shapes`. This module is their one list: a new effect is
added to :data:`EFFECT_CLASSES`.

Magnitudes (the 1-σ of ``default_sigma``, used as prior and by ``--realistic``) come from
the datasheets where they give them (ADXL345, MPU-9150, AK8975), else from what such
arms show; each class says where its numbers come from.
"""

from __future__ import annotations

from armfusion.models.effects.accelerometer import (
    AccelAxes,
    AccelBias,
    AccelScale,
    TemperatureDrift,
    axis_directions,
)
from armfusion.models.effects.frames import (
    BaseMount,
    MotionAcceleration,
    MountRotation,
    TimeDrift,
    TimeOffset,
)
from armfusion.models.effects.imu import (
    MU0_OVER_4PI_UT_M3_PER_AM2,
    GyroBias,
    GyroScale,
    MagArmDisturbance,
    MagHardIron,
    MagSoftIron,
    dipole_field,
    soft_iron_matrix,
)
from armfusion.models.effects.joints import Backlash, EncoderScale, JointOffset, LinkCompliance

EFFECT_CLASSES = (
    AccelBias, AccelScale, AccelAxes, MountRotation, JointOffset, BaseMount, LinkCompliance,
    MotionAcceleration, TimeOffset, TimeDrift, EncoderScale, Backlash, GyroBias, GyroScale, MagHardIron,
    MagSoftIron, MagArmDisturbance, TemperatureDrift,
)
EFFECTS: dict[str, type] = {c.name: c for c in EFFECT_CLASSES}
"""Every effect of the library, by name."""

__all__ = [
    "EFFECTS", "EFFECT_CLASSES", "MU0_OVER_4PI_UT_M3_PER_AM2", "AccelAxes", "AccelBias", "AccelScale",
    "Backlash", "BaseMount", "EncoderScale", "GyroBias", "GyroScale", "JointOffset", "LinkCompliance",
    "MagArmDisturbance", "MagHardIron", "MagSoftIron", "MotionAcceleration", "MountRotation",
    "TemperatureDrift", "TimeDrift", "TimeOffset", "axis_directions", "dipole_field", "soft_iron_matrix",
]
