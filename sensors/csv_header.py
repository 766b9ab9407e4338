"""Which columns of a recording CSV make which stream (``shared/spec/recording-csv.md``, and
beyond it a link gyroscope's ``P_gx, P_gy, P_gz`` as the stream ``P_gyro``):
the columns a stream is written to (:func:`csv_columns`) and the streams a header holds
(:func:`streams_from_header`), with the sensors left out because only some of their
columns are there and the unknown columns, for the reader's one warning.
"""

from __future__ import annotations

import re
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

from armfusion.sensors.samples import (
    IMU_STREAMS,
    LINK_GYRO_SUFFIX,
    TRUTH_BASE_COLUMNS,
    RecordingError,
    Stream,
    StreamKind,
    accel_columns,
    clipped_repr,
    encoder_columns,
    link_gyro_columns,
    truth_joint_columns,
)

T_COLUMN = "t"
"""The time column, in seconds: the first of every recording CSV's header."""


@dataclass(frozen=True)
class StreamColumns:
    """A stream found in a header: its name, kind and columns (in channel order)."""

    name: str
    kind: StreamKind
    columns: tuple[str, ...]


def csv_columns(stream: Stream) -> tuple[str, ...]:
    """The CSV columns that hold ``stream``, as the spec names them.

    Raises ``ValueError`` when the stream's name, kind and channels do not match a
    column group of the format (the CSV has no other way to say what a column is).
    """
    k = len(stream.channels)
    if stream.kind == "accel":
        expected: tuple[str, ...] = accel_columns(stream.name)
        if _is_reserved_prefix(stream.name):
            raise ValueError(
                f"stream {stream.name!r} (kind accel): an accelerometer name may not start "
                "with 'imu' or 'true_' in the recording CSV"
            )
    elif stream.kind == "link_gyro":
        sensor = stream.name[: -len(LINK_GYRO_SUFFIX)]
        if not stream.name.endswith(LINK_GYRO_SUFFIX) or not sensor or _is_reserved_prefix(sensor):
            raise ValueError(
                f"stream {stream.name!r} (kind link_gyro): a link gyroscope's stream is its "
                f"sensor's name + {LINK_GYRO_SUFFIX!r} (the sensor's name may not start with 'imu' "
                "or 'true_')"
            )
        expected = link_gyro_columns(sensor)
    elif stream.kind == "encoder":
        expected = encoder_columns(k)
        _expect_name(stream, "enc", expected)
    elif stream.kind == "truth_joints":
        expected = truth_joint_columns(k)
        _expect_name(stream, "true_q", expected)
    elif stream.kind == "truth_base":
        expected = TRUTH_BASE_COLUMNS
        _expect_name(stream, "true_base", expected)
    else:
        imu = {kind: (name, cols) for name, (kind, cols) in IMU_STREAMS.items()}
        if stream.kind not in imu:
            raise ValueError(f"stream {stream.name!r}: unknown kind {stream.kind!r}")
        name, expected = imu[stream.kind]
        _expect_name(stream, name, expected)
    if tuple(stream.channels) != expected:
        raise ValueError(
            f"stream {stream.name!r} (kind {stream.kind}) has channels {list(stream.channels)}; "
            f"the recording CSV names them {list(expected)}"
        )
    return expected


def _expect_name(stream: Stream, name: str, expected: tuple[str, ...]) -> None:
    if stream.name != name:
        raise ValueError(
            f"stream {stream.name!r} (kind {stream.kind}): the recording CSV holds this kind "
            f"only as stream {name!r} (columns {', '.join(expected)})"
        )


def _is_reserved_prefix(prefix: str) -> bool:
    return prefix == "imu" or prefix.startswith(("imu_", "true_"))


def _contiguous(header: set[str], stem: str) -> tuple[str, ...]:
    cols = []
    i = 1
    while f"{stem}{i}" in header:
        cols.append(f"{stem}{i}")
        i += 1
    return tuple(cols)


class _HeaderScan:
    """What a header scan has found so far: the streams, their names, the columns they take,
    and the sensors left out because only some of their columns are there."""

    def __init__(self, header: list[str]):
        self.present = set(header)
        self.found: list[StreamColumns] = []
        self.names: set[str] = set()
        self.taken: set[str] = {T_COLUMN}
        self.incomplete: list[str] = []

    def complete(self, cols: tuple[str, ...]) -> bool:
        """Whether every one of ``cols`` is in the header."""
        return all(c in self.present for c in cols)

    def add(self, name: str, kind: StreamKind, cols: tuple[str, ...]) -> None:
        """A stream found: ``name`` of ``kind`` in ``cols``."""
        self.found.append(StreamColumns(name, kind, cols))
        self.names.add(name)
        self.taken |= set(cols)

    def partial(self, name: str, cols: tuple[str, ...]) -> None:
        """Say ``name`` is left out when the header has some of ``cols`` but not all."""
        have = [c for c in cols if c in self.present]
        if have and len(have) < len(cols):
            missing = [c for c in cols if c not in self.present]
            self.incomplete.append(f"{name} (has {', '.join(have)}; needs {', '.join(missing)} too)")


