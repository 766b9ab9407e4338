"""What armfusion nodes say to each other over Zenoh: key expressions and payloads.

Key expressions (``<robot>`` and ``<sensor>`` are names of letters, digits, ``_``, ``-``)::

    armfusion/<robot>/raw/<sensor>      RawBatch    a batch of one sensor's raw counts
    armfusion/<robot>/state/joints      JointState  joint angles, sigma, flags
    armfusion/<robot>/state/heading     Heading     the base's heading (yaw) and its sigma
    armfusion/<robot>/status            Status      a node's health and counters
    armfusion/<robot>/calibrate         Calibration the fusion node's reply to a calibration request
    armfusion/<robot>/health            Health      the fusion node's model-change alarms
    armfusion/<robot>/maneuver[/<do>]   Maneuver    the planned calibration maneuver: the plan,
                                                    its run (start, done, abort, apply) and fit

Every payload is one UTF-8 JSON object (no pickle, nothing that carries code) with
``"v"``, its type's version (:data:`VERSIONS`: 2 for ``heading``, 1 for the others), and
``"type"``, one of ``raw``, ``joints``, ``heading``, ``status``, ``calibration``, ``health``,
``maneuver``; the fields
of each are those of the dataclasses below and are written out in docs/reference/service.md. The
fields of ``joints`` and ``heading`` are an estimate's one wire form, written by
:mod:`armfusion.fusion.tracking.estimate` (``joints_record``, ``heading_record``). JSON keeps a
float's every bit (Python writes the shortest repr that reads back the same), so a replayed
recording is recorded unchanged.

:func:`decode` checks a payload: larger than :data:`MAX_PAYLOAD_BYTES`, not JSON, of an
unknown version or type, with a missing, mistyped or inconsistent field (or a type that does
not match its key expression) raises :class:`PayloadError`, naming the reason; a receiving
node's :class:`armfusion.fusion.service.inbox.Inbox` counts it by reason and drops it with one log
line, never an exception into the node.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from itertools import chain
from typing import Any

import numpy as np
from armfusion.fusion.tracking.alarm import EFFECTS as ALARM_EFFECTS
from armfusion.fusion.tracking.alarm import UNITS as ALARM_UNITS
from armfusion.fusion.tracking.estimate import HEADING_STATUS, NORTH, Estimate, heading_record, joints_record
from armfusion.models.trajectories.planned import PlannedManeuver
from armfusion.sensors.samples import RAW_KINDS, Stream, clipped_repr

VERSIONS = {"raw": 2, "joints": 1, "heading": 3, "status": 1, "calibration": 1, "health": 1,
            "maneuver": 1}
"""Each payload type's schema version (the one written). ``heading`` 2: ``sigma_rad`` became
``heading_sigma_rad``, and the base's roll and pitch, their sigmas, the gyro bias and
``magnetic_recovery`` came in (the estimate's one wire form); 3: ``heading_status``,
``north``, ``yaw_enu_rad`` and ``yaw_enu_variance_rad2`` came in (a localisation
consumer's fields). ``raw`` 2: ``counts`` became
``values``, which may hold decimals (a sensor whose description declares its values in g,
°/s…, as an imported recording holds them)."""
READ_VERSIONS = {**{k: (v,) for k, v in VERSIONS.items()}, "raw": (1, 2)}
"""The versions this node reads: a version-1 ``raw`` (whole ``counts``) is read as before."""
MAX_PAYLOAD_BYTES = 1 << 20
"""1 MiB: a raw batch of 1 s of a 3-axis sensor at 1 kHz is about 60 kB."""
SEQ_MAX = (1 << 64) - 1
"""The largest batch number (an unsigned 64-bit counter's); a negative one is malformed."""
ROOT = "armfusion"
NAME_RE = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


class PayloadError(ValueError):
    """A payload that is not what the schema says. ``reason`` is a short counter name."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


# --- key expressions ------------------------------------------------------------------------


def check_name(name: str, what: str) -> str:
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise ValueError(f"{what} {name!r}: use 1 to 64 letters, digits, '_' or '-'")
    return name


def raw_key(robot: str, sensor: str) -> str:
    return f"{ROOT}/{check_name(robot, 'robot')}/raw/{check_name(sensor, 'sensor')}"


def raw_keys(robot: str) -> str:
    """The key expression of every raw sensor of ``robot``."""
    return f"{ROOT}/{check_name(robot, 'robot')}/raw/*"


def joints_key(robot: str) -> str:
    return f"{ROOT}/{check_name(robot, 'robot')}/state/joints"


def heading_key(robot: str) -> str:
    return f"{ROOT}/{check_name(robot, 'robot')}/state/heading"


def status_key(robot: str) -> str:
    return f"{ROOT}/{check_name(robot, 'robot')}/status"


def calibrate_key(robot: str) -> str:
    """The fusion node's queryable: a query re-runs the startup calibration (see serve)."""
    return f"{ROOT}/{check_name(robot, 'robot')}/calibrate"


def health_key(robot: str) -> str:
    """The fusion node's model-change alarms (:class:`Health`)."""
    return f"{ROOT}/{check_name(robot, 'robot')}/health"


MANEUVER_ACTIONS = ("start", "done", "abort", "apply")
"""What a query on ``armfusion/<robot>/maneuver/<do>`` asks of the fusion node: begin keeping the
samples (the arm's controller is about to play the plan), end and fit them, drop them, or
track with the config the fit wrote (a person has reviewed it)."""


def maneuver_key(robot: str, action: str | None = None) -> str:
    """The planned maneuver's key (its state, published and answered), or a request's
    (``action`` one of :data:`MANEUVER_ACTIONS`)."""
    base = f"{ROOT}/{check_name(robot, 'robot')}/maneuver"
    if action is None:
        return base
    if action not in MANEUVER_ACTIONS:
        raise ValueError(f"maneuver request {action!r}: expected one of {', '.join(MANEUVER_ACTIONS)}")
    return f"{base}/{action}"


def parse_key(key: str) -> tuple[str, str, str | None]:
    """``(robot, type, sensor)`` of a key expression; raises :class:`PayloadError`."""
    parts = str(key).split("/")
    if len(parts) >= 3 and parts[0] == ROOT and NAME_RE.match(parts[1]):
        robot, rest = parts[1], parts[2:]
        if len(rest) == 2 and rest[0] == "raw" and NAME_RE.match(rest[1]):
            return robot, "raw", rest[1]
        if rest in (["state", "joints"], ["state", "heading"]):
            return robot, rest[1], None
        if rest == ["status"]:
            return robot, "status", None
        if rest == ["calibrate"]:
            return robot, "calibration", None
        if rest == ["health"]:
            return robot, "health", None
        if rest[0] == "maneuver" and (len(rest) == 1 or (len(rest) == 2 and rest[1] in MANEUVER_ACTIONS)):
            return robot, "maneuver", None
    raise PayloadError("bad_key", f"key expression {key!r} is not an armfusion key")


# --- payload types --------------------------------------------------------------------------


@dataclass(frozen=True)
class RawBatch:
    """A batch of one sensor's raw values: ``stream.t_s (N,)``, ``stream.values (N, k)``
    (register counts, or decimals in the unit the sensor's description declares).

    ``seq`` numbers the batches of one sensor from one publisher (0, 1, 2…, at most
    :data:`SEQ_MAX`; a counter may wrap to 0) so that a receiver can count the batches it
    missed.
    """

    robot: str
    stream: Stream
    seq: int

    def to_json(self) -> dict[str, Any]:
        s = self.stream
        return {"v": VERSIONS["raw"], "type": "raw", "robot": self.robot, "sensor": s.name,
                "kind": s.kind, "channels": list(s.channels), "seq": self.seq,
                "t_s": s.t_s.tolist(), "values": s.values.tolist()}


@dataclass(frozen=True)
class JointState:
    """One instant's joint estimate: the joints record of an :class:`~armfusion.fusion.tracking.estimate.Estimate`."""

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
    """The fusion node's sensor statuses, as in :class:`JointState` (other nodes: none)."""

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


Payload = RawBatch | JointState | Heading | Status | Calibration | Health | Maneuver


def encode(payload: Payload) -> bytes:
    """The wire form of ``payload``: compact UTF-8 JSON."""
    data = json.dumps(payload.to_json(), separators=(",", ":"), allow_nan=False).encode()
    if len(data) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"{type(payload).__name__}: {len(data)} bytes is more than "
                         f"{MAX_PAYLOAD_BYTES}; publish smaller batches")
    return data


# --- decoding -------------------------------------------------------------------------------


def _field(d: dict, name: str, types: type | tuple[type, ...]) -> Any:
    if name not in d:
        raise PayloadError("malformed", f"missing field {name!r}")
    v = d[name]
    allowed = types if isinstance(types, tuple) else (types,)
    if not isinstance(v, allowed) or (isinstance(v, bool) and bool not in allowed):
        raise PayloadError("malformed", f"field {name!r}: {type(v).__name__} is not the expected type")
    return v


def _finite(d: dict, name: str) -> float:
    v = float(_field(d, name, (int, float)))
    if not math.isfinite(v):
        raise PayloadError("malformed", f"field {name!r} is not finite")
    return v


def _floats(d: dict, name: str, n: int | None = None) -> tuple[float, ...]:
    v = _field(d, name, list)
    if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
        raise PayloadError("malformed", f"field {name!r}: expected a list of numbers")
    if n is not None and len(v) != n:
        raise PayloadError("malformed", f"field {name!r}: {len(v)} values, expected {n}")
    return tuple(float(x) for x in v)


def _strings(d: dict, name: str, n: int | None = None) -> tuple[str, ...]:
    v = _field(d, name, list)
    if not all(isinstance(x, str) for x in v):
        raise PayloadError("malformed", f"field {name!r}: expected a list of strings")
    if n is not None and len(v) != n:
        raise PayloadError("malformed", f"field {name!r}: {len(v)} values, expected {n}")
    return tuple(v)


def _optional_floats(d: dict, name: str, n: int) -> tuple[float | None, ...]:
    v = _field(d, name, list)
    if len(v) != n or not all(x is None or (isinstance(x, int | float) and not isinstance(x, bool)
                                            and math.isfinite(x)) for x in v):
        raise PayloadError("malformed", f"field {name!r}: expected {n} numbers or nulls")
    return tuple(None if x is None else float(x) for x in v)


def _optional_finite(d: dict, name: str) -> float | None:
    return None if d.get(name) is None else _finite(d, name)


def _sensors(d: dict) -> tuple[tuple[str, str], ...]:
    """The optional ``sensors`` field: sensor names to status strings."""
    v = d.get("sensors", {})
    if not isinstance(v, dict) or not all(isinstance(k, str) and isinstance(x, str) for k, x in v.items()):
        raise PayloadError("malformed", "field 'sensors': expected sensor names to status strings")
    return tuple(v.items())


def _raw_plain(d: dict, robot: str) -> RawBatch | None:
    """A raw batch as a driver sends it (names, a batch number in range, finite times, rows
    of whole counts within 64 bits), checked with C-level passes over its lists; ``None``
    when any check fails or the batch holds anything else (decimals, a version-1 payload):
    :func:`_raw` then checks it field by field and says what is wrong. The checks are those
    of :func:`_raw`, and :class:`~armfusion.sensors.samples.Stream`'s still run on the arrays."""
    sensor, kind, channels, seq = d.get("sensor"), d.get("kind"), d.get("channels"), d.get("seq")
    t, rows = d.get("t_s"), d.get("values")
    if not (type(sensor) is str and type(kind) is str and type(channels) is list and type(seq) is int
            and type(t) is list and type(rows) is list and d["v"] != 1 and channels and t
            and len(t) == len(rows) and 0 <= seq <= SEQ_MAX and kind in RAW_KINDS
            and NAME_RE.match(sensor)):
        return None
    n = len(channels)
    try:
        if not (set(map(type, channels)) == {str} and set(map(type, rows)) == {list}
                and set(map(len, rows)) == {n} and set(map(type, t)) <= _NUMBER_TYPES
                and set(map(type, chain.from_iterable(rows))) == {int} and all(map(math.isfinite, t))):
            return None
        stream = Stream(sensor, kind, np.array(t, dtype=np.float64), np.array(rows, dtype=np.int64),
                        tuple(channels))
    except (OverflowError, ValueError):  # (an integer beyond 64 bits, times not increasing…)
        return None
    return RawBatch(robot, stream, seq)


_NUMBER_TYPES = frozenset((int, float))


def _raw(d: dict, robot: str) -> RawBatch:
    plain = _raw_plain(d, robot)
    if plain is not None:
        return plain
    sensor = check_name_or_fail(_field(d, "sensor", str), "sensor")
    kind = _field(d, "kind", str)
    if kind not in RAW_KINDS:
        raise PayloadError("malformed", f"kind {kind!r} is not a raw kind ({', '.join(sorted(RAW_KINDS))})")
    channels = _strings(d, "channels")
    seq = _field(d, "seq", int)
    if not 0 <= seq <= SEQ_MAX:
        raise PayloadError("malformed", f"field 'seq' = {str(seq)[:24]} is not a batch number 0…2⁶⁴ − 1")
    t = _field(d, "t_s", list)
    whole = d["v"] == 1  # version 1: whole register counts only
    name = "counts" if whole else "values"
    rows = _field(d, name, list)
    if not channels or not t or len(t) != len(rows):
        raise PayloadError("malformed", f"{len(t)} times and {len(rows)} rows of {name} "
                           f"over {len(channels)} channels")
    if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in t):
        raise PayloadError("malformed", "field 't_s': expected a list of numbers")
    number = int if whole else (int, float)
    if not all(isinstance(r, list) and len(r) == len(channels)
               and all(isinstance(x, number) and not isinstance(x, bool) for x in r) for r in rows):
        raise PayloadError("malformed", f"field {name!r}: expected rows of {len(channels)} "
                           + ("integers" if whole else "numbers"))
    try:
        t_s = np.asarray(t, dtype=np.float64)
    except OverflowError:  # (an integer beyond any float)
        raise PayloadError("malformed", "field 't_s' is not finite") from None
    if not np.all(np.isfinite(t_s)):
        raise PayloadError("malformed", "field 't_s' is not finite")
    try:
        values = np.asarray(rows, dtype=np.int64 if whole else None)
        stream = Stream(sensor, kind, t_s, values, channels)
    except (ValueError, OverflowError) as e:
        raise PayloadError("malformed", str(e)) from e
    return RawBatch(robot, stream, seq)


def check_name_or_fail(name: str, what: str) -> str:
    if not NAME_RE.match(name):
        raise PayloadError("malformed", f"{what} {name!r} is not a valid name")
    return name


def _flag(d: dict, name: str) -> bool:
    return _field(d, name, bool)


def _joints(d: dict, robot: str) -> JointState:
    names = _strings(d, "joint_names")
    n = len(names)
    axis = _floats(d, "axis_to_vertical_deg", n) if "axis_to_vertical_deg" in d else None
    return JointState(robot, _finite(d, "t_s"), names, _floats(d, "q_rad", n),
                      _floats(d, "sigma_rad", n), _strings(d, "flags", n), _sensors(d), axis,
                      _combinations(d) if "combinations" in d else None)


def _combinations(d: dict) -> tuple[dict, ...]:
    """The joints payload's optional ``combinations``: each an object of a ``name``, its
    ``coefficients`` (names to finite numbers), a finite ``angle_rad`` and ``sigma_rad``."""
    items = _field(d, "combinations", list)
    out = []
    for k, c in enumerate(items):
        if not isinstance(c, dict):
            raise PayloadError("malformed", f"combinations[{k}]: expected an object")
        coef = _field(c, "coefficients", dict)
        if not all(isinstance(a, str) and isinstance(v, int | float) and not isinstance(v, bool)
                   and math.isfinite(v) for a, v in coef.items()):
            raise PayloadError("malformed",
                               f"combinations[{k}].coefficients: expected names to finite numbers")
        out.append({"name": _field(c, "name", str), "coefficients": {a: float(v) for a, v in coef.items()},
                    "angle_rad": _finite(c, "angle_rad"), "sigma_rad": _finite(c, "sigma_rad")})
    return tuple(out)


def _heading(d: dict, robot: str) -> Heading:
    bias = _floats(d, "gyro_bias_rad_s", 3)
    if not all(math.isfinite(b) for b in bias):
        raise PayloadError("malformed", "field 'gyro_bias_rad_s' is not finite")
    status = _field(d, "heading_status", str)
    if status not in HEADING_STATUS:
        raise PayloadError("malformed", f"heading_status {clipped_repr(status)}: expected one of "
                                        f"{', '.join(HEADING_STATUS)}")
    north = _field(d, "north", str)
    if north not in NORTH:
        raise PayloadError("malformed", f"north {clipped_repr(north)}: expected one of {', '.join(NORTH)}")
    _finite(d, "yaw_enu_rad")  # (derived from heading_rad: checked, not kept)
    _finite(d, "yaw_enu_variance_rad2")
    return Heading(robot, _finite(d, "t_s"), _finite(d, "heading_rad"), _finite(d, "heading_sigma_rad"),
                   _finite(d, "roll_rad"), _finite(d, "roll_sigma_rad"), _finite(d, "pitch_rad"),
                   _finite(d, "pitch_sigma_rad"), bias, _flag(d, "magnetic_disturbance"),
                   _flag(d, "magnetic_recovery"), status, north == "true")


def _status(d: dict, robot: str) -> Status:
    state = _field(d, "state", str)
    if state not in NODE_STATES:
        raise PayloadError("malformed", f"state {state!r}: expected one of {', '.join(NODE_STATES)}")
    counters = _field(d, "counters", dict)
    if not all(isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool)
               for k, v in counters.items()):
        raise PayloadError("malformed", "field 'counters': expected names to integers")
    return Status(robot, _field(d, "node", str), state, _finite(d, "t_wall_s"),
                  _field(d, "message", str), tuple(sorted(counters.items())), _sensors(d))


