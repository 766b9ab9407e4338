"""Recording CSV: read and write the plain-text interchange format.

The format is ``shared/spec/recording-csv.md``: one header row, then one row per
sample instant; an empty cell means that sensor was not sampled at that instant.
Each stream takes the rows where *all* of its columns are filled; a row with only
some of them filled is an error, and so is a row with fewer or more cells than the
header. One :class:`RecordingWarning` names the sensors left out because only some of
their columns are there, and the first few unknown columns ignored.

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

The reader bounds its work (:class:`CsvLimits`: file size, line length, header
columns, the length of a cell in use; a NUL byte is refused), so that a broken or
hostile file is refused with a :class:`~sensors.samples.RecordingError` naming the
place, within bounded time and memory, as soon as the problem is met
(``docs/cli.md``, "What the readers refuse").
"""

from __future__ import annotations

import csv
import io
import os
import re
import warnings
from array import array
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensors.samples import (
    IMU_STREAMS,
    TRUTH_BASE_COLUMNS,
    TRUTH_KINDS,
    Recording,
    RecordingError,
    Stream,
    StreamKind,
    accel_columns,
    clipped_repr,
    encoder_columns,
    truth_joint_columns,
)

__all__ = [
    "DEFAULT_LIMITS",
    "CsvLimits",
    "RecordingError",
    "RecordingWarning",
    "csv_columns",
    "read_csv",
    "write_csv",
]

_BLOCK_ROWS = 65536  # rows parsed per np.loadtxt call at most
_BLOCK_CELLS = 1 << 19  # and cells: a block's parse takes ~ 100 B a cell (~50 MB)
_BLOCK_CHARS = 1 << 24  # and characters of text held at once
_CELL_BYTES = 32  # fixed cell width for parsing; wider cells trigger a re-parse to the limit
_ECHO_START = 16  # characters of a too-long cell quoted in its message
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


def _streams_from_header(
    header: list[str], path: Path
) -> tuple[list[_StreamColumns], list[str], list[str], list[str]]:
    """Column groups found in ``header``, the columns used, the sensors left out because
    only some of their columns are there (each saying what it has and what it needs),
    and the unknown columns."""
    present = set(header)
    found: list[_StreamColumns] = []
    incomplete: list[str] = []

    def partial(name: str, cols: tuple[str, ...]) -> None:
        have = [c for c in cols if c in present]
        if have and len(have) < len(cols):
            missing = [c for c in cols if c not in present]
            incomplete.append(f"{name} (has {', '.join(have)}; needs {', '.join(missing)} too)")

    for name, (kind, cols) in IMU_STREAMS.items():
        if all(c in present for c in cols):
            found.append(_StreamColumns(name, kind, cols))
        partial(name, cols)
    enc = _contiguous(present, "enc")
    if enc:
        found.append(_StreamColumns("enc", "encoder", enc))
    tq = _contiguous(present, "true_q")
    if tq:
        found.append(_StreamColumns("true_q", "truth_joints", tq))
    if all(c in present for c in TRUTH_BASE_COLUMNS):
        found.append(_StreamColumns("true_base", "truth_base", TRUTH_BASE_COLUMNS))
    partial("true_base", TRUTH_BASE_COLUMNS)
    taken = {c for s in found for c in s.columns} | {_T}
    names = {s.name for s in found}
    imu_columns = {c for _, cols in IMU_STREAMS.values() for c in cols} | set(TRUTH_BASE_COLUMNS)
    accel_prefixes: list[str] = []
    for col in header:
        if col in taken or col[-2:] not in ("_x", "_y", "_z"):
            continue
        prefix = col[:-2]
        if prefix and not _is_reserved_prefix(prefix) and prefix not in accel_prefixes:
            accel_prefixes.append(prefix)
    for prefix in accel_prefixes:
        cols = accel_columns(prefix)
        if all(c in present for c in cols):
            if prefix in names:
                raise RecordingError(
                    f"{path}: columns {', '.join(cols)} would make an accelerometer stream "
                    f"{prefix!r}, which clashes with another stream of that name"
                )
            found.append(_StreamColumns(prefix, "accel", cols))
            names.add(prefix)
            taken |= set(cols)
        else:
            partial(prefix, cols)
    order = {c: i for i, c in enumerate(header)}
    found.sort(key=lambda s: order[s.columns[0]])
    unknown = []
    for col in header:
        if col in taken or col in imu_columns:
            continue
        if col[-2:] in ("_x", "_y", "_z") and col[:-2] in accel_prefixes:
            continue  # said as an incomplete sensor
        m = re.fullmatch(r"(enc|true_q)(\d+)", col)
        if m:
            incomplete.append(f"{col} ({m.group(1)}1..N must be contiguous from 1)")
            continue
        unknown.append(clipped_repr(col))
    return found, sorted(taken), incomplete, unknown


