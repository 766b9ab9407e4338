"""What the tracker gives for one instant (:class:`Estimate`) and its one wire form.

An estimate goes out as two JSON records, with the unit in every field's name:

- the **joints record** (:func:`joints_record`): ``t_s``, ``joint_names``, ``q_rad``,
  ``sigma_rad``, ``flags``, ``sensors`` and, where known, ``axis_to_vertical_deg`` and
  ``combinations`` (what gravity reads where it cannot read single joints: each a ``name``
  such as ``"shoulder + elbow"``, its ``coefficients`` by joint name (or ``base roll``,
  ``base pitch``), ``angle_rad`` and ``sigma_rad``; :mod:`armfusion.fusion.startup.combinations`);
- the **heading record** (:func:`heading_record`): ``t_s``, ``heading_rad`` (yaw of the base
  about the vertical, counter-clockwise seen from above, from north: 0 facing north, +pi/2
  facing west), ``heading_sigma_rad``, ``roll_rad``, ``roll_sigma_rad``, ``pitch_rad``,
  ``pitch_sigma_rad``, ``gyro_bias_rad_s``, ``magnetic_disturbance``, ``magnetic_recovery``,
  ``heading_status`` (:data:`HEADING_STATUS`), ``north`` (``true`` where the config gives the
  site's declination, else ``magnetic``), and the same heading in the convention of robot
  localisation stacks (REP 103's ENU: yaw counter-clockwise from east),
  ``yaw_enu_rad`` (in (-pi, pi]) and ``yaw_enu_variance_rad2``.

Every writer of an estimate uses these two functions: :meth:`Estimate.as_dict` (both records
in one object: ``armfusion track --json``), the Zenoh payloads on ``state/joints`` and
``state/heading`` (:mod:`armfusion.fusion.service.payloads` adds its envelope ``v``, ``type``,
``robot``), and the MCAP topics :data:`JOINTS_TOPIC` and :data:`HEADING_TOPIC`
(:func:`write_mcap_record`: ``armfusion record``, ``armfusion track --out EST.mcap``; each
channel carries the record's JSON schema). docs/reference/service.md describes them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

JOINTS_TOPIC = "estimates/joints"
HEADING_TOPIC = "estimates/heading"
"""The MCAP topics of the two records (JSON messages, one per estimate)."""
JOINTS_SCHEMA = "armfusion.JointState"
HEADING_SCHEMA = "armfusion.Heading"
"""The MCAP schema names of the two records."""

_NUMBER = {"type": "number"}
_NUMBERS = {"type": "array", "items": _NUMBER}
JOINTS_JSON_SCHEMA = {
    "title": JOINTS_SCHEMA, "type": "object",
    "required": ["t_s", "joint_names", "q_rad", "sigma_rad", "flags", "sensors"],
    "properties": {"t_s": _NUMBER, "joint_names": {"type": "array", "items": {"type": "string"}},
                   "q_rad": _NUMBERS, "sigma_rad": _NUMBERS,
                   "flags": {"type": "array", "items": {"type": "string"}},
                   "sensors": {"type": "object", "additionalProperties": {"type": "string"}},
                   "axis_to_vertical_deg": _NUMBERS,
                   "combinations": {"type": "array", "items": {
                       "type": "object", "required": ["name", "coefficients", "angle_rad", "sigma_rad"],
                       "properties": {"name": {"type": "string"},
                                      "coefficients": {"type": "object", "additionalProperties": _NUMBER},
                                      "angle_rad": _NUMBER, "sigma_rad": _NUMBER}}}},
}
HEADING_STATUS = ("compass_fused", "gyro_only", "disturbed", "calibrating")
"""The heading's status (:mod:`armfusion.fusion.tracking.compass` sets it): ``compass_fused``, the
compass corrected the heading at its last period; ``gyro_only``, there is no compass (or
no field reference), the gyro carries the heading; ``disturbed``, the field is disturbed
and the compass is not used (the gyro carries the heading, its sigma growing);
``calibrating``, the compass's iron is not yet known well enough to fuse it (turn the
chair, e.g. once on the spot)."""
NORTH = ("magnetic", "true")
HEADING_JSON_SCHEMA = {
    "title": HEADING_SCHEMA, "type": "object",
    "required": ["t_s", "heading_rad", "heading_sigma_rad", "roll_rad", "roll_sigma_rad", "pitch_rad",
                 "pitch_sigma_rad", "gyro_bias_rad_s", "magnetic_disturbance", "magnetic_recovery",
                 "heading_status", "north", "yaw_enu_rad", "yaw_enu_variance_rad2"],
    "properties": {"t_s": _NUMBER, "heading_rad": _NUMBER, "heading_sigma_rad": _NUMBER,
                   "roll_rad": _NUMBER, "roll_sigma_rad": _NUMBER, "pitch_rad": _NUMBER,
                   "pitch_sigma_rad": _NUMBER,
                   "gyro_bias_rad_s": {**_NUMBERS, "minItems": 3, "maxItems": 3},
                   "magnetic_disturbance": {"type": "boolean"}, "magnetic_recovery": {"type": "boolean"},
                   "heading_status": {"enum": list(HEADING_STATUS)}, "north": {"enum": list(NORTH)},
                   "yaw_enu_rad": _NUMBER, "yaw_enu_variance_rad2": _NUMBER},
}
"""The JSON schemas the MCAP channels of the two records carry (for other MCAP readers)."""
MCAP_CHANNELS = {"joints": (JOINTS_TOPIC, JOINTS_SCHEMA, JOINTS_JSON_SCHEMA),
                 "heading": (HEADING_TOPIC, HEADING_SCHEMA, HEADING_JSON_SCHEMA)}
"""Per record: its MCAP topic, schema name and JSON schema."""


def write_mcap_record(mcap, kind: str, record: dict) -> None:
    """Write one record (``kind`` ``joints`` or ``heading``) to an open
    :class:`armfusion.sensors.recording_mcap.McapRecorder`, on its topic with its schema."""
    topic, name, schema = MCAP_CHANNELS[kind]
    mcap.write_json(topic, name, record, t_s=record["t_s"], schema=schema)


def _floats(values: Iterable) -> list[float]:
    return [float(v) for v in values]


def joints_record(t_s: float, joint_names: Iterable[str], q_rad: Iterable[float],
                  sigma_rad: Iterable[float], flags: Iterable[str],
                  sensors: Mapping[str, str] | Iterable[tuple[str, str]],
                  axis_to_vertical_deg: Iterable[float] | None = None,
                  combinations: Iterable[dict] | None = None) -> dict:
    """The joints record: each joint's angle, one-sigma and flag, and each sensor's status.
    ``axis_to_vertical_deg`` (each joint axis's angle to the vertical) and ``combinations``
    (:meth:`armfusion.fusion.startup.combinations.Combination.as_dict` each) only where known."""
    doc = {"t_s": float(t_s), "joint_names": [str(n) for n in joint_names], "q_rad": _floats(q_rad),
           "sigma_rad": _floats(sigma_rad), "flags": [str(f) for f in flags],
           "sensors": {str(k): str(v) for k, v in dict(sensors).items()}}
    if axis_to_vertical_deg is not None:
        doc["axis_to_vertical_deg"] = _floats(axis_to_vertical_deg)
    if combinations is not None:
        doc["combinations"] = [{"name": str(c["name"]),
                                "coefficients": {str(k): float(v) for k, v in c["coefficients"].items()},
                                "angle_rad": float(c["angle_rad"]), "sigma_rad": float(c["sigma_rad"])}
                               for c in combinations]
    return doc


def yaw_enu_rad(heading_rad: float) -> float:
    """A heading (counter-clockwise from north) as ENU yaw (counter-clockwise from east),
    in (-pi, pi]."""
    a = math.remainder(float(heading_rad) + math.pi / 2, 2 * math.pi)
    return math.pi if a == -math.pi else a


def heading_record(t_s: float, rpy_rad: Iterable[float], rpy_sigma_rad: Iterable[float],
                   gyro_bias_rad_s: Iterable[float], magnetic_disturbance: bool,
                   magnetic_recovery: bool, heading_status: str, true_north: bool) -> dict:
    """The heading record: the base's attitude (roll, pitch, heading: yaw about the vertical)
    with each one's one-sigma, the gyro bias, the magnetometer's state, the heading's status
    and north, and the heading as ENU yaw with its variance."""
    roll, pitch, yaw = _floats(rpy_rad)
    s_roll, s_pitch, s_yaw = _floats(rpy_sigma_rad)
    return {"t_s": float(t_s), "heading_rad": yaw, "heading_sigma_rad": s_yaw,
            "roll_rad": roll, "roll_sigma_rad": s_roll, "pitch_rad": pitch, "pitch_sigma_rad": s_pitch,
            "gyro_bias_rad_s": _floats(gyro_bias_rad_s),
            "magnetic_disturbance": bool(magnetic_disturbance), "magnetic_recovery": bool(magnetic_recovery),
            "heading_status": str(heading_status), "north": NORTH[bool(true_north)],
            "yaw_enu_rad": yaw_enu_rad(yaw), "yaw_enu_variance_rad2": s_yaw * s_yaw}


@dataclass(frozen=True)
class Estimate:
    """One instant's estimate: immutable, small, everything a consumer needs."""

    t_s: float
    q_rad: np.ndarray
    sigma_rad: np.ndarray
    flags: tuple[str, ...]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    attitude_sigma_rad: np.ndarray
    gyro_bias_rad_s: np.ndarray
    axis_to_vertical_deg: np.ndarray
    sensors: tuple[tuple[str, str], ...]
    magnetic_disturbance: bool = False
    magnetic_recovery: bool = False
    joint_names: tuple[str, ...] = ()
    heading_status: str = "gyro_only"
    """:data:`HEADING_STATUS`."""
    true_north: bool = False
    """Whether the heading is from true north (the config gave the site's declination)."""
    combinations: tuple = ()
    """What gravity reads where it cannot read single joints
    (:class:`armfusion.fusion.startup.combinations.Combination` s)."""

    @property
    def heading_rad(self) -> float:
        return self.yaw_rad

    @property
    def heading_sigma_rad(self) -> float:
        return float(self.attitude_sigma_rad[2])

    def sensor_status(self, name: str) -> str:
        return dict(self.sensors)[name]

    def summary(self) -> str:
        """One line for a person."""
        bad = [f"{n} {f}" for n, f in zip(self.joint_names, self.flags, strict=True) if f != "ok"]
        sens = [f"{n} {s}" for n, s in self.sensors if s != "ok"]
        worst = float(np.degrees(np.max(self.sigma_rad)))
        text = (f"t={self.t_s:.2f}s heading {np.degrees(self.yaw_rad):.1f}±"
                f"{np.degrees(self.heading_sigma_rad):.2f}°, worst joint sigma {worst:.3f}°")
        if bad:
            text += "; " + ", ".join(bad)
        if self.combinations:
            text += "; known together: " + ", ".join(
                f"{c.name} {math.degrees(c.angle_rad):.1f}±{math.degrees(c.sigma_rad):.2f}°"
                for c in self.combinations)
        if sens:
            text += "; sensors: " + ", ".join(sens)
        if self.magnetic_disturbance:
            text += "; magnetic disturbance"
        return text

    def joints_record(self) -> dict:
        return joints_record(self.t_s, self.joint_names, self.q_rad, self.sigma_rad, self.flags,
                             self.sensors, self.axis_to_vertical_deg,
                             [c.as_dict() for c in self.combinations])

    def heading_record(self) -> dict:
        return heading_record(self.t_s, (self.roll_rad, self.pitch_rad, self.yaw_rad),
                              self.attitude_sigma_rad, self.gyro_bias_rad_s, self.magnetic_disturbance,
                              self.magnetic_recovery, self.heading_status, self.true_north)

    def as_dict(self) -> dict:
        """Both records in one object (they share ``t_s``; no other field name)."""
        return {**self.joints_record(), **self.heading_record()}