def _calibration(d: dict, robot: str) -> Calibration:
    names = _strings(d, "joint_names")
    n = len(names)
    return Calibration(robot, _field(d, "ok", bool), _field(d, "message", str),
                       _optional_finite(d, "t_start_s"), _optional_finite(d, "t_end_s"), names,
                       _optional_floats(d, "q_rad", n), _optional_floats(d, "sigma_rad", n),
                       _strings(d, "flags", n), _optional_finite(d, "roll_rad"),
                       _optional_finite(d, "pitch_rad"))


def _health(d: dict, robot: str) -> Health:
    alarms = _field(d, "alarms", list)
    if len(alarms) > MAX_ALARMS:
        raise PayloadError("malformed", f"field 'alarms': {len(alarms)} alarms, at most {MAX_ALARMS}")
    out = []
    for i, a in enumerate(alarms):
        if not isinstance(a, dict):
            raise PayloadError("malformed", f"alarm {i}: a JSON {type(a).__name__}, not an object")
        sensor = _field(a, "sensor", str)
        if not NAME_RE.match(sensor):
            raise PayloadError("malformed", f"alarm {i}: sensor {clipped_repr(sensor)}: use 1 to 64 letters, "
                               "digits, '_' or '-'")
        effect = _field(a, "effect", str)
        if effect not in ALARM_EFFECTS:
            raise PayloadError("malformed", f"alarm {i}: effect {clipped_repr(effect)}: expected one of "
                               f"{', '.join(ALARM_EFFECTS)}")
        unit = _field(a, "unit", str)
        if unit != ALARM_UNITS[effect]:
            raise PayloadError("malformed", f"alarm {i}: unit {clipped_repr(unit)} for {effect}: expected "
                               f"{ALARM_UNITS[effect]!r}")
        size, sigma = _finite(a, "size"), _finite(a, "sigma")
        if size < 0 or sigma < 0:
            raise PayloadError("malformed", f"alarm {i}: a negative size or sigma")
        cands = tuple(_strings(a, "candidates")) if "candidates" in a else (effect,)
        if not 1 <= len(cands) <= len(ALARM_EFFECTS) or cands[0] != effect or \
                len(set(cands)) != len(cands) or not set(cands) <= set(ALARM_EFFECTS):
            raise PayloadError("malformed", f"alarm {i}: candidates {clipped_repr(list(cands))}: the effect "
                               f"first, then others of {', '.join(ALARM_EFFECTS)}, each once")
        out.append((sensor, effect, size, sigma, unit, _finite(a, "since_s"), _finite(a, "raised_s"), cands))
    return Health(robot, _finite(d, "t_s"), tuple(out))


