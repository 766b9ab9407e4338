"""What the nodes say of themselves and answer: a node's :class:`Status`, the fusion node's
reply to a calibration request (:class:`Calibration`), its model-change alarms
(:class:`Health`) and the planned maneuver it serves (:class:`Maneuver`); and their checked
decoding."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from armfusion.fusion.service.payload_schema import (
    NAME_RE,
    VERSIONS,
    PayloadError,
    read_field,
    read_finite,
    read_optional_finite,
    read_optional_floats,
    read_sensors,
    read_strings,
)
from armfusion.fusion.tracking.alarm import EFFECTS as ALARM_EFFECTS
from armfusion.fusion.tracking.alarm import UNITS as ALARM_UNITS
from armfusion.models.trajectories.planned import PlannedManeuver
from armfusion.sensors.samples import clipped_repr

NODE_STATES = ("starting", "running", "calibrating", "tracking", "done", "stopping", "error")


@dataclass(frozen=True)
class Status:
    """A node's health: its state, a line for a person, and its counters."""

    robot: str
    node: str
    state: str
    t_wall_s: float
    message: str = ""
    counters: tuple[tuple[str, int], ...] = ()
    sensors: tuple[tuple[str, str], ...] = ()
    """The fusion node's sensor statuses, as in
    :class:`~armfusion.fusion.service.estimate_payloads.JointState` (other nodes: none)."""

    def to_json(self) -> dict[str, Any]:
        return {"v": VERSIONS["status"], "type": "status", "robot": self.robot, "node": self.node,
                "state": self.state, "t_wall_s": self.t_wall_s, "message": self.message,
                "counters": dict(self.counters), "sensors": dict(self.sensors)}


@dataclass(frozen=True)
class Calibration:
    """The fusion node's reply on ``armfusion/<robot>/calibrate``.

    ``ok``: the startup calibration ran on the still stretch ``t_start_s``-``t_end_s`` and
    the tracker restarted from it; ``message`` is its summary. Otherwise ``message`` says why
    it was refused (the arm moves, no still stretch yet, no samples) and the other fields
    are empty. ``q_rad`` and ``sigma_rad`` are ``None`` (JSON ``null``) for a joint gravity
    cannot read (``gimbal_lock``, ``ambiguous``).
    """

    robot: str
    ok: bool
    message: str
    t_start_s: float | None = None
    t_end_s: float | None = None
    joint_names: tuple[str, ...] = ()
    q_rad: tuple[float | None, ...] = ()
    sigma_rad: tuple[float | None, ...] = ()
    flags: tuple[str, ...] = ()
    roll_rad: float | None = None
    pitch_rad: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {"v": VERSIONS["calibration"], "type": "calibration", "robot": self.robot, "ok": self.ok,
                "message": self.message, "t_start_s": self.t_start_s, "t_end_s": self.t_end_s,
                "joint_names": list(self.joint_names), "q_rad": list(self.q_rad),
                "sigma_rad": list(self.sigma_rad), "flags": list(self.flags),
                "roll_rad": self.roll_rad, "pitch_rad": self.pitch_rad}


MAX_ALARMS = 64
"""More alarms than this in one health payload is refused (a node raises a handful)."""


@dataclass(frozen=True)
class Health:
    """The fusion node's model-change alarms on ``armfusion/<robot>/health``: each active
    alarm (not cleared by a recalibration) as ``(sensor, effect, size, sigma, unit, since_s,
    raised_s, candidates)``: ``effect`` one of :data:`ALARM_EFFECTS`, ``size`` and its
    1-sigma in ``unit`` (deg, g, uT by effect), ``since_s`` when the change began and
    ``raised_s`` when the alarm was raised (the tracker's clock, the samples' time stamps),
    ``candidates`` the effects not yet told apart (``effect``, the likelier, first;
    ``(effect,)`` once decided; optional on the wire, absent meaning decided); ``t_s`` the
    tracker's time when sent."""

    robot: str
    t_s: float
    alarms: tuple[tuple[str, str, float, float, str, float, float, tuple[str, ...]], ...] = ()

    @classmethod
    def of(cls, robot: str, t_s: float, alarms) -> Health:
        """From :class:`armfusion.fusion.tracking.alarm.Alarm` objects."""
        return cls(robot, float(t_s), tuple((a.sensor, a.effect, float(a.size), float(a.sigma), a.unit,
                                             float(a.since_s), float(a.raised_s), tuple(a.candidates))
                                            for a in alarms))

    def to_json(self) -> dict[str, Any]:
        keys = ("sensor", "effect", "size", "sigma", "unit", "since_s", "raised_s")
        return {"v": VERSIONS["health"], "type": "health", "robot": self.robot, "t_s": self.t_s,
                "alarms": [{**dict(zip(keys, a[:7], strict=True)), "candidates": list(a[7])}
                           for a in self.alarms]}


MANEUVER_STATES = ("ready", "recording", "fitting", "calibrated", "applied", "failed")
"""A served maneuver's run: ``ready`` (the plan waits for the controller), ``recording`` (the
node keeps every accepted sample from the ``start`` request on), ``fitting`` (``done``: the
sensor fit runs on them), ``calibrated`` (a config written), ``applied`` (the node tracks
with it, after ``apply``) or ``failed`` (the message says why; ``start`` begins again)."""


