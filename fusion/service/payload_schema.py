"""What every armfusion payload shares: its type's version, the names in its key
expressions, the error a bad payload raises (:class:`PayloadError`, with the reason it is
counted by), and the checked reading of its fields (``read_*``: a missing, mistyped or
non-finite field raises it). The payloads themselves are in
:mod:`armfusion.fusion.service.payloads`."""

from __future__ import annotations

import math
import re
from typing import Any

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
NAME_RE = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


class PayloadError(ValueError):
    """A payload that is not what the schema says. ``reason`` is a short counter name."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def check_name(name: str, what: str) -> str:
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise ValueError(f"{what} {name!r}: use 1 to 64 letters, digits, '_' or '-'")
    return name


def check_name_or_fail(name: str, what: str) -> str:
    if not NAME_RE.match(name):
        raise PayloadError("malformed", f"{what} {name!r} is not a valid name")
    return name


# --- checked fields ---------------------------------------------------------------------------


def read_field(d: dict, name: str, types: type | tuple[type, ...]) -> Any:
    if name not in d:
        raise PayloadError("malformed", f"missing field {name!r}")
    v = d[name]
    allowed = types if isinstance(types, tuple) else (types,)
    if not isinstance(v, allowed) or (isinstance(v, bool) and bool not in allowed):
        raise PayloadError("malformed", f"field {name!r}: {type(v).__name__} is not the expected type")
    return v


def read_finite(d: dict, name: str) -> float:
    v = float(read_field(d, name, (int, float)))
    if not math.isfinite(v):
        raise PayloadError("malformed", f"field {name!r} is not finite")
    return v


def read_floats(d: dict, name: str, n: int | None = None) -> tuple[float, ...]:
    v = read_field(d, name, list)
    if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
        raise PayloadError("malformed", f"field {name!r}: expected a list of numbers")
    if n is not None and len(v) != n:
        raise PayloadError("malformed", f"field {name!r}: {len(v)} values, expected {n}")
    return tuple(float(x) for x in v)


def read_strings(d: dict, name: str, n: int | None = None) -> tuple[str, ...]:
    v = read_field(d, name, list)
    if not all(isinstance(x, str) for x in v):
        raise PayloadError("malformed", f"field {name!r}: expected a list of strings")
    if n is not None and len(v) != n:
        raise PayloadError("malformed", f"field {name!r}: {len(v)} values, expected {n}")
    return tuple(v)


def read_optional_floats(d: dict, name: str, n: int) -> tuple[float | None, ...]:
    v = read_field(d, name, list)
    if len(v) != n or not all(x is None or (isinstance(x, int | float) and not isinstance(x, bool)
                                            and math.isfinite(x)) for x in v):
        raise PayloadError("malformed", f"field {name!r}: expected {n} numbers or nulls")
    return tuple(None if x is None else float(x) for x in v)


def read_optional_finite(d: dict, name: str) -> float | None:
    return None if d.get(name) is None else read_finite(d, name)


def read_sensors(d: dict) -> tuple[tuple[str, str], ...]:
    """The optional ``sensors`` field: sensor names to status strings."""
    v = d.get("sensors", {})
    if not isinstance(v, dict) or not all(isinstance(k, str) and isinstance(x, str) for k, x in v.items()):
        raise PayloadError("malformed", "field 'sensors': expected sensor names to status strings")
    return tuple(v.items())


def read_flag(d: dict, name: str) -> bool:
    return read_field(d, name, bool)
