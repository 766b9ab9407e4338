"""Where the sensors sit and when they sample: a board turned on its link, the IMU not
parallel to the arm's base, a sensor's lever arm off, samples stamped late.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.effects.base import MountEffect, TimeEffect, accel_stream, device_streams
from armfusion.models.effects.shapes import XYZ, FrameRotation
from armfusion.models.rotations import DEG


class MountRotation(FrameRotation):
    name = "mount_rotation"
    target_kind = "link_accelerometer"
    summary = "accelerometer board turned on its link"
    description = (
        "The accelerometer board is glued or screwed onto its link turned by a degree or "
        "two from where the config says. Its axes then see gravity from a slightly "
        "different direction. The rotation is a small rotation vector about the board's "
        "own x, y, z axes (the real mount is R_LS·exp(ρ)).")
    seen_in = "a board glued 1-3° off"

    @property
    def streams(self):
        return (self.target,)

    def default_sigma(self):
        return np.full(3, 2.0 * DEG)


class BaseMount(FrameRotation):
    name = "base_mount"
    target_kind = "imu"
    summary = "IMU not parallel to the arm's base"
    description = (
        "The IMU sits on the chair and the arm's base on its own bracket: the two are not "
        "exactly parallel, so the tilt the IMU measures is not quite the tilt of the arm's "
        "base. A small rotation vector about the IMU's own axes; it turns the IMU's "
        "accelerometer, gyro and compass together.")
    seen_in = "the thesis found the WMRA not level across the chair's base (ch. 4)"

    @property
    def streams(self):
        return ("imu_acc", "imu_gyro", "imu_mag")

    def default_sigma(self):
        return np.full(3, 1.0 * DEG)


class MotionAcceleration(MountEffect):
    name = "motion_acceleration"
    key = "lever_arm_offset_m"
    shape = (3,)
    units = "m"
    labels = XYZ
    bound = 0.25
    target_kind = "accelerometer"
    summary = "sensor's lever arm off: wrong centripetal and tangential acceleration"
    description = (
        "When the arm swings or the chair turns, an accelerometer feels centripetal and "
        "tangential acceleration in proportion to its distance from the axes that turn. "
        "If the sensor sits a few centimetres from where the config says, those motion "
        "terms come out wrong while standing still is unaffected. The offset is in the "
        "link's axes.")
    seen_in = "arm motion and chair driving; a sensor position measured by eye"

    @property
    def streams(self):
        return (accel_stream(self.arm, self.target),)

    def default_sigma(self):
        return np.full(3, 0.02)

    def apply_mount(self, R_LS, p_LS_m, theta):
        return R_LS, p_LS_m + theta

    def jac_params(self, ctx):
        return ctx.lever_arm_jacobian()[:, ctx.sensor(self.target)]


class TimeOffset(TimeEffect):
    name = "time_offset"
    key = "offset_s"
    shape = (1,)
    units = "s"
    labels = ("offset",)
    bound = 0.25
    target_kind = "device"
    summary = "samples stamped late (or early)"
    description = (
        "The device's samples carry a time stamp a little later than the instant they were "
        "measured (bus latency, a FIFO, buffering in the driver): what is stamped t was "
        "true at t - offset. Invisible while still; while moving it looks like the sensor "
        "lags the others.")
    seen_in = "I2C/SPI latency and FIFO buffering, a few ms"

    @property
    def streams(self):
        return device_streams(self.arm, self.target)

    def default_sigma(self):
        return np.array([0.005])


class TimeDrift(TimeEffect):
    name = "time_drift"
    key = "rate_s_per_s"
    shape = (1,)
    units = "s/s"
    labels = ("rate",)
    bound = 0.01
    target_kind = "device"
    summary = "time offset drifting (the device's clock runs at another rate)"
    description = (
        "The device's time stamps come from a clock that is not disciplined to the encoders' "
        "(another computer, a logger merging two files by time): its offset grows by a fixed "
        "amount every second, what is stamped t was true at t - (offset + rate t), t from the "
        "recording's start. With time_offset, the two are the offset at the start and its "
        "drift; alone, an offset that starts at zero.")
    seen_in = ("two undisciplined clocks (quartz tolerances of 20-100 ppm each) and a logger's "
               "buffered time stamps: a few ms over a minute")

    @property
    def streams(self):
        return device_streams(self.arm, self.target)

    def default_sigma(self):
        # 2e-4: 12 ms over a minute, a few quartz tolerances and a buffered logger's stamps
        return np.array([2e-4])
