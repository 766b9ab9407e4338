"""Foreign recordings: the columns of another program's file, read as plain numbers.

A foreign file knows nothing of arms or streams: it is a table of named columns (a CSV with a
header, the column vectors of a MATLAB ``.mat`` v5 file, the datasets of an HDF5 file). The
import (:mod:`armfusion.fusion.importing`) names the columns it needs by their address
(:mod:`armfusion.sensors.foreign.table`), and :func:`read_columns` reads those, and only those, as
float64, bounded in size, naming the file and the column in every refusal.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from armfusion.sensors.foreign.table import ForeignColumns, ForeignFileError, parse_address

__all__ = ["SUFFIXES", "ForeignColumns", "ForeignFileError", "parse_address", "read_columns"]

SUFFIXES: dict[str, str] = {".csv": "CSV with a header row", ".mat": "MATLAB .mat v5",
                            ".h5": "HDF5", ".hdf5": "HDF5"}
"""The foreign files read, by suffix."""


def read_columns(path: str | Path, columns: Sequence[str], scalars: Sequence[str] = ()) -> ForeignColumns:
    """The ``columns`` (addresses: ``NAME`` or ``NAME[:, K]``) of the foreign file ``path``, each
    float64 ``(N,)`` (NaN where a CSV cell is empty), and the ``scalars`` (variables of one value,
    such as the rig's ``data_line``); :class:`ForeignFileError` naming the file and the column
    for an unknown column, one that is not numbers, columns of different lengths, a file too
    large, or a suffix not in :data:`SUFFIXES`."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ForeignFileError(f"{path}: unknown suffix {path.suffix or '(none)'!r}; the import reads "
                               + ", ".join(f"{k} ({v})" for k, v in SUFFIXES.items()))
    if not path.exists():
        raise ForeignFileError(f"{path}: no such file")
    if not path.is_file():  # (a FIFO would block, /dev/zero not end)
        raise ForeignFileError(f"{path}: not a regular file (a device, a FIFO, a directory); a recording "
                               "is a file")
    if suffix == ".csv":
        from armfusion.sensors.foreign.csv_table import read_csv_columns

        return read_csv_columns(path, columns, scalars)
    if suffix == ".mat":
        from armfusion.sensors.foreign.mat_table import read_mat_columns

        return read_mat_columns(path, columns, scalars)
    from armfusion.sensors.foreign.hdf5_table import read_hdf5_columns

    return read_hdf5_columns(path, columns, scalars)
