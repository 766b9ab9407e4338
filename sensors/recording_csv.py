"""Recording CSV: read and write the plain-text interchange format.

The format is ``shared/spec/recording-csv.md``: one header row, then one row per
sample instant; an empty cell means that sensor was not sampled at that instant.
Each stream takes the rows where *all* of its columns are filled; a row with only
some of them filled is an error. Unknown columns are ignored with one
:class:`RecordingWarning` that names them.

Which columns make which stream (see :mod:`sensors.samples`):

- ``t``: the time of the row in seconds, strictly increasing;
- ``P_x, P_y, P_z`` for any prefix ``P`` (not ``imu``/``imu_*``/``true_*``): the link
  accelerometer stream ``P``;
- ``imu_ax..az``, ``imu_gx..gz``, ``imu_mx..mz``, ``imu_temp``: the IMU streams;
- ``enc1 .. encN`` (contiguous from 1): the stream ``enc``;
- ``true_q1 .. true_qN`` (contiguous from 1): ``true_q``; ``true_roll, true_pitch,
  true_yaw``: ``true_base``.

Parsing is column-wise with numpy (``np.loadtxt`` on fixed-width byte strings, in
blocks), so a one-hour, 100 Hz, 30-column file reads in a few seconds.
"""

from __future__ import annotations

import csv
import io
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np

from sensors.samples import (
    IMU_STREAMS,
    TRUTH_BASE_COLUMNS,
    TRUTH_KINDS,
    Recording,
    Stream,
    StreamKind,
    accel_columns,
    encoder_columns,
    truth_joint_columns,
)

__all__ = ["RecordingWarning", "csv_columns", "read_csv", "write_csv"]

_BLOCK_ROWS = 65536  # rows parsed per np.loadtxt call: bounds memory to ~ block * columns * 32 B
_CELL_BYTES = 32  # fixed cell width for parsing; wider cells trigger an unsized re-parse
_T = "t"


class RecordingWarning(UserWarning):
    """A recording was read, but part of it was ignored or lost (said in the message)."""


@dataclass(frozen=True)
class _StreamColumns:
    name: str
    kind: StreamKind
    columns: tuple[str, ...]


# ---------------------------------------------------------------------------- columns


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


def _streams_from_header(header: list[str]) -> tuple[list[_StreamColumns], list[str], list[str]]:
    """Column groups found in ``header``, the columns used, and the columns ignored
    (each with a reason when it looks like a known column that is incomplete)."""
    present = set(header)
    found: list[_StreamColumns] = []
    for name, (kind, cols) in IMU_STREAMS.items():
        if all(c in present for c in cols):
            found.append(_StreamColumns(name, kind, cols))
    enc = _contiguous(present, "enc")
    if enc:
        found.append(_StreamColumns("enc", "encoder", enc))
    tq = _contiguous(present, "true_q")
    if tq:
        found.append(_StreamColumns("true_q", "truth_joints", tq))
    if all(c in present for c in TRUTH_BASE_COLUMNS):
        found.append(_StreamColumns("true_base", "truth_base", TRUTH_BASE_COLUMNS))
    taken = {c for s in found for c in s.columns} | {_T}
    names = {s.name for s in found}
    for col in header:
        if col in taken or not col.endswith("_x"):
            continue
        prefix = col[:-2]
        cols = accel_columns(prefix)
        if prefix and not _is_reserved_prefix(prefix) and all(c in present for c in cols):
            if prefix in names:
                raise ValueError(
                    f"columns {', '.join(cols)} would make an accelerometer stream {prefix!r}, "
                    "which clashes with another stream of that name"
                )
            found.append(_StreamColumns(prefix, "accel", cols))
            names.add(prefix)
            taken |= set(cols)
    order = {c: i for i, c in enumerate(header)}
    found.sort(key=lambda s: order[s.columns[0]])
    ignored = []
    for col in header:
        if col in taken:
            continue
        why = ""
        for name, (_, cols) in IMU_STREAMS.items():
            if col in cols:
                missing = [c for c in cols if c not in present]
                why = f" ({name} needs {', '.join(missing)} too)"
        if col in TRUTH_BASE_COLUMNS:
            missing = [c for c in TRUTH_BASE_COLUMNS if c not in present]
            why = f" (true_base needs {', '.join(missing)} too)"
        m = re.fullmatch(r"(enc|true_q)(\d+)", col)
        if m:
            why = f" ({m.group(1)}1..N must be contiguous from 1)"
        ignored.append(f"{col!r}{why}")
    return found, sorted(taken), ignored


