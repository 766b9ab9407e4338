"""Recording CSV: read and write the plain-text interchange format.

The format is ``shared/spec/recording-csv.md``: one header row, then one row per
sample instant; an empty cell means that sensor was not sampled at that instant.
The spec's raw columns hold integer counts; this reader is a superset: a raw column may
also hold finite decimals (a sensor that delivers its values in g or deg/s, the unit its
sensor description in the config declares), and the stream then holds floats
(:class:`~armfusion.sensors.samples.Stream`); ``nan``/``inf`` there is refused.
Each stream takes the rows where *all* of its columns are filled; a row with only
some of them filled is an error, and so is a row with fewer or more cells than the
header. One :class:`RecordingWarning` names the sensors left out because only some of
their columns are there, and the first few unknown columns ignored.

Which columns make which stream (see :mod:`armfusion.sensors.samples`):

- ``t``: the time of the row in seconds, strictly increasing;
- ``P_x, P_y, P_z`` for any prefix ``P`` (not ``imu``/``imu_*``/``true_*``): the link
  accelerometer stream ``P``;
- ``imu_ax..az``, ``imu_gx..gz``, ``imu_mx..mz``, ``imu_temp``: the IMU streams;
- ``P_gx, P_gy, P_gz`` for a prefix ``P`` as above: the link gyroscope stream ``P_gyro``
  (kind ``link_gyro``; beyond the shared spec);
- ``enc1 .. encN`` (contiguous from 1): the stream ``enc``;
- ``true_q1 .. true_qN`` (contiguous from 1): ``true_q``; ``true_roll, true_pitch,
  true_yaw``: ``true_base``.

Parsing is column-wise with numpy (``np.loadtxt`` on fixed-width byte strings, in
blocks: :mod:`armfusion.sensors.csv_blocks`), so a one-hour, 100 Hz, 30-column file reads in a few
seconds; the columns of each stream are :mod:`armfusion.sensors.csv_header`.

The reader bounds its work (:class:`CsvLimits`: file size, line length, header
columns, the length of a cell in use; a NUL byte is refused), so that a broken or
hostile file is refused with a :class:`~armfusion.sensors.samples.RecordingError` naming the
place, within bounded time and memory, as soon as the problem is met
(``docs/reference/refusals.md``).
"""

from __future__ import annotations

import warnings
from array import array
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.sensors.csv_blocks import (
    BLOCK_ROWS,
    DEFAULT_LIMITS,
    CsvLimits,
    parse_rows,
    read_header,
    row_error,
)
from armfusion.sensors.csv_header import T_COLUMN, StreamColumns, csv_columns, first_few, streams_from_header
from armfusion.sensors.output_files import replaced_when_done
from armfusion.sensors.sample_checks import CSV_ROW_LINES, CSV_ROW_TIMES
from armfusion.sensors.samples import TRUTH_KINDS, Recording, RecordingError, Stream, clipped_repr

__all__ = [
    "DEFAULT_LIMITS",
    "CsvLimits",
    "RecordingError",
    "RecordingWarning",
    "csv_columns",
    "read_csv",
    "write_csv",
]


class RecordingWarning(UserWarning):
    """A recording was read, but part of it was ignored or lost (said in the message)."""


def read_csv(path: str | Path, limits: CsvLimits = DEFAULT_LIMITS) -> Recording:
    """Read a recording CSV (``shared/spec/recording-csv.md``) into a :class:`Recording`.

    Raises :class:`~armfusion.sensors.samples.RecordingError` (a ``ValueError``) naming the file,
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


def _check_header(path: Path, header: list[str], header_line_no: int) -> None:
    """A ``RecordingError`` for a header without ``t`` or one that repeats a column."""
    if T_COLUMN not in header:
        raise RecordingError(
            f"{path}: no column 't' in the header (line {header_line_no}): "
            f"{first_few([clipped_repr(h) for h in header])}"
        )
    dup = sorted(h for h, k in Counter(header).items() if k > 1)
    if dup:
        raise RecordingError(
            f"{path}: the header repeats column(s) {first_few([clipped_repr(h) for h in dup])}"
        )


def _warn_left_out(path: Path, incomplete: list[str], unknown: list[str]) -> None:
    """The one :class:`RecordingWarning` naming the incomplete sensors and the first few
    unknown columns, pointing at the caller of :func:`read_csv`."""
    said = []
    if incomplete:
        said.append(f"incomplete sensor(s) left out: {first_few(incomplete)}")
    if unknown:
        said.append(f"ignored {len(unknown)} unknown column(s): {first_few(unknown)}")
    if said:
        warnings.warn(f"{path}: " + "; ".join(said), RecordingWarning, stacklevel=4)


@dataclass(frozen=True)
class _ColumnLayout:
    """Where each used column is read from: its index among the used columns (the empty
    mask's), and whether it is an integer column with its index among those (else among
    the float columns)."""

    used: list[str]
    usecols: list[int]
    col_of: dict[str, int]
    where: dict[str, tuple[bool, int]]
    int_cols: np.ndarray
    float_cols: np.ndarray

    @classmethod
    def of(cls, header: list[str], used: list[str], groups: list[StreamColumns]) -> _ColumnLayout:
        """The layout of the ``used`` columns of ``header`` (truth columns and ``t`` read as
        floats, the raw ones as integers)."""
        index = {c: i for i, c in enumerate(header)}
        used = sorted(used, key=index.__getitem__)
        is_float = {T_COLUMN: True}
        for g in groups:
            for c in g.columns:
                is_float[c] = g.kind in TRUTH_KINDS
        is_int = np.array([not is_float[c] for c in used], bool)
        ic, fc = np.flatnonzero(is_int), np.flatnonzero(~is_int)
        where = {c: (bool(is_int[j]), int(np.searchsorted(ic if is_int[j] else fc, j)))
                 for j, c in enumerate(used)}
        return cls(used, [index[c] for c in used], {c: j for j, c in enumerate(used)}, where, ic, fc)


@dataclass(frozen=True)
class _Rows:
    """The parsed data rows: the integer, decimal and float columns' values, the empty mask
    of the used columns, and each row's line number."""

    layout: _ColumnLayout
    ints: np.ndarray
    decimals: np.ndarray | None
    floats: np.ndarray
    empty: np.ndarray
    lines: array

    def column(self, c: str) -> np.ndarray:
        """Column ``c``'s values (a raw column that holds decimals, as its decimals)."""
        as_int, k = self.layout.where[c]
        if not as_int:
            return self.floats[:, k]
        if self.decimals is not None and not np.isnan(self.decimals[:1, k]).all():
            return self.decimals[:, k]  # a raw column that holds decimals
        return self.ints[:, k]

    def filled(self, columns: tuple[str, ...]) -> np.ndarray:
        """``(rows, len(columns))``: where each of ``columns`` holds a value."""
        return ~self.empty[:, [self.layout.col_of[c] for c in columns]]


