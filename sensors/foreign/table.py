"""What every foreign reader returns (:class:`ForeignColumns`), how a column is addressed
(:func:`parse_address`: ``NAME`` for a column vector, ``NAME[:, K]`` for column K of a 2-D
variable or dataset), and the checks every reader shares: a variable's shape and type, the
columns' common length, the size bound."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.sensors.samples import RecordingError, clipped_repr

MAX_FILE_BYTES = 4 * 1024**3
"""A foreign file larger than this is refused unread (the rig's 25-minute trials are 3 MB)."""
MAX_VALUES = 1 << 28
"""Values a variable may hold (2.1 GB as float64): one claiming more is refused unread."""


class ForeignFileError(RecordingError):
    """A foreign file, or a column of it, that cannot be read; the message names both."""


@dataclass(frozen=True)
class Address:
    """A column of a foreign file: a variable (dataset) ``name`` and, for a 2-D one, the
    column ``index`` (None: the variable is a column vector)."""

    name: str
    index: int | None

    def __str__(self) -> str:
        return self.name if self.index is None else f"{self.name}[:, {self.index}]"


_ADDRESS = re.compile(r"\s*([^\[\]]+?)\s*(?:\[\s*:\s*,\s*(\d{1,6})\s*\])?\s*")


def parse_address(text: str) -> Address:
    """``"imu_acc[:, 0]"`` -> ``Address("imu_acc", 0)``; ``"all_time"`` -> ``Address("all_time", None)``."""
    m = _ADDRESS.fullmatch(text) if isinstance(text, str) and len(text) <= 256 else None
    if m is None:
        raise ValueError(f"{clipped_repr(text)} is not a column: write NAME, or NAME[:, K] for "
                         "column K (from 0) of a 2-D variable")
    return Address(m.group(1), None if m.group(2) is None else int(m.group(2)))


@dataclass(frozen=True)
class ForeignColumns:
    """The columns read from a foreign file: ``columns[address]`` float64 ``(n_rows,)``,
    ``scalars[name]`` one number each, and every variable the file holds (for messages)."""

    source: Path
    n_rows: int
    columns: dict[str, np.ndarray]
    scalars: dict[str, float]
    available: tuple[str, ...]


def available_words(names: Sequence[str], first: int = 12) -> str:
    """The first few names a file holds, for a message."""
    shown = [clipped_repr(n) for n in names[:first]]
    more = len(names) - first
    return ", ".join(shown) + (f", … and {more} more" if more > 0 else "")


def unknown_column(path: Path, address: Address | str, names: Sequence[str]) -> ForeignFileError:
    return ForeignFileError(f"{path}: no column {clipped_repr(str(address))}; the file has "
                            f"{available_words(list(names))}")


def check_variable(path: Path, address: Address, shape: tuple[int, ...], dtype: np.dtype) -> int:
    """The number of rows of column ``address`` of a variable of ``shape`` and ``dtype``,
    refusing a type that is not numbers, a shape that is not a column (or its index out of
    it), and a variable of more than :data:`MAX_VALUES` values (a reader may load it whole)."""
    where = f"{path}: column {clipped_repr(str(address))}"
    if np.dtype(dtype).kind not in "biuf":
        raise ForeignFileError(f"{where} holds {clipped_repr(str(dtype), 20)[1:-1]} values, not numbers")
    dims = [d for d in shape if d != 1] if len(shape) <= 2 else list(shape)
    if address.index is None:
        if len(dims) > 1:
            raise ForeignFileError(f"{where} is a {' x '.join(map(str, shape))} array: name one column "
                                   f"of it as {address.name}[:, K] (K from 0)")
        n = dims[0] if dims else int(np.prod(shape, dtype=np.int64))
    else:
        if len(shape) != 2:
            raise ForeignFileError(f"{where}: [:, K] takes a 2-D variable; this one is "
                                   f"{' x '.join(map(str, shape)) or 'a scalar'}")
        if address.index >= shape[1]:
            raise ForeignFileError(f"{where}: the variable has {shape[1]} columns (K from 0 to "
                                   f"{shape[1] - 1})")
        n = shape[0]
    total = int(np.prod(shape, dtype=np.float64))
    if total > MAX_VALUES:
        raise ForeignFileError(f"{where}: its variable holds {total} values; the import takes at most "
                               f"{MAX_VALUES} a variable")
    return int(n)


def check_size(path: Path) -> None:
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ForeignFileError(f"{path}: {size / 1e9:.1f} GB is more than the import reads "
                               f"({MAX_FILE_BYTES / 1e9:.1f} GB); split the recording")


def same_length(path: Path, columns: dict[str, np.ndarray]) -> int:
    """The columns' common length, or :class:`ForeignFileError` naming two that differ."""
    lengths = {k: v.shape[0] for k, v in columns.items()}
    if not lengths:
        return 0
    first = next(iter(lengths))
    for k, n in lengths.items():
        if n != lengths[first]:
            raise ForeignFileError(f"{path}: column {clipped_repr(k)} has {n} rows but "
                                   f"{clipped_repr(first)} has {lengths[first]}; the columns of a "
                                   "recording are sampled together")
    return lengths[first]


def scalar_value(path: Path, name: str, value: np.ndarray) -> float:
    """One number of a variable that must hold exactly one (the rig's ``data_line``)."""
    v = np.asarray(value)
    if v.dtype.kind not in "biuf" or v.size != 1:
        raise ForeignFileError(f"{path}: {clipped_repr(name)} should be one number; it is "
                               f"{' x '.join(map(str, v.shape)) or 'a scalar'} of {v.dtype}")
    return float(v.reshape(-1)[0])
