"""The accelerometers' own errors (the link accelerometers' and the IMU's): offset, scale,
axes not at right angles, and an offset that drifts with temperature.

Magnitudes (the 1-σ of ``default_sigma``, used as prior and by ``--realistic``) come from
the ADXL345 and MPU-9150 datasheets; each class says where its numbers come from.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.effects.base import SensorEffect, accel_stream
from armfusion.models.effects.shapes import XYZ, AxisOffset, AxisScale, by_sensor_type, diag_batch


class _AccelEffect(SensorEffect):
    target_kind = "accelerometer"

    @property
    def streams(self) -> tuple[str, ...]:
        return (accel_stream(self.arm, self.target),)


class AccelBias(AxisOffset, _AccelEffect):
    name = "accel_bias"
    rank = 40
    key = "bias_g"
    units = "g"
    bound = 0.3
    summary = "constant offset on each accelerometer axis"
    description = (
        "The accelerometer reads a constant extra amount on each axis, even when it is "
        "perfectly still (its '0 g offset'). Typical ADXL345 boards are a few hundredths "
        "of a g off; the error looks like a tilt that changes with the pose.")
    seen_in = ("ADXL345 0 g offset ±35 mg x/y, ±40 mg z typical; MPU-9150 accelerometer "
               "±80 mg x/y, ±150 mg z initial tolerance; MPU-6050 ±50 mg x/y, ±80 mg z (σ taken as half)")

    def default_sigma(self):
        return by_sensor_type(self.arm, self.target, {
            "adxl345": [0.035, 0.035, 0.040], "mpu9150": [0.040, 0.040, 0.075],
            "mpu6050": [0.025, 0.025, 0.040], "default": [0.02] * 3})


class AccelScale(AxisScale, _AccelEffect):
    name = "accel_scale"
    rank = 30
    units = "1 (fraction: 0.01 = reads 1 % more)"
    bound = 0.15
    summary = "sensitivity of each accelerometer axis off by a fraction"
    description = (
        "Each axis turns g into counts with its own sensitivity, a little off the nominal "
        "256 LSB/g: a 1 % error reads 1.01 g for 1 g. It shows as a reading that is "
        "slightly too large (or small) in proportion to what the axis feels.")
    seen_in = ("ADXL345 sensitivity 230-282 LSB/g at ±2 g (about ±1 % typical after trim); "
               "MPU-9150 ±3 % tolerance")

    def default_sigma(self):
        return by_sensor_type(self.arm, self.target, {
            "adxl345": [0.01] * 3, "mpu9150": [0.015] * 3, "mpu6050": [0.015] * 3, "default": [0.01] * 3})


# the article's eq. 4-6: axis k is e_x turned by beta about y, then gamma about z, carried

# onto the nominal axis by the cyclic permutation x -> y -> z -> x
_CYCLE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_CYCLE_POW = (np.eye(3), _CYCLE, _CYCLE @ _CYCLE)


def axis_directions(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensing directions ``M (3, 3)`` (rows) of the three axes for angles ``theta (3, 2)``
    (β, γ per axis), and ``dM/dβ``, ``dM/dγ`` (row k: derivative of row k)."""
    M = np.empty((3, 3))
    dB = np.empty((3, 3))
    dG = np.empty((3, 3))
    for k in range(3):
        b, g = theta[k]
        P = np.array([np.cos(g) * np.cos(b), np.sin(g) * np.cos(b), -np.sin(b)])
        Pb = np.array([-np.cos(g) * np.sin(b), -np.sin(g) * np.sin(b), -np.cos(b)])
        Pg = np.array([-np.sin(g) * np.cos(b), np.cos(g) * np.cos(b), 0.0])
        C = _CYCLE_POW[k]
        M[k], dB[k], dG[k] = C @ P, C @ Pb, C @ Pg
    return M, dB, dG


class AccelAxes(_AccelEffect):
    name = "accel_axes"
    rank = 20
    key = "axis_angles_rad"
    shape = (3, 2)
    units = "rad"
    labels = ("x.beta", "x.gamma", "y.beta", "y.gamma", "z.beta", "z.gamma")
    bound = 0.2
    summary = "accelerometer axes not exactly at right angles (cross-axis sensitivity)"
    description = (
        "The three sensing axes inside the chip are not exactly at right angles to each "
        "other, so each axis also feels a little of what the others feel (cross-axis "
        "sensitivity). Each axis's real direction is given by two small angles, as in the "
        "sensor-calibration article (eq. 4-6): gamma tilts it toward the next axis "
        "(x toward y, y toward z, z toward x), beta away from the one after (x toward -z, "
        "y toward -x, z toward -y).")
    seen_in = "ADXL345 cross-axis sensitivity ±1 %; MPU-9150 ±2 %"

    def default_sigma(self):
        return by_sensor_type(self.arm, self.target, {
            "adxl345": [0.01] * 6, "mpu9150": [0.02] * 6, "mpu6050": [0.02] * 6, "default": [0.01] * 6})

    def apply(self, y, theta, ctx, stream):
        M, _, _ = axis_directions(theta)
        return y @ M.T

    def jac_params(self, y, theta, ctx, stream):
        _, dB, dG = axis_directions(theta)
        N = y.shape[0]
        J = np.zeros((N, 3, 6))
        for k in range(3):
            J[:, k, 2 * k] = y @ dB[k]
            J[:, k, 2 * k + 1] = y @ dG[k]
        return J

    def jac_input(self, y, theta, ctx, stream):
        M, _, _ = axis_directions(theta)
        return np.broadcast_to(M, (y.shape[0], 3, 3))


class TemperatureDrift(_AccelEffect):
    name = "temperature_drift"
    rank = 50
    key = "drift_g_per_c"
    shape = (3,)
    units = "g/°C"
    labels = XYZ
    bound = 0.01
    T_REF_C = 25.0
    summary = "accelerometer offset that changes with temperature"
    description = (
        "The accelerometer's zero point moves as it warms up: each axis reads an extra "
        "amount proportional to how far the temperature is from 25 °C. It shows as a slow "
        "drift over the first minutes after power-up, or between a cold and a warm day.")
    seen_in = ("ADXL345 0 g offset vs temperature ±0.4 mg/°C x/y, ±1.2 mg/°C z; MPU-9150 "
               "±35 mg x/y, ±60 mg z over 0-70 °C (≈ ±0.5 / ±0.9 mg/°C)")

    def default_sigma(self):
        return by_sensor_type(self.arm, self.target, {
            "adxl345": [0.0004, 0.0004, 0.0012], "mpu9150": [0.0005, 0.0005, 0.0009],
            "mpu6050": [0.0005, 0.0005, 0.0009],
            "default": [0.0004] * 3})

    def apply(self, y, theta, ctx, stream):
        dT = ctx.state.temperature_c - self.T_REF_C
        return y + dT[:, None] * theta

    def jac_params(self, y, theta, ctx, stream):
        dT = ctx.state.temperature_c - self.T_REF_C
        return diag_batch(np.broadcast_to(dT[:, None], y.shape))
