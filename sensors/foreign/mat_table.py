"""The columns of a MATLAB ``.mat`` file (v5, through :func:`scipy.io.loadmat`): each
variable a column vector ``(N, 1)`` (or ``(1, N)``), or a 2-D matrix whose columns are named
``NAME[:, K]``. The variables' shapes and types are checked from the file's directory
(:func:`scipy.io.whosmat`) before anything is loaded, and only the variables named are."""

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

_MAT_TYPES = {"double": "f8", "single": "f4", "int8": "i1", "int16": "i2", "int32": "i4", "int64": "i8",
              "uint8": "u1", "uint16": "u2", "uint32": "u4", "uint64": "u8", "logical": "b1"}


def read_mat_columns(path: Path, columns: Sequence[str], scalars: Sequence[str] = ()) -> ForeignColumns:
    import scipy.io

    check_size(path)
    try:
        directory = scipy.io.whosmat(str(path))
    except NotImplementedError:
        raise ForeignFileError(f"{path}: a MATLAB v7.3 file (HDF5 inside): save it with -v7, or "
                               "import it as .h5") from None
    except Exception as e:  # scipy's own errors for a file that is not .mat
        raise ForeignFileError(f"{path}: not a MATLAB .mat file ({type(e).__name__})") from None
    shapes = {name: (tuple(shape), cls) for name, shape, cls in directory}
    addresses = {c: parse_address(c) for c in columns}
    for c, a in addresses.items():
        if a.name not in shapes:
            raise unknown_column(path, c, list(shapes))
        shape, cls = shapes[a.name]
        check_variable(path, a, shape, np.dtype(_MAT_TYPES.get(cls, "O")))
    for name in scalars:
        if name not in shapes:
            raise unknown_column(path, name, list(shapes))
    wanted = sorted({a.name for a in addresses.values()} | set(scalars))
    data = scipy.io.loadmat(str(path), variable_names=wanted)
    out = {}
    for c, a in addresses.items():
        v = np.asarray(data[a.name])
        out[c] = (v.reshape(-1) if a.index is None else v[:, a.index]).astype(np.float64)
    values = {name: scalar_value(path, name, data[name]) for name in scalars}
    return ForeignColumns(path, same_length(path, out), out, values, tuple(shapes))