def _maneuver(d: dict, robot: str) -> Maneuver:
    state = _field(d, "state", str)
    if state not in MANEUVER_STATES:
        raise PayloadError("malformed", f"field 'state': {clipped_repr(state)}, expected one of "
                           f"{', '.join(MANEUVER_STATES)}")
    try:
        plan = PlannedManeuver.from_dict(_field(d, "plan", dict), "field 'plan'")
    except ValueError as e:
        raise PayloadError("malformed", str(e)[:300]) from None
    reached = d.get("poses_reached")
    if reached is not None and (isinstance(reached, bool) or not isinstance(reached, int)
                                or not 0 <= reached <= len(plan.poses_rad)):
        raise PayloadError("malformed", f"field 'poses_reached': {clipped_repr(reached)}, expected null or "
                           f"a count of at most the plan's {len(plan.poses_rad)} poses")
    return Maneuver(robot, state, _field(d, "accepted", bool), _field(d, "message", str), plan,
                    _optional_finite(d, "t_start_s"), _optional_finite(d, "t_end_s"), reached,
                    _field(d, "recording", str), _field(d, "config", str))


_DECODERS = {"raw": _raw, "joints": _joints, "heading": _heading, "status": _status,
             "calibration": _calibration, "health": _health, "maneuver": _maneuver}


