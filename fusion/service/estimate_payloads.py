"""The estimate's payloads: the joints (:class:`JointState`, on ``state/joints``) and the
heading (:class:`Heading`, on ``state/heading``), each an estimate's record
(:mod:`armfusion.fusion.tracking.estimate`) in an envelope, and their checked decoding."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from armfusion.fusion.service.payload_schema import (
    VERSIONS,
    PayloadError,
    read_field,
    read_finite,
    read_flag,
    read_floats,
    read_sensors,
    read_strings,
)
from armfusion.fusion.tracking.estimate import HEADING_STATUS, NORTH, Estimate, heading_record, joints_record
from armfusion.sensors.samples import clipped_repr


@dataclass(frozen=True)
class JointState:
    """One instant's joint estimate: the joints record of an
    :class:`~armfusion.fusion.tracking.estimate.Estimate`."""

    robot: str
    t_s: float
    joint_names: tuple[str, ...]
    q_rad: tuple[float, ...]
    sigma_rad: tuple[float, ...]
    flags: tuple[str, ...]
    sensors: tuple[tuple[str, str], ...] = ()
    """Each sensor's status (``ok``, ``rejecting``, ``stale``, ``stuck``, ``dead``, ``absent``)."""
    axis_to_vertical_deg: tuple[float, ...] | None = None
    """Each joint axis's angle to the vertical (near 0: gimbal lock); ``None``: not sent."""
    combinations: tuple[dict, ...] | None = None
    """What gravity reads where it cannot read single joints (each ``name``,
    ``coefficients``, ``angle_rad``, ``sigma_rad``); ``None``: not sent (an optional field
    of version 1: a reader that does not know it ignores it)."""

    @classmethod
    def of(cls, robot: str, e: Estimate) -> JointState:
        return cls(robot, float(e.t_s), tuple(e.joint_names), tuple(float(x) for x in e.q_rad),
                   tuple(float(x) for x in e.sigma_rad), tuple(e.flags), tuple(e.sensors),
                   tuple(float(x) for x in e.axis_to_vertical_deg),
                   tuple(c.as_dict() for c in e.combinations))

    def record(self) -> dict[str, Any]:
        """The joints record (:func:`armfusion.fusion.tracking.estimate.joints_record`): no envelope."""
        return joints_record(self.t_s, self.joint_names, self.q_rad, self.sigma_rad, self.flags,
                             self.sensors, self.axis_to_vertical_deg, self.combinations)

    def to_json(self) -> dict[str, Any]:
        return {"v": VERSIONS["joints"], "type": "joints", "robot": self.robot, **self.record()}


@dataclass(frozen=True)
class Heading:
    """The base's heading (yaw about the vertical), roll and pitch, each with its one-sigma
    uncertainty, the gyro bias and the magnetometer's state: the heading record of an
    :class:`~armfusion.fusion.tracking.estimate.Estimate`."""

    robot: str
    t_s: float
    heading_rad: float
    heading_sigma_rad: float
    roll_rad: float
    roll_sigma_rad: float
    pitch_rad: float
    pitch_sigma_rad: float
    gyro_bias_rad_s: tuple[float, float, float]
    magnetic_disturbance: bool = False
    magnetic_recovery: bool = False
    heading_status: str = "gyro_only"
    true_north: bool = False

    @classmethod
    def of(cls, robot: str, e: Estimate) -> Heading:
        s_roll, s_pitch, s_yaw = (float(x) for x in e.attitude_sigma_rad)
        bias = tuple(float(x) for x in e.gyro_bias_rad_s)
        return cls(robot, float(e.t_s), float(e.heading_rad), s_yaw, float(e.roll_rad), s_roll,
                   float(e.pitch_rad), s_pitch, bias, bool(e.magnetic_disturbance),
                   bool(e.magnetic_recovery), e.heading_status, bool(e.true_north))

    def record(self) -> dict[str, Any]:
        """The heading record (:func:`armfusion.fusion.tracking.estimate.heading_record`): no envelope."""
        return heading_record(self.t_s, (self.roll_rad, self.pitch_rad, self.heading_rad),
                              (self.roll_sigma_rad, self.pitch_sigma_rad, self.heading_sigma_rad),
                              self.gyro_bias_rad_s, self.magnetic_disturbance, self.magnetic_recovery,
                              self.heading_status, self.true_north)

    def to_json(self) -> dict[str, Any]:
        return {"v": VERSIONS["heading"], "type": "heading", "robot": self.robot, **self.record()}


def decode_joints(d: dict, robot: str) -> JointState:
    names = read_strings(d, "joint_names")
    n = len(names)
    axis = read_floats(d, "axis_to_vertical_deg", n) if "axis_to_vertical_deg" in d else None
    return JointState(robot, read_finite(d, "t_s"), names, read_floats(d, "q_rad", n),
                      read_floats(d, "sigma_rad", n), read_strings(d, "flags", n), read_sensors(d), axis,
                      _combinations(d) if "combinations" in d else None)


def _combinations(d: dict) -> tuple[dict, ...]:
    """The joints payload's optional ``combinations``: each an object of a ``name``, its
    ``coefficients`` (names to finite numbers), a finite ``angle_rad`` and ``sigma_rad``."""
    items = read_field(d, "combinations", list)
    out = []
    for k, c in enumerate(items):
        if not isinstance(c, dict):
            raise PayloadError("malformed", f"combinations[{k}]: expected an object")
        coef = read_field(c, "coefficients", dict)
        if not all(isinstance(a, str) and isinstance(v, int | float) and not isinstance(v, bool)
                   and math.isfinite(v) for a, v in coef.items()):
            raise PayloadError("malformed",
                               f"combinations[{k}].coefficients: expected names to finite numbers")
        out.append({"name": read_field(c, "name", str),
                    "coefficients": {a: float(v) for a, v in coef.items()},
                    "angle_rad": read_finite(c, "angle_rad"), "sigma_rad": read_finite(c, "sigma_rad")})
    return tuple(out)


def decode_heading(d: dict, robot: str) -> Heading:
    bias = read_floats(d, "gyro_bias_rad_s", 3)
    if not all(math.isfinite(b) for b in bias):
        raise PayloadError("malformed", "field 'gyro_bias_rad_s' is not finite")
    status = read_field(d, "heading_status", str)
    if status not in HEADING_STATUS:
        raise PayloadError("malformed", f"heading_status {clipped_repr(status)}: expected one of "
                                        f"{', '.join(HEADING_STATUS)}")
    north = read_field(d, "north", str)
    if north not in NORTH:
        raise PayloadError("malformed", f"north {clipped_repr(north)}: expected one of {', '.join(NORTH)}")
    read_finite(d, "yaw_enu_rad")  # (derived from heading_rad: checked, not kept)
    read_finite(d, "yaw_enu_variance_rad2")
    return Heading(robot, read_finite(d, "t_s"), read_finite(d, "heading_rad"),
                   read_finite(d, "heading_sigma_rad"),
                   read_finite(d, "roll_rad"), read_finite(d, "roll_sigma_rad"), read_finite(d, "pitch_rad"),
                   read_finite(d, "pitch_sigma_rad"), bias, read_flag(d, "magnetic_disturbance"),
                   read_flag(d, "magnetic_recovery"), status, north == "true")
