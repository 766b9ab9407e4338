"""The armfusion MCAP layout that the writer and the reader share
(``docs/recording-mcap.md``): the magic, the metadata record's name and format version,
the topics of sample streams (``raw/<stream>``, ``truth/<stream>``) and the JSON schema of
one sample per stream kind.
"""

from __future__ import annotations

from typing import Any

from armfusion.sensors.samples import RAW_KINDS, TRUTH_KINDS

MAGIC = b"\x89MCAP0\r\n"
METADATA_NAME = "armfusion"
FORMAT_VERSION = "2"
"""The format written: 2 since raw values may be decimals (a sensor described in g, °/s…)."""
READ_FORMAT_VERSIONS = ("1", "2")
"""The formats read: version 1's raw values are all whole counts, read the same way."""
RAW_PREFIX = "raw/"
TRUTH_PREFIX = "truth/"

# ---------------------------------------------------------------------------- schemas

_AS_GIVEN = ("; integer counts, or numbers in the unit the config's sensor description "
             "declares when the sensor delivers physical values")

KIND_DOC: dict[str, tuple[str, int | None, str]] = {
    # kind: (what one sample is, number of values or None if per arm, value type). Raw
    # values are "number": whole counts, or decimals in a physical unit (files written
    # before said "integer", and read the same).
    "accel": ("a link accelerometer's x, y, z as the device gives them" + _AS_GIVEN, 3, "number"),
    "imu_accel": ("the base IMU accelerometer's x, y, z" + _AS_GIVEN, 3, "number"),
    "gyro": ("the base IMU gyroscope's x, y, z" + _AS_GIVEN, 3, "number"),
    "link_gyro": ("a link gyroscope's x, y, z" + _AS_GIVEN, 3, "number"),
    "mag": ("the base magnetometer's x, y, z in the IMU accelerometer's axes" + _AS_GIVEN, 3, "number"),
    "temperature": ("the IMU temperature register" + _AS_GIVEN, 1, "number"),
    "encoder": ("the joint encoders, joint 1 first: relative counts", None, "number"),
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