# ---------------------------------------------------------------------------- reading


class _Lines:
    """Non-blank data lines of a text file, remembering each one's line number."""

    def __init__(self, f: io.TextIOBase, first_line: int) -> None:
        self._f = f
        self._line = first_line - 1
        self.line_numbers: list[int] = []

    def __iter__(self) -> Iterator[str]:
        for text in self._f:
            self._line += 1
            if text.strip():
                self.line_numbers.append(self._line)
                yield text


def _row_error(path: Path, row0: int, lines: list[int], what: str) -> ValueError:
    return ValueError(f"{path}: row {row0 + 1} (line {lines[row0]}): {what}")


def _parse_block(
    path: Path,
    block: list[str],
    usecols: list[int],
    n_header: int,
    row_offset: int,
    lines: list[int],
) -> np.ndarray:
    """Cells of the used columns as a ``(rows, len(usecols))`` byte-string array."""
    # Fixed-width cells parse fast; a cell that fills the width may have been cut,
    # so that block is parsed again with cells as wide as they need to be.
    cells = _loadtxt(path, block, usecols, n_header, row_offset, lines, f"S{_CELL_BYTES}")
    if cells.size and np.char.str_len(cells).max() >= _CELL_BYTES:
        cells = _loadtxt(path, block, usecols, n_header, row_offset, lines, "S")
    return cells


def _loadtxt(
    path: Path,
    block: list[str],
    usecols: list[int],
    n_header: int,
    row_offset: int,
    lines: list[int],
    dtype: str,
) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            return np.loadtxt(
                block,
                delimiter=",",
                dtype=dtype,
                comments=None,
                quotechar='"',
                usecols=usecols,
                ndmin=2,
                encoding="utf-8",
            )
    except ValueError as e:
        # find the row whose cell count differs from the header, to say where
        for i, row in enumerate(csv.reader(block)):
            if len(row) != n_header:
                raise _row_error(
                    path,
                    row_offset + i,
                    lines,
                    f"{len(row)} cells, but the header has {n_header} columns",
                ) from None
        raise ValueError(f"{path}: cannot parse rows {row_offset + 1}..: {e}") from None


def _strip(cells: np.ndarray) -> np.ndarray:
    """Cells without surrounding spaces (a hand-written ``0.1, 12, , 5`` is fine)."""
    if cells.size and np.any(cells.view(np.uint8) == ord(" ")):
        return np.char.strip(cells)
    return cells


