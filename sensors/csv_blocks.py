"""The recording CSV reader's bounded parsing: :class:`CsvLimits` (what it refuses), a line
source that never reads past a line's limit (:class:`LineReader`), and the rows parsed in
blocks, column-wise with numpy (``np.loadtxt`` on fixed-width byte strings, integers by a
vectorised digit parser; :func:`parse_rows`), every error naming the row, line and
column, quoting at most a few dozen characters.

Raw columns hold integer counts (the shared spec) or, beyond the spec, finite decimal
values (a sensor that delivers g or deg/s): a raw column of a block that holds a cell
that is not an integer is parsed as floats, whole column at once; ``nan`` or ``inf`` in a
raw column is refused (an empty cell is how a recording says "not sampled").
"""

from __future__ import annotations

import csv
import io
import os
import re
import warnings
from array import array
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.sensors.samples import RecordingError, clipped_repr

BLOCK_ROWS = 65536  # rows parsed per np.loadtxt call at most (and written per write)
_BLOCK_CELLS = 1 << 19  # and cells: a block's parse takes ~ 100 B a cell (~50 MB)
_BLOCK_CHARS = 1 << 24  # and characters of text held at once
_CELL_BYTES = 32  # fixed cell width for parsing; wider cells trigger a re-parse to the limit
_ECHO_START = 16  # characters of a too-long cell quoted in its message