def _some(items: list[str], first: int = 8) -> str:
    """The first few of ``items``, and how many more (a header of 1000 unknown columns is
    said in one line, not listed)."""
    more = len(items) - first
    return ", ".join(items[:first]) + (f", … and {more} more" if more > 0 else "")


# ---------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class CsvLimits:
    """What :func:`read_csv` refuses, so that a broken or hostile file costs bounded time
    and memory (``docs/cli.md``, "What the readers refuse"). Each is far above what a
    recording needs: a number fits in 30 characters, the WMRA's richest recording has 42
    columns, and a day at 100 Hz of it is about 1.5 GB.

    ``max_cell_chars`` applies to the cells of the columns the reader uses (an ignored
    column, a note say, may hold longer text, within ``max_line_chars``).
    """

    max_file_bytes: int = 2 * 1024**3
    max_columns: int = 1000
    max_cell_chars: int = 64
    max_line_chars: int = 65536


DEFAULT_LIMITS = CsvLimits()


class _Lines:
    """Lines of a text file read at most ``max_line_chars`` at a time: a line longer than
    that (a file of one endless line, padding of NUL bytes) or one that holds a NUL is
    refused as soon as it is met, without reading the rest."""

    def __init__(self, path: Path, f: io.TextIOBase, limits: CsvLimits) -> None:
        self._path = path
        self._readline = f.readline
        self._limits = limits
        self.line = 0

    def next(self) -> str:
        """The next line ("" at the end of the file)."""
        n = self._limits.max_line_chars + 1
        text = self._readline(n)
        if not text:
            return ""
        self.line += 1
        if "\0" in text:
            raise RecordingError(
                f"{self._path}: line {self.line} holds a NUL byte; a recording CSV is text"
            )
        if len(text) == n and text[-1] != "\n":
            what = "the header row" if self.line == 1 else f"line {self.line}"
            raise RecordingError(
                f"{self._path}: {what} is longer than {self._limits.max_line_chars} characters "
                f"(a recording has at most {self._limits.max_columns} columns of numbers); "
                "is it a recording CSV?"
            )
        return text


def _row_error(path: Path, row0: int, lines, what: str) -> RecordingError:
    return RecordingError(f"{path}: row {row0 + 1} (line {lines[row0]}): {what}")


def _check_widths(path: Path, block: list[str], n_header: int, row_offset: int, lines) -> None:
    """Every row has as many cells as the header: more is refused as well as fewer (an
    extra cell shifts every later one into the wrong column)."""
    commas = np.fromiter((text.count(",") for text in block), np.int64, len(block))
    quoted = np.fromiter(('"' in text for text in block), bool, len(block))
    for i in np.flatnonzero((commas != n_header - 1) | quoted):
        try:
            n = len(next(csv.reader([block[i]])))
        except csv.Error as e:
            raise _row_error(path, row_offset + int(i), lines, f"not a CSV row ({e})") from None
        if n != n_header:
            raise _row_error(path, row_offset + int(i), lines,
                             f"{n} cells, but the header has {n_header} columns")


def _parse_block(
    path: Path,
    block: list[str],
    used: list[str],
    usecols: list[int],
    row_offset: int,
    lines,
    limits: CsvLimits,
) -> np.ndarray:
    """Cells of the used columns as a ``(rows, len(usecols))`` byte-string array."""
    # Fixed-width cells parse fast; a cell that fills the width may have been cut, so
    # that block is parsed again with cells one longer than the limit, to find any beyond.
    first = min(_CELL_BYTES, limits.max_cell_chars + 1)
    cells = _loadtxt(path, block, used, usecols, row_offset, lines, f"S{first}")
    if cells.size and np.char.str_len(cells).max() >= first:
        if first <= limits.max_cell_chars:
            cells = _loadtxt(path, block, used, usecols, row_offset, lines,
                             f"S{limits.max_cell_chars + 1}")
        too_long = np.char.str_len(cells) > limits.max_cell_chars
        if too_long.any():
            i, j = (int(x[0]) for x in np.nonzero(too_long))
            raise _row_error(
                path, row_offset + i, lines,
                f"column {clipped_repr(used[j])}: a cell longer than {limits.max_cell_chars} "
                f"characters (it starts {_text(cells[i, j][:_ECHO_START])!r}); "
                "no number needs so many",
            )
    return cells