def _parse_ints(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decimal integers ``[+-]digits`` of an ``(R, C)`` byte-string array, vectorised.

    Returns the values and a mask of the cells that are such integers (anything else,
    e.g. ``1_000``, ``12.5`` or an empty cell, is left for the caller).
    """
    length = np.char.str_len(cells)
    n_chars = int(length.max(initial=0))
    width = cells.dtype.itemsize
    b = np.ascontiguousarray(cells).view(np.uint8).reshape(-1, width)[:, :n_chars]
    planes = np.ascontiguousarray(b.T)  # (n_chars, R * C): one contiguous plane per position
    length = length.reshape(-1)
    neg = planes[0] == ord("-") if n_chars else np.zeros(length.shape, bool)
    signed = neg | (planes[0] == ord("+")) if n_chars else neg
    ok = (length - signed >= 1) & (length - signed <= 18)  # 18 digits fit in int64
    value = np.zeros(length.shape, np.int64)
    for k in range(n_chars):
        d = planes[k] - np.uint8(ord("0"))  # wraps: any non-digit becomes > 9
        inside = k < length
        if k == 0:
            d[signed] = 0
        ok &= (d <= 9) | ~inside
        value = np.where(inside, value * 10 + d, value)
    value = np.where(neg, -value, value)
    return value.reshape(cells.shape), ok.reshape(cells.shape)


def _parse_block_values(
    path: Path,
    names: list[str],
    cells: np.ndarray,
    is_int: np.ndarray,
    row_offset: int,
    lines: list[int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer values, float values and the empty mask of one block of cells."""
    empty = cells == b""
    ints = np.zeros(cells.shape, np.int64)
    floats = np.zeros(cells.shape, np.float64)
    ic = np.flatnonzero(is_int)
    fc = np.flatnonzero(~is_int)
    if ic.size:
        sub = cells[:, ic]
        v, ok = _parse_ints(sub)
        ints[:, ic] = v
        slow = ~ok & ~empty[:, ic]
        for i, j in zip(*np.nonzero(slow), strict=True):  # rare: anything int() accepts
            ints[i, ic[j]] = _convert(path, names[ic[j]], sub[i, j], int, row_offset + i, lines)
    if fc.size:
        sub = np.where(empty[:, fc], b"0", cells[:, fc])
        try:
            floats[:, fc] = sub.astype(np.float64)
        except ValueError:
            for i, j in zip(*np.nonzero(~empty[:, fc]), strict=True):
                floats[i, fc[j]] = _convert(path, names[fc[j]], sub[i, j], float, row_offset + i, lines)
    return ints, floats, empty


def _convert(path: Path, name: str, cell: bytes, conv: type, row0: int, lines: list[int]):
    try:
        return conv(cell)
    except ValueError:
        kind = "an integer (raw counts)" if conv is int else "a number"
        value = cell.decode("utf-8", "replace")
        raise _row_error(path, row0, lines, f"column {name!r}: {value!r} is not {kind}") from None


def read_csv(path: str | Path) -> Recording:
    """Read a recording CSV (``shared/spec/recording-csv.md``) into a :class:`Recording`.

    Raises ``ValueError`` naming the file, row (1-based data row), line and column for
    a missing ``t`` column, an empty or non-increasing ``t``, a cell that is not a
    number (or not an integer in a count column), a row too short to reach the
    columns in use, and a row that fills only some of a stream's columns.
    Warns once (:class:`RecordingWarning`) naming the columns it ignored.
    """
    path = Path(path)
    try:
        return _read_csv(path)
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text ({e.reason}); is it a recording CSV?") from None


def _read_csv(path: Path) -> Recording:
    with open(path, encoding="utf-8-sig", newline=None) as f:
        header_line = f.readline()
        first_data_line = 2
        while header_line and not header_line.strip():
            header_line = f.readline()
            first_data_line += 1
        if not header_line:
            raise ValueError(f"{path}: the file is empty; expected a header row starting with 't'")
        header = [h.strip() for h in next(csv.reader([header_line]))]
        if _T not in header:
            raise ValueError(
                f"{path}: no column 't' in the header (line {first_data_line - 1}): {', '.join(header)}"
            )
        dup = sorted({h for h in header if header.count(h) > 1})
        if dup:
            raise ValueError(f"{path}: the header repeats column(s) {', '.join(dup)}")
        groups, used, ignored = _streams_from_header(header)
        if ignored:
            warnings.warn(
                f"{path}: ignored {len(ignored)} unknown column(s): {', '.join(ignored)}",
                RecordingWarning,
                stacklevel=3,
            )
        index = {c: i for i, c in enumerate(header)}
        used = sorted(used, key=index.__getitem__)
        usecols = [index[c] for c in used]
        col_of = {c: j for j, c in enumerate(used)}
        dtypes = {_T: np.float64}
        for g in groups:
            for c in g.columns:
                dtypes[c] = np.float64 if g.kind in TRUTH_KINDS else np.int64

        source = _Lines(f, first_data_line)
        lines = source.line_numbers
        it = iter(source)
        is_int = np.array([dtypes[c] is np.int64 for c in used])
        int_parts: list[np.ndarray] = []
        float_parts: list[np.ndarray] = []
        empty_parts: list[np.ndarray] = []
        n_rows = 0
        while block := list(islice(it, _BLOCK_ROWS)):
            cells = _strip(_parse_block(path, block, usecols, len(header), n_rows, lines))
            ints, floats, empty = _parse_block_values(path, used, cells, is_int, n_rows, lines)
            int_parts.append(ints)
            float_parts.append(floats)
            empty_parts.append(empty)
            n_rows += len(block)

    shape = (0, len(used))
    all_ints = np.concatenate(int_parts) if int_parts else np.zeros(shape, np.int64)
    all_floats = np.concatenate(float_parts) if float_parts else np.zeros(shape)
    all_empty = np.concatenate(empty_parts) if empty_parts else np.zeros(shape, bool)

    def column(c: str) -> np.ndarray:
        j = col_of[c]
        return all_ints[:, j] if is_int[j] else all_floats[:, j]

    t_s = column(_T)
    t_empty = all_empty[:, col_of[_T]]
    if t_empty.any():
        raise _row_error(path, int(np.argmax(t_empty)), lines, "t is empty; every row needs a time")
    if not np.all(np.isfinite(t_s)):
        i = int(np.argmax(~np.isfinite(t_s)))
        raise _row_error(path, i, lines, f"t = {float(t_s[i])!r} is not a finite time")
    bad = np.flatnonzero(np.diff(t_s) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise _row_error(
            path,
            i,
            lines,
            f"t must increase from row to row, but t = {float(t_s[i])!r} follows "
            f"t = {float(t_s[i - 1])!r} at row {i} (line {lines[i - 1]})",
        )

    streams: dict[str, Stream] = {}
    for g in groups:
        filled = ~all_empty[:, [col_of[c] for c in g.columns]]
        every = filled.all(axis=1)
        partial = filled.any(axis=1) & ~every
        if partial.any():
            i = int(np.argmax(partial))
            have = [c for c, f_ in zip(g.columns, filled[i], strict=True) if f_]
            miss = [c for c, f_ in zip(g.columns, filled[i], strict=True) if not f_]
            raise _row_error(
                path,
                i,
                lines,
                f"stream {g.name!r} has {', '.join(have)} but column(s) {', '.join(miss)} "
                "empty; a sensor's columns must be all filled or all empty",
            )
        values = np.stack([column(c)[every] for c in g.columns], axis=1)
        streams[g.name] = Stream(g.name, g.kind, t_s[every], values, g.columns)
    return Recording(streams, meta={"source": str(path)})


# ---------------------------------------------------------------------------- writing


def _cells(stream: Stream) -> list[str]:
    """One text per sample: the stream's cells joined by commas."""
    fmt = "%.10g".__mod__ if stream.kind in TRUTH_KINDS else str
    per_channel = [list(map(fmt, stream.values[:, j].tolist())) for j in range(stream.values.shape[1])]
    return list(map(",".join, zip(*per_channel, strict=True)))


def write_csv(rec: Recording, path: str | Path) -> None:
    """Write ``rec`` as a recording CSV.

    All streams are merged onto the union of their time instants (one row per
    instant, in time order); a stream's cells are empty where it was not sampled.
    ``t`` is written with the shortest text that reads back to the same float (so
    reading the file gives the same instants), counts as integers, ground truth
    with 10 significant digits.
    """
    path = Path(path)
    streams = list(rec.streams.values())
    header = [_T]
    for s in streams:
        cols = csv_columns(s)
        clash = set(cols) & set(header)
        if clash:
            raise ValueError(f"stream {s.name!r}: column(s) {', '.join(sorted(clash))} twice")
        header.extend(cols)
    ts = [s.t_s for s in streams]
    t_all = np.unique(np.concatenate(ts)) if ts else np.zeros(0)
    n = t_all.size
    columns: list[list[str]] = [list(map(repr, t_all.tolist()))]
    for s in streams:
        cells = _cells(s)
        if len(s) == n:  # sampled at every instant
            columns.append(cells)
            continue
        col = np.full(n, "," * (len(s.channels) - 1), dtype=object)
        col[np.searchsorted(t_all, s.t_s)] = cells
        columns.append(col.tolist())
    with open(path, "w", encoding="utf-8", newline="") as f:
        f.write(",".join(header) + "\n")
        for start in range(0, n, _BLOCK_ROWS):
            rows = zip(*(c[start : start + _BLOCK_ROWS] for c in columns), strict=True)
            f.write("\n".join(map(",".join, rows)))
            f.write("\n")
