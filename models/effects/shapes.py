"""What several effects of the library share: the parameter shapes a sensor's error takes
(an offset added to every axis, a scale error per axis, a small rotation of the sensor's
axes), each with its value and analytic Jacobians written once, and the small array
helpers the effects use.

An effect of one of these shapes inherits from it and says only what is its own: its
name, target, units, magnitudes and where they come from.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.effects.base import SensorEffect
from armfusion.models.rotations import exp_so3, skew, so3_right_jacobian

XYZ = ("x", "y", "z")


def by_sensor_type(arm: ArmModel, name: str, table: dict[str, list[float]]) -> np.ndarray:
    """``table[type of sensor name]`` (else ``table["default"]``) as an array: a magnitude
    that depends on the device (an ADXL345's against an MPU-9150's)."""
    return np.array(table.get(arm.sensor(name).type, table["default"]), dtype=float)


def eye_batch(N: int, k: int) -> np.ndarray:
    """``N`` identity matrices ``(N, k, k)`` (a read-only view)."""
    return np.broadcast_to(np.eye(k), (N, k, k))


def diag_batch(v: np.ndarray) -> np.ndarray:
    """``(N, k)`` -> ``(N, k, k)`` diagonal matrices."""
    N, k = v.shape
    out = np.zeros((N, k, k))
    idx = np.arange(k)
    out[:, idx, idx] = v
    return out


class AxisOffset(SensorEffect):
    """A constant added to each of the three axes: ``y + θ``."""

    shape = (3,)
    labels = XYZ

    def apply(self, y, theta, ctx, stream):
        return y + theta

    def jac_params(self, y, theta, ctx, stream):
        return eye_batch(y.shape[0], 3)


class AxisScale(SensorEffect):
    """Each axis's sensitivity off by a fraction: ``y (1 + θ)``, per axis."""

    input_is_diagonal = True
    shape = (3,)
    labels = XYZ
    key = "scale_error"

    def apply(self, y, theta, ctx, stream):
        return y * (1.0 + theta)

    def jac_params(self, y, theta, ctx, stream):
        return diag_batch(y)

    def jac_input(self, y, theta, ctx, stream):
        return diag_batch(np.broadcast_to(1.0 + theta, y.shape))


class FrameRotation(SensorEffect):
    """The sensor's axes turned by a small rotation vector ρ about its own axes (the real
    mount is the nominal one times ``exp(ρ)``): it reads ``exp(-ρ) y``."""

    rank = 10
    key = "rotvec_rad"
    shape = (3,)
    units = "rad"
    labels = XYZ
    bound = 0.35

    def apply(self, y, theta, ctx, stream):
        return y @ exp_so3(-theta).T

    def jac_params(self, y, theta, ctx, stream):
        R = exp_so3(-theta)
        Jr = so3_right_jacobian(-theta)
        return R @ skew(y) @ Jr  # (N, 3, 3)

    def jac_input(self, y, theta, ctx, stream):
        return np.broadcast_to(exp_so3(-theta), (y.shape[0], 3, 3))