_LOADTXT_PLACE = re.compile(r"at row (\d+), column (\d+)")


def _loadtxt(
    path: Path, block: list[str], used: list[str], usecols: list[int], row_offset: int, lines,
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
        # numpy names the block's row (from 0) and the file's column (from 1): say it
        # our way, with the cell (a letter outside ASCII in a number column, say)
        m = _LOADTXT_PLACE.search(str(e))
        if m and int(m.group(1)) < len(block) and int(m.group(2)) - 1 in usecols:
            i, c = int(m.group(1)), int(m.group(2)) - 1
            try:
                cell = next(csv.reader([block[i]]))[c].strip()
            except (csv.Error, IndexError):
                cell = "?"
            raise _row_error(path, row_offset + i, lines,
                             f"column {clipped_repr(used[usecols.index(c)])}: "
                             f"{clipped_repr(cell)} is not a number") from None
        raise RecordingError(
            f"{path}: cannot parse rows {row_offset + 1}..{row_offset + len(block)}: "
            f"{clipped_repr(str(e), 80)}"
        ) from None


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
    ic: np.ndarray,
    fc: np.ndarray,
    row_offset: int,
    lines,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The integer columns ``ic``' values, the float columns ``fc``' values and the empty
    mask (all columns) of one block of cells."""
    empty = cells == b""
    ints = np.zeros((cells.shape[0], ic.size), np.int64)
    floats = np.zeros((cells.shape[0], fc.size), np.float64)
    if ic.size:
        sub = cells[:, ic]
        v, ok = _parse_ints(sub)
        ints[:] = v
        slow = ~ok & ~empty[:, ic]
        for i, j in zip(*np.nonzero(slow), strict=True):  # rare: anything int() accepts
            ints[i, j] = _convert(path, names[ic[j]], sub[i, j], int, row_offset + i, lines)
    if fc.size:
        sub = np.where(empty[:, fc], b"0", cells[:, fc])
        try:
            floats[:] = sub.astype(np.float64)
        except ValueError:
            for i, j in zip(*np.nonzero(~empty[:, fc]), strict=True):
                floats[i, j] = _convert(path, names[fc[j]], sub[i, j], float, row_offset + i, lines)
    return ints, floats, empty


_INT64 = (-(2**63), 2**63 - 1)


def _text(cell: bytes) -> str:
    """A parsed cell as the file wrote it: numpy stores the characters below 256 of a
    byte-string cell one byte each (latin-1); any other makes it fail earlier."""
    return cell.decode("latin-1")


def _convert(path: Path, name: str, cell: bytes, conv: type, row0: int, lines):
    try:
        value = conv(cell)
    except ValueError:
        kind = "an integer (raw counts)" if conv is int else "a number"
        raise _row_error(
            path, row0, lines, f"column {clipped_repr(name)}: {clipped_repr(_text(cell))} is not {kind}"
        ) from None
    if conv is int and not _INT64[0] <= value <= _INT64[1]:
        raise _row_error(
            path, row0, lines,
            f"column {clipped_repr(name)}: {clipped_repr(_text(cell))} is beyond any count "
            "(raw counts are 64-bit integers)",
        )
    return value


def read_csv(path: str | Path, limits: CsvLimits = DEFAULT_LIMITS) -> Recording:
    """Read a recording CSV (``shared/spec/recording-csv.md``) into a :class:`Recording`.

    Raises :class:`~sensors.samples.RecordingError` (a ``ValueError``) naming the file,
    row (1-based data row), line and column for a missing ``t`` column, an empty or
    non-increasing ``t``, a cell that is not a number (or not an integer in a count
    column, or one beyond 64 bits), a row with fewer or more cells than the header, and
    a row that fills only some of a stream's columns; and for a file beyond ``limits``
    (its size, a line, the header's columns, a used cell) or holding a NUL byte, as
    soon as that is met. Messages quote at most a few dozen characters of a value.
    Warns once (:class:`RecordingWarning`) naming the sensors left out because some of
    their columns are missing, and the first few unknown columns ignored.
    """
    path = Path(path)
    try:
        return _read_csv(path, limits)
    except UnicodeDecodeError as e:
        raise RecordingError(f"{path}: not UTF-8 text ({e.reason}); is it a recording CSV?") from None


def _read_csv(path: Path, limits: CsvLimits) -> Recording:
    with open(path, encoding="utf-8-sig", newline=None) as f:
        size = os.fstat(f.fileno()).st_size
        if size > limits.max_file_bytes:
            raise RecordingError(
                f"{path}: {size / 1e6:.0f} MB is more than the reader takes "
                f"({limits.max_file_bytes / 1e6:.0f} MB); split the recording"
            )
        source = _Lines(path, f, limits)
        header_line = source.next()
        while header_line and not header_line.strip():
            header_line = source.next()
        if not header_line:
            raise RecordingError(f"{path}: the file is empty; expected a header row starting with 't'")
        header_line_no = source.line
        try:
            header = [h.strip() for h in next(csv.reader([header_line]))]
        except csv.Error as e:
            raise RecordingError(f"{path}: line {header_line_no}: not a CSV header ({e})") from None
        if len(header) > limits.max_columns:
            raise RecordingError(
                f"{path}: the header has {len(header)} columns; the reader takes at most "
                f"{limits.max_columns} (is it a recording CSV?)"
            )
        if _T not in header:
            raise RecordingError(
                f"{path}: no column 't' in the header (line {header_line_no}): "
                f"{_some([clipped_repr(h) for h in header])}"
            )
        dup = sorted(h for h, k in Counter(header).items() if k > 1)
        if dup:
            raise RecordingError(
                f"{path}: the header repeats column(s) {_some([clipped_repr(h) for h in dup])}"
            )
        groups, used, incomplete, unknown = _streams_from_header(header, path)
        said = []
        if incomplete:
            said.append(f"incomplete sensor(s) left out: {_some(incomplete)}")
        if unknown:
            said.append(f"ignored {len(unknown)} unknown column(s): {_some(unknown)}")
        if said:
            warnings.warn(f"{path}: " + "; ".join(said), RecordingWarning, stacklevel=3)
        index = {c: i for i, c in enumerate(header)}
        used = sorted(used, key=index.__getitem__)
        usecols = [index[c] for c in used]
        col_of = {c: j for j, c in enumerate(used)}
        is_float = {_T: True}
        for g in groups:
            for c in g.columns:
                is_float[c] = g.kind in TRUTH_KINDS
        is_int = np.array([not is_float[c] for c in used], bool)
        ic, fc = np.flatnonzero(is_int), np.flatnonzero(~is_int)
        # where each used column's values are: (is it an int column, its index there)
        where = {c: (bool(is_int[j]), int(np.searchsorted(ic if is_int[j] else fc, j)))
                 for j, c in enumerate(used)}

        lines = array("q")  # the line number of each data row
        block_rows = max(1, min(_BLOCK_ROWS, _BLOCK_CELLS // max(len(used), 1)))
        int_parts: list[np.ndarray] = []
        float_parts: list[np.ndarray] = []
        empty_parts: list[np.ndarray] = []
        n_rows = 0
        while True:
            block: list[str] = []
            chars = 0
            while len(block) < block_rows and chars < _BLOCK_CHARS:
                text = source.next()
                if not text:
                    break
                if text.strip():
                    block.append(text)
                    lines.append(source.line)
                    chars += len(text)
            if not block:
                break
            _check_widths(path, block, len(header), n_rows, lines)
            cells = _strip(_parse_block(path, block, used, usecols, n_rows, lines, limits))
            del block
            ints, floats, empty = _parse_block_values(path, used, cells, ic, fc, n_rows, lines)
            int_parts.append(ints)
            float_parts.append(floats)
            empty_parts.append(empty)
            n_rows += len(cells)

    def joined(parts: list[np.ndarray], width: int, dtype) -> np.ndarray:
        out = np.concatenate(parts) if parts else np.zeros((0, width), dtype)
        parts.clear()  # the blocks go as soon as they are joined: memory stays ~ one copy
        return out

    all_ints = joined(int_parts, ic.size, np.int64)
    all_floats = joined(float_parts, fc.size, np.float64)
    all_empty = joined(empty_parts, len(used), bool)

    def column(c: str) -> np.ndarray:
        as_int, k = where[c]
        return all_ints[:, k] if as_int else all_floats[:, k]

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
        try:
            streams[g.name] = Stream(g.name, g.kind, t_s[every], values, g.columns)
        except ValueError as e:
            raise RecordingError(f"{path}: {e}") from None
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