def _fixed_streams(scan: _HeaderScan) -> None:
    """The streams of fixed names: the IMU's, the encoders, the truth's."""
    for name, (kind, cols) in IMU_STREAMS.items():
        if scan.complete(cols):
            scan.add(name, kind, cols)
        scan.partial(name, cols)
    enc = _contiguous(scan.present, "enc")
    if enc:
        scan.add("enc", "encoder", enc)
    tq = _contiguous(scan.present, "true_q")
    if tq:
        scan.add("true_q", "truth_joints", tq)
    if scan.complete(TRUTH_BASE_COLUMNS):
        scan.add("true_base", "truth_base", TRUTH_BASE_COLUMNS)
    scan.partial("true_base", TRUTH_BASE_COLUMNS)


def _prefixes(header: list[str], suffixes: tuple[str, ...], skip: Collection[str] = ()) -> list[str]:
    """The sensors' names the header's columns ending in ``suffixes`` (all of one length)
    give, in the header's order; none reserved, no column of ``skip``."""
    out: list[str] = []
    n = len(suffixes[0])
    for col in header:
        if col in skip or col[-n:] not in suffixes:
            continue
        prefix = col[:-n]
        if prefix and not _is_reserved_prefix(prefix) and prefix not in out:
            out.append(prefix)
    return out


def _link_gyros(scan: _HeaderScan, prefixes: list[str]) -> None:
    """Link gyroscopes: ``P_gx, P_gy, P_gz`` -> stream ``P_gyro``."""
    for prefix in prefixes:
        cols, name = link_gyro_columns(prefix), prefix + LINK_GYRO_SUFFIX
        if scan.complete(cols):
            scan.add(name, "link_gyro", cols)
        else:
            scan.partial(name, cols)


def _accelerometers(scan: _HeaderScan, prefixes: list[str], path: Path) -> None:
    """Link accelerometers: ``P_x, P_y, P_z`` -> stream ``P`` (a ``RecordingError`` when ``P``
    is another stream's name)."""
    for prefix in prefixes:
        cols = accel_columns(prefix)
        if scan.complete(cols):
            if prefix in scan.names:
                raise RecordingError(
                    f"{path}: columns {', '.join(cols)} would make an accelerometer stream "
                    f"{prefix!r}, which clashes with another stream of that name"
                )
            scan.add(prefix, "accel", cols)
        else:
            scan.partial(prefix, cols)


def _unknown_columns(scan: _HeaderScan, header: list[str], accel_prefixes: list[str],
                     gyro_prefixes: list[str]) -> list[str]:
    """The columns no stream takes and no incomplete sensor explains (a gap in ``enc1..N``
    or ``true_q1..N`` is said as incomplete)."""
    imu_columns = {c for _, cols in IMU_STREAMS.values() for c in cols} | set(TRUTH_BASE_COLUMNS)
    unknown = []
    for col in header:
        if col in scan.taken or col in imu_columns:
            continue
        if col[-2:] in ("_x", "_y", "_z") and col[:-2] in accel_prefixes:
            continue  # said as an incomplete sensor
        if col[-3:] in ("_gx", "_gy", "_gz") and col[:-3] in gyro_prefixes:
            continue  # said as an incomplete link gyroscope
        m = re.fullmatch(r"(enc|true_q)(\d+)", col)
        if m:
            scan.incomplete.append(f"{col} ({m.group(1)}1..N must be contiguous from 1)")
            continue
        unknown.append(clipped_repr(col))
    return unknown


def streams_from_header(
    header: list[str], path: Path
) -> tuple[list[StreamColumns], list[str], list[str], list[str]]:
    """Column groups found in ``header``, the columns used, the sensors left out because
    only some of their columns are there (each saying what it has and what it needs),
    and the unknown columns."""
    scan = _HeaderScan(header)
    _fixed_streams(scan)
    gyro_prefixes = _prefixes(header, ("_gx", "_gy", "_gz"))
    _link_gyros(scan, gyro_prefixes)
    accel_prefixes = _prefixes(header, ("_x", "_y", "_z"), skip=scan.taken)
    _accelerometers(scan, accel_prefixes, path)
    order = {c: i for i, c in enumerate(header)}
    scan.found.sort(key=lambda s: order[s.columns[0]])
    unknown = _unknown_columns(scan, header, accel_prefixes, gyro_prefixes)
    return scan.found, sorted(scan.taken), scan.incomplete, unknown


def first_few(items: list[str], first: int = 8) -> str:
    """The first few of ``items``, and how many more (a header of 1000 unknown columns is
    said in one line, not listed)."""
    more = len(items) - first
    return ", ".join(items[:first]) + (f", … and {more} more" if more > 0 else "")
