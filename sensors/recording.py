"""Read or write a recording, as CSV or MCAP by the file's suffix."""

from __future__ import annotations

import stat
import warnings
from pathlib import Path

from armfusion.sensors.recording_csv import RecordingWarning, read_csv, write_csv
from armfusion.sensors.recording_mcap import read_mcap, write_mcap
from armfusion.sensors.sample_checks import feed_problems, sample_place
from armfusion.sensors.samples import Recording, RecordingError

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
    :class:`~armfusion.sensors.samples.RecordingError` (a ``ValueError``) naming the place; so does
    one holding a sample the rules every door applies refuse (:func:`refuse_bad_samples`).
    For MCAP the :class:`~armfusion.sensors.recording_mcap.ReadReport` is in
    ``rec.meta["read_report"]``, and a :class:`RecordingWarning` says what was lost
    when the file ends early or is damaged, and another naming the sample topics left out
    (an unknown kind, no metadata).
    """
    path = Path(path)
    suffix = _suffix(path)
    if path.exists() and not stat.S_ISREG(path.stat().st_mode):  # (a FIFO would block, /dev/zero not end)
        raise RecordingError(f"{path}: not a regular file (a device, a FIFO, a directory); "
                             "a recording is a file")
    if suffix == ".csv":
        rec = read_csv(path)
    else:
        rec, report = read_mcap(path)
        if not report.complete and report.messages_read == 0:  # (an empty file, a cut header, a bad chunk)
            raise RecordingError(f"{report.message}; no message in it could be read")
        if not report.complete:
            warnings.warn(report.message, RecordingWarning, stacklevel=2)
        if report.left_out:
            warnings.warn(f"{path}: left out {report.left_out_words()}", RecordingWarning, stacklevel=2)
        rec = Recording(rec.streams, {**rec.meta, "read_report": report})
    refuse_bad_samples(rec, path)
    return rec


def refuse_bad_samples(rec: Recording, path: str | Path) -> None:
    """Raise :class:`RecordingError` at the first sample of ``rec`` the config-free rules
    refuse (:func:`armfusion.sensors.sample_checks.feed_problems`: a time beyond any clock, a value
    beyond the feed's range), naming the file, the place in it and the value."""
    problems = feed_problems(rec)
    if problems:
        p = problems[0]
        why = ("no ground truth can be that" if p.reason == "truth_not_finite"
               else "no sensor can have said that")
        raise RecordingError(f"{path}: {sample_place(rec, p.stream, p.index)}: {p.words}; "
                             f"{why}, so the recording is refused")


def write_recording(rec: Recording, path: str | Path) -> None:
    """Write ``rec`` as ``.csv`` or ``.mcap``, by the suffix of ``path``."""
    path = Path(path)
    if _suffix(path) == ".csv":
        write_csv(rec, path)
    else:
        write_mcap(rec, path)
