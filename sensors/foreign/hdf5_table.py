"""The columns of an HDF5 file (through h5py): each dataset a vector ``(N,)`` (or
``(N, 1)``), or a 2-D ``(N, k)`` one whose columns are named ``NAME[:, K]`` (the BROAD
files' ``imu_acc[:, 0]``); a dataset in a group is named by its path (``group/name``).
Shapes and types are checked from the datasets' headers before anything is read, and
only the columns named are read. A scalar is a dataset or a file attribute of one value."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from armfusion.sensors.foreign.table import (
    ForeignColumns,
    ForeignFileError,
    check_size,
    check_variable,
    parse_address,
    same_length,
    scalar_value,
    unknown_column,
)

_MAX_LISTED = 200  # datasets listed for a message at most


def read_hdf5_columns(path: Path, columns: Sequence[str], scalars: Sequence[str] = ()) -> ForeignColumns:
    import h5py

    check_size(path)
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise ForeignFileError(f"{path}: not an HDF5 file") from None
    with f:
        names: list[str] = []

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                names.append(name)
            return None if len(names) < _MAX_LISTED else True

        f.visititems(visit)
        out = {}
        for c in columns:
            a = parse_address(c)
            ds = f.get(a.name)
            if not isinstance(ds, h5py.Dataset):
                raise unknown_column(path, c, names)
            check_variable(path, a, tuple(ds.shape), ds.dtype)
            v = ds[()] if a.index is None else ds[:, a.index]
            out[c] = np.asarray(v).reshape(-1).astype(np.float64)
        values = {}
        for name in scalars:
            ds = f.get(name)
            if isinstance(ds, h5py.Dataset) and ds.size == 1:
                values[name] = scalar_value(path, name, ds[()])
            elif name in f.attrs:
                values[name] = scalar_value(path, name, np.asarray(f.attrs[name]))
            else:
                raise unknown_column(path, name, names + [f"(attribute) {k}" for k in f.attrs])
    return ForeignColumns(path, same_length(path, out), out, values, tuple(names))
