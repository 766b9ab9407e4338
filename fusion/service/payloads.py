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
``"v"``, its type's version (:data:`VERSIONS`: 3 for ``heading``, 2 for ``raw``, 1 for the
others), and ``"type"``, one of ``raw``, ``joints``, ``heading``, ``status``, ``calibration``,
``health``, ``maneuver``; the fields of each are those of its dataclass, written out in
docs/reference/service.md. The dataclasses live by family, each with its checked decoding,
and are imported from here: the raw batch in :mod:`~armfusion.fusion.service.raw_payload`, the
estimate's two in :mod:`~armfusion.fusion.service.estimate_payloads`, the nodes' status,
replies, alarms and maneuver in :mod:`~armfusion.fusion.service.node_payloads`; what they
share (versions, names, the error, the checked fields) in
:mod:`~armfusion.fusion.service.payload_schema`. The
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

from armfusion.fusion.service.estimate_payloads import Heading, JointState, decode_heading, decode_joints
from armfusion.fusion.service.node_payloads import (
    MANEUVER_STATES,
    MAX_ALARMS,
    NODE_STATES,
    Calibration,
    Health,
    Maneuver,
    Status,
    decode_calibration,
    decode_health,
    decode_maneuver,
    decode_status,
)
from armfusion.fusion.service.payload_schema import (
    MAX_PAYLOAD_BYTES,
    NAME_RE,
    READ_VERSIONS,
    SEQ_MAX,
    VERSIONS,
    PayloadError,
    check_name,
    check_name_or_fail,
)
from armfusion.fusion.service.raw_payload import RawBatch, decode_raw
from armfusion.sensors.samples import clipped_repr

__all__ = ["MANEUVER_ACTIONS", "MANEUVER_STATES", "MAX_ALARMS", "MAX_PAYLOAD_BYTES", "NAME_RE", "NODE_STATES",
           "READ_VERSIONS", "ROOT", "SEQ_MAX", "VERSIONS", "Calibration", "Heading", "Health", "JointState",
           "Maneuver", "Payload", "PayloadError", "RawBatch", "Status", "calibrate_key", "check_name",
           "check_name_or_fail", "decode", "encode", "health_key", "heading_key", "joints_key",
           "maneuver_key", "parse_key", "raw_key", "raw_keys", "status_key"]

ROOT = "armfusion"


# --- key expressions ------------------------------------------------------------------------


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


# --- encoding and decoding ------------------------------------------------------------------


Payload = RawBatch | JointState | Heading | Status | Calibration | Health | Maneuver


def encode(payload: Payload) -> bytes:
    """The wire form of ``payload``: compact UTF-8 JSON."""
    data = json.dumps(payload.to_json(), separators=(",", ":"), allow_nan=False).encode()
    if len(data) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"{type(payload).__name__}: {len(data)} bytes is more than "
                         f"{MAX_PAYLOAD_BYTES}; publish smaller batches")
    return data


_DECODERS = {"raw": decode_raw, "joints": decode_joints, "heading": decode_heading, "status": decode_status,
             "calibration": decode_calibration, "health": decode_health, "maneuver": decode_maneuver}


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