def _row_times(path: Path, rows: _Rows) -> np.ndarray:
    """The ``t`` column, checked: filled, finite and strictly increasing in every row."""
    t_s = rows.column(T_COLUMN)
    t_empty = rows.empty[:, rows.layout.col_of[T_COLUMN]]
    if t_empty.any():
        raise row_error(path, int(np.argmax(t_empty)), rows.lines, "t is empty; every row needs a time")
    if not np.all(np.isfinite(t_s)):
        i = int(np.argmax(~np.isfinite(t_s)))
        raise row_error(path, i, rows.lines, f"t = {float(t_s[i])!r} is not a finite time")
    bad = np.flatnonzero(np.diff(t_s) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise row_error(
            path,
            i,
            rows.lines,
            f"t must increase from row to row, but t = {float(t_s[i])!r} follows "
            f"t = {float(t_s[i - 1])!r} at row {i} (line {rows.lines[i - 1]})",
        )
    return t_s


def _stream(path: Path, rows: _Rows, g: StreamColumns, t_s: np.ndarray) -> Stream:
    """Stream ``g`` from the rows that fill all its columns (a ``RecordingError`` naming the
    first row that fills only some)."""
    filled = rows.filled(g.columns)
    every = filled.all(axis=1)
    partial = filled.any(axis=1) & ~every
    if partial.any():
        i = int(np.argmax(partial))
        have = [c for c, f_ in zip(g.columns, filled[i], strict=True) if f_]
        miss = [c for c, f_ in zip(g.columns, filled[i], strict=True) if not f_]
        raise row_error(
            path,
            i,
            rows.lines,
            f"stream {g.name!r} has {', '.join(have)} but column(s) {', '.join(miss)} "
            "empty; a sensor's columns must be all filled or all empty",
        )
    values = np.stack([rows.column(c)[every] for c in g.columns], axis=1)
    try:
        return Stream(g.name, g.kind, t_s[every], values, g.columns)
    except ValueError as e:
        raise RecordingError(f"{path}: {e}") from None


def _read_csv(path: Path, limits: CsvLimits) -> Recording:
    """:func:`read_csv`'s work: the header, its streams, the rows, each stream checked."""
    with open(path, encoding="utf-8-sig", newline=None) as f:
        source, header, header_line_no = read_header(
            path, f, limits, "expected a header row starting with 't'", " (is it a recording CSV?)")
        _check_header(path, header, header_line_no)
        groups, used, incomplete, unknown = streams_from_header(header, path)
        _warn_left_out(path, incomplete, unknown)
        layout = _ColumnLayout.of(header, used, groups)
        rows = _Rows(layout, *parse_rows(path, source, len(header), layout.used, layout.usecols,
                                         layout.int_cols, layout.float_cols, limits))
    t_s = _row_times(path, rows)
    streams = {g.name: _stream(path, rows, g, t_s) for g in groups}
    return Recording(streams, meta={"source": str(path), CSV_ROW_TIMES: t_s, CSV_ROW_LINES: rows.lines})


# ---------------------------------------------------------------------------- writing


def _cells(stream: Stream) -> list[str]:
    """One text per sample: the stream's cells joined by commas (counts as integers, raw
    decimals with the shortest text that reads back to the same float)."""
    fmt = "%.10g".__mod__ if stream.kind in TRUTH_KINDS else str
    per_channel = [list(map(fmt, stream.values[:, j].tolist())) for j in range(stream.values.shape[1])]
    return list(map(",".join, zip(*per_channel, strict=True)))


def write_csv(rec: Recording, path: str | Path) -> None:
    """Write ``rec`` as a recording CSV.

    All streams are merged onto the union of their time instants (one row per
    instant, in time order); a stream's cells are empty where it was not sampled.
    ``t`` is written with the shortest text that reads back to the same float (so
    reading the file gives the same instants), counts as integers, raw values that are
    not whole numbers (a sensor delivering g, say) as the shortest text that reads back
    to the same float, ground truth with 10 significant digits.
    """
    path = Path(path)
    streams = list(rec.streams.values())
    header = [T_COLUMN]
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
    with replaced_when_done(path) as tmp, open(tmp, "w", encoding="utf-8", newline="") as f:
        f.write(",".join(header) + "\n")
        for start in range(0, n, BLOCK_ROWS):
            rows = zip(*(c[start : start + BLOCK_ROWS] for c in columns), strict=True)
            f.write("\n".join(map(",".join, rows)))
            f.write("\n")