def decode(key: str, data: bytes) -> Payload:
    """The payload received on ``key``; raises :class:`PayloadError` with a reason."""
    if len(data) > MAX_PAYLOAD_BYTES:
        raise PayloadError("oversized", f"{len(data)} bytes, more than {MAX_PAYLOAD_BYTES}")
    robot, kind, sensor = parse_key(key)
    try:
        d = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise PayloadError("malformed", f"not JSON: {e}") from e
    if not isinstance(d, dict):
        raise PayloadError("malformed", f"a JSON {type(d).__name__}, not an object")
    version = d.get("v")
    if isinstance(version, bool) or version not in READ_VERSIONS[kind]:
        raise PayloadError("unknown_version", f"{kind} payload version {clipped_repr(version)}; this "
                           f"node reads version {' or '.join(map(str, READ_VERSIONS[kind]))}")
    if d.get("type") != kind:
        raise PayloadError("malformed", f"type {d.get('type')!r} on a {kind} key")
    if d.get("robot") != robot:
        raise PayloadError("malformed", f"robot {d.get('robot')!r} on robot {robot!r}'s key")
    payload = _DECODERS[kind](d, robot)
    if isinstance(payload, RawBatch) and payload.stream.name != sensor:
        raise PayloadError("malformed", f"sensor {payload.stream.name!r} on sensor {sensor!r}'s key")
    return payload