@dataclass(frozen=True)
class CsvLimits:
    """What :func:`read_csv` refuses, so that a broken or hostile file costs bounded time
    and memory (``docs/reference/refusals.md``). Each is far above what a
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


class LineReader:
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


def read_header(path: Path, f: io.TextIOBase, limits: CsvLimits, empty_hint: str,
                too_wide_hint: str = "") -> tuple[LineReader, list[str], int]:
    """The line source of an open CSV file, its header row's names (stripped) and that row's
    line number; refuses a file over ``limits.max_file_bytes`` unread, an empty one (saying
    ``empty_hint``), a header that is not CSV and one of more than ``limits.max_columns``."""
    size = os.fstat(f.fileno()).st_size
    if size > limits.max_file_bytes:
        raise RecordingError(
            f"{path}: {size / 1e6:.0f} MB is more than the reader takes "
            f"({limits.max_file_bytes / 1e6:.0f} MB); split the recording"
        )
    source = LineReader(path, f, limits)
    header_line = source.next()
    while header_line and not header_line.strip():
        header_line = source.next()
    if not header_line:
        raise RecordingError(f"{path}: the file is empty; {empty_hint}")
    try:
        header = [h.strip() for h in next(csv.reader([header_line]))]
    except csv.Error as e:
        raise RecordingError(f"{path}: line {source.line}: not a CSV header ({e})") from None
    if len(header) > limits.max_columns:
        raise RecordingError(
            f"{path}: the header has {len(header)} columns; the reader takes at most "
            f"{limits.max_columns}{too_wide_hint}"
        )
    return source, header, source.line


def row_error(path: Path, row0: int, lines, what: str) -> RecordingError:
    return RecordingError(f"{path}: row {row0 + 1} (line {lines[row0]}): {what}")


def check_widths(path: Path, block: list[str], n_header: int, row_offset: int, lines) -> None:
    """Every row has as many cells as the header: more is refused as well as fewer (an
    extra cell shifts every later one into the wrong column)."""
    commas = np.fromiter((text.count(",") for text in block), np.int64, len(block))
    quoted = np.fromiter(('"' in text for text in block), bool, len(block))
    for i in np.flatnonzero((commas != n_header - 1) | quoted):
        try:
            n = len(next(csv.reader([block[i]])))
        except csv.Error as e:
            raise row_error(path, row_offset + int(i), lines, f"not a CSV row ({e})") from None
        if n != n_header:
            raise row_error(path, row_offset + int(i), lines,
                             f"{n} cells, but the header has {n_header} columns")


def parse_block(
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
            raise row_error(
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
            raise row_error(path, row_offset + i, lines,
                             f"column {clipped_repr(used[usecols.index(c)])}: "
                             f"{clipped_repr(cell)} is not a number") from None
        raise RecordingError(
            f"{path}: cannot parse rows {row_offset + 1}..{row_offset + len(block)}: "
            f"{clipped_repr(str(e), 80)}"
        ) from None


def strip_cells(cells: np.ndarray) -> np.ndarray:
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


def parse_block_values(
    path: Path,
    names: list[str],
    cells: np.ndarray,
    ic: np.ndarray,
    fc: np.ndarray,
    row_offset: int,
    lines,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """One block of cells: the raw columns ``ic``' values as integers, the same as floats
    where a column holds a decimal (``None`` when none does; a column of whole numbers only
    is left as integers), the float columns ``fc``' values and the empty mask (all
    columns)."""
    empty = cells == b""
    ints = np.zeros((cells.shape[0], ic.size), np.int64)
    decimals: np.ndarray | None = None
    floats = np.zeros((cells.shape[0], fc.size), np.float64)
    if ic.size:
        sub = cells[:, ic]
        v, ok = _parse_ints(sub)
        ints[:] = v
        slow = ~ok & ~empty[:, ic]
        for j in np.flatnonzero(slow.any(axis=0)):  # a column with a cell int() or float() takes
            col = _raw_column(path, names[ic[j]], sub[:, j], empty[:, ic[j]], slow[:, j], row_offset,
                              lines)
            if isinstance(col, np.ndarray):
                if decimals is None:
                    decimals = np.full(ints.shape, np.nan)
                decimals[:, j] = col
            else:
                for i, value in col.items():
                    ints[i, j] = value
    if fc.size:
        sub = np.where(empty[:, fc], b"0", cells[:, fc])
        try:
            if _has_underscore(sub):
                raise ValueError  # numpy reads 2_59 as 259: the cells one by one say where
            floats[:] = sub.astype(np.float64)
        except ValueError:
            for i, j in zip(*np.nonzero(~empty[:, fc]), strict=True):
                floats[i, j] = _convert(path, names[fc[j]], sub[i, j], float, row_offset + i, lines)
    return ints, decimals, floats, empty


def _raw_column(path: Path, name: str, col: np.ndarray, empty: np.ndarray, slow: np.ndarray,
                row_offset: int, lines):
    """A raw column of one block whose fast integer parse failed somewhere: ``{row: count}``
    for the cells that ``int()`` reads (``1_000``, ``+0``…) when all of them are integers, or
    the whole column as floats (empty cells NaN) when one is a decimal; a cell that is
    neither, or not finite, is refused naming its row."""
    as_ints: dict[int, int] = {}
    decimal = False
    for i in np.flatnonzero(slow):
        cell = col[i]
        if not decimal and not (b"." in cell or b"e" in cell.lower() or b"n" in cell.lower()):
            as_ints[int(i)] = _convert(path, name, cell, int, row_offset + int(i), lines)
            continue
        value = _convert(path, name, cell, float, row_offset + int(i), lines)
        if not np.isfinite(value):
            raise row_error(path, row_offset + int(i), lines,
                            f"column {clipped_repr(name)}: {clipped_repr(_text(cell))} is not a finite "
                            "value (leave the cell empty where the sensor was not sampled)")
        decimal = True
        break
    if not decimal:
        return as_ints
    try:
        if _has_underscore(col):
            raise ValueError
        out = np.where(empty, b"nan", col).astype(np.float64)
    except ValueError:
        out = np.array([np.nan if e else _convert(path, name, c, float, row_offset + i, lines)
                        for i, (c, e) in enumerate(zip(col, empty, strict=True))])
    bad = ~np.isfinite(out) & ~empty
    if bad.any():
        i = int(np.argmax(bad))
        raise row_error(path, row_offset + i, lines,
                        f"column {clipped_repr(name)}: {clipped_repr(_text(col[i]))} is not a finite "
                        "value (leave the cell empty where the sensor was not sampled)")
    return out


_INT64 = (-(2**63), 2**63 - 1)


def _has_underscore(cells: np.ndarray) -> bool:
    """Does a cell hold ``_`` (Python's digit grouping, which numpy and ``int`` read)?"""
    return bool(cells.size) and bool((np.char.find(cells, b"_") >= 0).any())


def _text(cell: bytes) -> str:
    """A parsed cell as the file wrote it: numpy stores the characters below 256 of a
    byte-string cell one byte each (latin-1); any other makes it fail earlier."""
    return cell.decode("latin-1")


def _convert(path: Path, name: str, cell: bytes, conv: type, row0: int, lines):
    try:
        if b"_" in cell:  # Python's literal syntax (2_59), not a number of a CSV
            raise ValueError
        value = conv(cell)
    except ValueError:
        kind = "an integer (raw counts) or a decimal" if conv is int else "a number"
        raise row_error(
            path, row0, lines, f"column {clipped_repr(name)}: {clipped_repr(_text(cell))} is not {kind}"
        ) from None
    if conv is int and not _INT64[0] <= value <= _INT64[1]:
        raise row_error(
            path, row0, lines,
            f"column {clipped_repr(name)}: {clipped_repr(_text(cell))} is beyond any count "
            "(raw counts are 64-bit integers)",
        )
    return value


def parse_rows(path: Path, source: LineReader, n_header: int, used: list[str], usecols: list[int],
               ic: np.ndarray, fc: np.ndarray, limits: CsvLimits,
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray, array]:
    """Every data row after the header, in blocks: the raw columns ``ic``' values as
    integers, and as floats the raw columns that hold a decimal somewhere (the others NaN
    there; ``None`` when no column does; see :func:`parse_block_values`), the float
    columns ``fc``' values, the empty
    mask of the ``used`` columns, and the line number of each row (blank lines skipped)."""
    lines = array("q")  # the line number of each data row
    block_rows = max(1, min(BLOCK_ROWS, _BLOCK_CELLS // max(len(used), 1)))
    int_parts: list[np.ndarray] = []
    decimal_parts: list[np.ndarray | None] = []
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
        check_widths(path, block, n_header, n_rows, lines)
        cells = strip_cells(parse_block(path, block, used, usecols, n_rows, lines, limits))
        del block
        ints, decimals, floats, empty = parse_block_values(path, used, cells, ic, fc, n_rows, lines)
        int_parts.append(ints)
        decimal_parts.append(decimals)
        float_parts.append(floats)
        empty_parts.append(empty)
        n_rows += len(cells)

    def joined(parts: list[np.ndarray], width: int, dtype) -> np.ndarray:
        out = np.concatenate(parts) if parts else np.zeros((0, width), dtype)
        parts.clear()  # the blocks go as soon as they are joined: memory stays ~ one copy
        return out

    all_decimals = None
    held = [d for d in decimal_parts if d is not None]
    if held:  # the raw columns that hold a decimal anywhere, as floats; the others stay integers
        is_decimal = np.any([~np.isnan(d).all(axis=0) for d in held], axis=0)
        all_decimals = joined([np.where(is_decimal, i, 0).astype(np.float64) if d is None
                               else np.where(np.isnan(d), i, d)
                               for i, d in zip(int_parts, decimal_parts, strict=True)],
                              ic.size, np.float64)
        all_decimals[:, ~is_decimal] = np.nan  # these columns are read from the integers
    decimal_parts.clear()
    return (joined(int_parts, ic.size, np.int64), all_decimals,
            joined(float_parts, fc.size, np.float64), joined(empty_parts, len(used), bool), lines)
