"""The columns of a foreign CSV file: a header row of names, then rows of numbers; an empty
cell (or ``NaN``) is a value not recorded, read as NaN. Read with the recording CSV's bounded
block parser (:mod:`armfusion.sensors.csv_blocks`: the same :class:`~armfusion.sensors.csv_blocks.CsvLimits`,
the same messages naming row, line and column), only the columns named. A CSV has no
scalars: a start row is given as a number in the column map."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from armfusion.sensors.csv_blocks import DEFAULT_LIMITS, CsvLimits, parse_rows, read_header
from armfusion.sensors.foreign.table import ForeignColumns, ForeignFileError, parse_address, unknown_column
from armfusion.sensors.samples import clipped_repr


def read_csv_columns(path: Path, columns: Sequence[str], scalars: Sequence[str] = (),
                     limits: CsvLimits = DEFAULT_LIMITS) -> ForeignColumns:
    if scalars:
        raise ForeignFileError(f"{path}: a CSV holds no variable {clipped_repr(scalars[0])}; give the "
                               "start row as a number")
    try:
        with open(path, encoding="utf-8-sig", newline=None) as f:
            source, header, _ = read_header(path, f, limits, "expected a header row of column names")
            twice = {h for h, k in Counter(header).items() if k > 1}
            used: list[str] = []
            for c in columns:
                a = parse_address(c)
                if a.index is not None or a.name not in header:
                    raise unknown_column(path, c, header)
                if a.name in twice:
                    raise ForeignFileError(f"{path}: the header names {clipped_repr(a.name)} twice")
                if a.name not in used:
                    used.append(a.name)
            index = {h: i for i, h in enumerate(header)}
            used.sort(key=index.__getitem__)
            usecols = [index[c] for c in used]
            _, _, floats, empty, _ = parse_rows(path, source, len(header), used, usecols,
                                                np.zeros(0, np.intp), np.arange(len(used)), limits)
    except UnicodeDecodeError as e:
        raise ForeignFileError(f"{path}: not UTF-8 text ({e.reason})") from None
    floats[empty] = np.nan
    out = {c: floats[:, used.index(parse_address(c).name)].copy() for c in columns}
    return ForeignColumns(path, floats.shape[0], out, {}, tuple(header))
