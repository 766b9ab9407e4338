"""The armfusion MCAP layout that the writer and the reader share
(``docs/recording-mcap.md``): the magic, the metadata record's name and format version,
the topics of sample streams (``raw/<stream>``, ``truth/<stream>``) and the JSON schema of
one sample per stream kind.
"""

from __future__ import annotations

from typing import Any

from sensors.samples import RAW_KINDS, TRUTH_KINDS

MAGIC = b"\x89MCAP0\r\n"
METADATA_NAME = "armfusion"
FORMAT_VERSION = "1"
RAW_PREFIX = "raw/"
TRUTH_PREFIX = "truth/"

# ---------------------------------------------------------------------------- schemas

KIND_DOC: dict[str, tuple[str, int | None, str]] = {
    # kind: (what one sample is, number of values or None if per arm, value type)
    "accel": ("a link accelerometer's x, y, z: signed counts as the device gives them", 3, "integer"),
    "imu_accel": ("the base IMU accelerometer's x, y, z: signed counts", 3, "integer"),
    "gyro": ("the base IMU gyroscope's x, y, z: signed counts", 3, "integer"),
    "mag": ("the base magnetometer's x, y, z in the IMU accelerometer's axes: signed counts", 3, "integer"),
    "temperature": ("the IMU temperature register: signed counts", 1, "integer"),
    "encoder": ("the joint encoders, joint 1 first: relative counts", None, "integer"),
    "truth_joints": ("ground-truth joint angles, joint 1 first, rad", None, "number"),
    "truth_base": ("ground-truth base roll, pitch, yaw, rad", 3, "number"),
}


def schema_for_kind(kind: str) -> dict[str, Any]:
    """The JSON schema (draft 2020-12) of one message of a stream of ``kind``."""
    if kind not in KIND_DOC:
        raise ValueError(f"unknown stream kind {kind!r}; expected one of {sorted(KIND_DOC)}")
    doc, n, item = KIND_DOC[kind]
    values: dict[str, Any] = {"type": "array", "items": {"type": item}, "description": doc}
    if n is not None:
        values["minItems"] = values["maxItems"] = n
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"armfusion.{kind}",
        "description": f"One sample of an armfusion '{kind}' stream.",
        "type": "object",
        "properties": {
            "t_s": {"type": "number", "description": "sample time, s (the recording's own origin)"},
            "values": values,
        },
        "required": ["t_s", "values"],
    }


def topic_for(stream_name: str, kind: str) -> str:
    """``raw/<stream>`` for raw kinds, ``truth/<stream>`` for ground truth."""
    if kind in RAW_KINDS:
        return RAW_PREFIX + stream_name
    if kind in TRUTH_KINDS:
        return TRUTH_PREFIX + stream_name
    raise ValueError(f"unknown stream kind {kind!r}; expected one of {sorted(KIND_DOC)}")
