"""The raw payload: a batch of one sensor's raw values on ``armfusion/<robot>/raw/<sensor>``
(:class:`RawBatch`), and its checked decoding (:func:`decode_raw`: a driver's batch checked
with C-level passes over its lists, anything else field by field)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import chain
from typing import Any

import numpy as np
from armfusion.fusion.service.payload_schema import (
    NAME_RE,
    SEQ_MAX,
    VERSIONS,
    PayloadError,
    check_name_or_fail,
    read_field,
    read_strings,
)
from armfusion.sensors.samples import RAW_KINDS, Stream


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


def _raw_plain(d: dict, robot: str) -> RawBatch | None:
    """A raw batch as a driver sends it (names, a batch number in range, finite times, rows
    of whole counts within 64 bits), checked with C-level passes over its lists; ``None``
    when any check fails or the batch holds anything else (decimals, a version-1 payload):
    :func:`decode_raw` then checks it field by field and says what is wrong. The checks are those
    of :func:`decode_raw`, and :class:`~armfusion.sensors.samples.Stream`'s still run on the arrays."""
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


def decode_raw(d: dict, robot: str) -> RawBatch:
    plain = _raw_plain(d, robot)
    if plain is not None:
        return plain
    sensor = check_name_or_fail(read_field(d, "sensor", str), "sensor")
    kind = read_field(d, "kind", str)
    if kind not in RAW_KINDS:
        raise PayloadError("malformed", f"kind {kind!r} is not a raw kind ({', '.join(sorted(RAW_KINDS))})")
    channels = read_strings(d, "channels")
    seq = read_field(d, "seq", int)
    if not 0 <= seq <= SEQ_MAX:
        raise PayloadError("malformed", f"field 'seq' = {str(seq)[:24]} is not a batch number 0…2⁶⁴ − 1")
    t = read_field(d, "t_s", list)
    whole = d["v"] == 1  # version 1: whole register counts only
    name = "counts" if whole else "values"
    rows = read_field(d, name, list)
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