@dataclass(frozen=True)
class Maneuver:
    """The planned self-calibration maneuver as the fusion node serves it, on
    ``armfusion/<robot>/maneuver`` (published when its state changes, and the reply to a query
    there or on ``maneuver/start``, ``/done``, ``/abort``, ``/apply``).

    ``plan``: what the arm's controller plays (the maneuver file's content: joint names, and
    per pose its angles in degrees, the move's and the dwell's seconds); ``accepted``: whether
    the request this replies to was done (a refusal says why in ``message``); ``t_start_s``,
    ``t_end_s``: the samples kept (sample time; ``None`` before); ``poses_reached``: how many
    of the plan's poses the encoders saw held (``None`` before the run ended); ``recording``,
    ``config``: the kept samples' file and the calibrated config's, on the node's machine
    (empty until written)."""

    robot: str
    state: str
    accepted: bool
    message: str
    plan: PlannedManeuver
    t_start_s: float | None = None
    t_end_s: float | None = None
    poses_reached: int | None = None
    recording: str = ""
    config: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"v": VERSIONS["maneuver"], "type": "maneuver", "robot": self.robot, "state": self.state,
                "accepted": self.accepted, "message": self.message, "plan": self.plan.as_dict(),
                "duration_s": round(self.plan.duration_s, 4), "t_start_s": self.t_start_s,
                "t_end_s": self.t_end_s, "poses_reached": self.poses_reached,
                "recording": self.recording, "config": self.config}


def decode_status(d: dict, robot: str) -> Status:
    state = read_field(d, "state", str)
    if state not in NODE_STATES:
        raise PayloadError("malformed", f"state {state!r}: expected one of {', '.join(NODE_STATES)}")
    counters = read_field(d, "counters", dict)
    if not all(isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool)
               for k, v in counters.items()):
        raise PayloadError("malformed", "field 'counters': expected names to integers")
    return Status(robot, read_field(d, "node", str), state, read_finite(d, "t_wall_s"),
                  read_field(d, "message", str), tuple(sorted(counters.items())), read_sensors(d))


def decode_calibration(d: dict, robot: str) -> Calibration:
    names = read_strings(d, "joint_names")
    n = len(names)
    return Calibration(robot, read_field(d, "ok", bool), read_field(d, "message", str),
                       read_optional_finite(d, "t_start_s"), read_optional_finite(d, "t_end_s"), names,
                       read_optional_floats(d, "q_rad", n), read_optional_floats(d, "sigma_rad", n),
                       read_strings(d, "flags", n), read_optional_finite(d, "roll_rad"),
                       read_optional_finite(d, "pitch_rad"))


def decode_health(d: dict, robot: str) -> Health:
    alarms = read_field(d, "alarms", list)
    if len(alarms) > MAX_ALARMS:
        raise PayloadError("malformed", f"field 'alarms': {len(alarms)} alarms, at most {MAX_ALARMS}")
    out = []
    for i, a in enumerate(alarms):
        if not isinstance(a, dict):
            raise PayloadError("malformed", f"alarm {i}: a JSON {type(a).__name__}, not an object")
        sensor = read_field(a, "sensor", str)
        if not NAME_RE.match(sensor):
            raise PayloadError("malformed", f"alarm {i}: sensor {clipped_repr(sensor)}: use 1 to 64 letters, "
                               "digits, '_' or '-'")
        effect = read_field(a, "effect", str)
        if effect not in ALARM_EFFECTS:
            raise PayloadError("malformed", f"alarm {i}: effect {clipped_repr(effect)}: expected one of "
                               f"{', '.join(ALARM_EFFECTS)}")
        unit = read_field(a, "unit", str)
        if unit != ALARM_UNITS[effect]:
            raise PayloadError("malformed", f"alarm {i}: unit {clipped_repr(unit)} for {effect}: expected "
                               f"{ALARM_UNITS[effect]!r}")
        size, sigma = read_finite(a, "size"), read_finite(a, "sigma")
        if size < 0 or sigma < 0:
            raise PayloadError("malformed", f"alarm {i}: a negative size or sigma")
        cands = tuple(read_strings(a, "candidates")) if "candidates" in a else (effect,)
        if not 1 <= len(cands) <= len(ALARM_EFFECTS) or cands[0] != effect or \
                len(set(cands)) != len(cands) or not set(cands) <= set(ALARM_EFFECTS):
            raise PayloadError("malformed", f"alarm {i}: candidates {clipped_repr(list(cands))}: the effect "
                               f"first, then others of {', '.join(ALARM_EFFECTS)}, each once")
        out.append((sensor, effect, size, sigma, unit, read_finite(a, "since_s"), read_finite(a, "raised_s"),
                    cands))
    return Health(robot, read_finite(d, "t_s"), tuple(out))


def decode_maneuver(d: dict, robot: str) -> Maneuver:
    state = read_field(d, "state", str)
    if state not in MANEUVER_STATES:
        raise PayloadError("malformed", f"field 'state': {clipped_repr(state)}, expected one of "
                           f"{', '.join(MANEUVER_STATES)}")
    try:
        plan = PlannedManeuver.from_dict(read_field(d, "plan", dict), "field 'plan'")
    except ValueError as e:
        raise PayloadError("malformed", str(e)[:300]) from None
    reached = d.get("poses_reached")
    if reached is not None and (isinstance(reached, bool) or not isinstance(reached, int)
                                or not 0 <= reached <= len(plan.poses_rad)):
        raise PayloadError("malformed", f"field 'poses_reached': {clipped_repr(reached)}, expected null or "
                           f"a count of at most the plan's {len(plan.poses_rad)} poses")
    return Maneuver(robot, state, read_field(d, "accepted", bool), read_field(d, "message", str), plan,
                    read_optional_finite(d, "t_start_s"), read_optional_finite(d, "t_end_s"), reached,
                    read_field(d, "recording", str), read_field(d, "config", str))
