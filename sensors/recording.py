"""Read or write a recording, as CSV or MCAP by the file's suffix."""

from __future__ import annotations

import warnings
from pathlib import Path

from sensors.recording_csv import RecordingWarning, read_csv, write_csv
from sensors.recording_mcap import read_mcap, write_mcap
from sensors.samples import Recording, RecordingError

__all__ = ["SUFFIXES", "RecordingError", "RecordingWarning", "read_recording", "write_recording"]

SUFFIXES = (".csv", ".mcap")


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(
            f"{path}: unknown recording suffix {path.suffix or '(none)'!r}; "
            f"expected {' or '.join(SUFFIXES)}"
        )
    return suffix


def read_recording(path: str | Path) -> Recording:
    """Read a ``.csv`` or ``.mcap`` recording.

    A file that is not a readable recording raises
    :class:`~sensors.samples.RecordingError` (a ``ValueError``) naming the place.
    For MCAP the :class:`~sensors.recording_mcap.ReadReport` is in
    ``rec.meta["read_report"]``, and a :class:`RecordingWarning` says what was lost
    when the file ends early or is damaged.
    """
    path = Path(path)
    if _suffix(path) == ".csv":
        return read_csv(path)
    rec, report = read_mcap(path)
    if not report.complete:
        warnings.warn(report.message, RecordingWarning, stacklevel=2)
    return Recording(rec.streams, {**rec.meta, "read_report": report})


def write_recording(rec: Recording, path: str | Path) -> None:
    """Write ``rec`` as ``.csv`` or ``.mcap``, by the suffix of ``path``."""
    path = Path(path)
    if _suffix(path) == ".csv":
        write_csv(rec, path)
    else:
        write_mcap(rec, path)
