"""The import: a foreign file, a column map and an arm's config in; the arm's native
recording and a summary of every change out (:func:`import_recording`).

Order: the map is checked against the config before the file is read
(:func:`~armfusion.fusion.importing.to_stream.check_map_against`); the file's columns are read
(:func:`armfusion.sensors.foreign.read_columns`); rows before the start row are left out; the time
column is converted to seconds (or made from the rate); rows whose time does not increase
are dropped (:mod:`~armfusion.fusion.importing.stamps`); in each stream a row with a NaN in one of its
columns is a gap (that sensor not sampled then) and counted, an infinite value is refused;
the values are brought into the config's unit (:func:`~armfusion.fusion.importing.to_stream.convert_values`);
then every sample meets the admission every door applies (:mod:`armfusion.models.sample_admission`: a
value past its sensor's range, a time beyond any clock, is refused naming the file's row).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from armfusion.fusion.importing.column_map import ColumnMap, StreamSource
from armfusion.fusion.importing.stamps import FIRST_ROWS, copies_dropped, increasing_rows
from armfusion.fusion.importing.to_stream import ImportMapError, Target, check_map_against, convert_values
from armfusion.fusion.importing.to_stream import targets as targets_of
from armfusion.models.arm import ArmModel
from armfusion.models.sample_admission import admission_problems
from armfusion.sensors.foreign import SUFFIXES, read_columns
from armfusion.sensors.samples import Recording, Stream, clipped_repr
from armfusion.sensors.units import convert


@dataclass(frozen=True)
class ImportResult:
    """The recording made and what the import did: ``summary`` (JSON-ready) and ``changes``,
    one sentence per change to the source's data (rows left out, gaps, rounding)."""

    recording: Recording
    summary: dict
    changes: tuple[str, ...]
    lost: int = 0
    """Rows (a bag's messages) left out for their time that were not copies of the one before:
    samples the recording does not hold."""


class Origin(NamedTuple):
    """Where a stream's values came from, for the messages that refuse one of them."""

    rows: np.ndarray
    """The source's row of each value: a file's 1-based row, or a bag topic's message index from 0."""
    row_word: str
    """What a row is called in a message: ``"row"`` (a file's) or ``"message"`` (a bag's)."""
    source: str
    """The source as a message names it: the file, or the bag and its topic."""


def _start_index(cmap: ColumnMap, scalars: dict[str, float], n_rows: int, path: Path) -> int:
    """The 0-based index of the first data row."""
    if cmap.start_row_variable is not None:
        value = scalars[cmap.start_row_variable]
        what = f"{path}: the start row {cmap.start_row_variable} = {value!r}"
    elif cmap.start_row is not None:
        value = float(cmap.start_row)
        what = f"column map {cmap.source}: start_row {cmap.start_row}"
    else:
        return 0
    if value != int(value) or not 1 <= value <= max(n_rows, 1):
        raise ImportMapError(f"{what}: expected a row number from 1 to the file's {n_rows} rows")
    return int(value) - 1


def refuse_what_no_sensor_said(rec: Recording, arm: ArmModel, cmap: ColumnMap,
                               stream_rows: dict[str, np.ndarray], path: Path, row_word: str = "row") -> None:
    """The admission every door applies (:mod:`armfusion.models.sample_admission`): a value past the
    range of the config's sensor (or the feed's), a time beyond any clock or apart from the
    rest, refused naming the file's row and columns, or a bag's message (``row_word``) and
    fields (the other commands would refuse the recording written)."""
    problems = admission_problems(arm, rec)
    if problems:
        p = problems[0]
        row = int(stream_rows[p.stream][p.index]) if p.stream in stream_rows else p.index + 1
        cols = ", ".join(cmap.streams[p.stream].columns) if p.stream in cmap.streams else p.stream
        what = "fields" if row_word == "message" else "columns"
        topic = getattr(cmap.streams.get(p.stream), "topic", None)
        where = f"{row_word} {row}" + (f" of topic {topic}" if topic and row_word == "message" else "")
        why = (", and the next sample moves it back: a spike no joint makes"
               if p.reason == "encoder_jump" else "; no sensor the config describes can have said that")
        raise ImportMapError(f"{path}: {where} ({what} {cols}, stream {p.stream}): {p.words}{why} "
                             "(does the config describe the sensor that recorded it?)")


def _times(cmap: ColumnMap, cols, s: int, path: Path) -> tuple[np.ndarray, float | None]:
    """Every row's time from the start row on, in s (from the time column, or the rate), and
    the rate when the time comes from it."""
    if cmap.time_column is not None:
        t_all = convert(cols.columns[cmap.time_column][s:], cmap.time_unit, "s")
        if np.isinf(t_all).any():
            i = int(np.argmax(np.isinf(t_all)))
            raise ImportMapError(f"{path}: column {cmap.time_column}: row {s + i + 1} holds an infinite time")
        return t_all, None
    rate_hz = cmap.rate_hz if cmap.rate_hz is not None else cols.scalars[cmap.rate_variable]
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ImportMapError(f"{path}: {cmap.rate_variable} = {rate_hz!r} is not a rate in Hz")
    return np.arange(cols.n_rows - s) / rate_hz, rate_hz


def import_recording(src: str | Path, cmap: ColumnMap, arm: ArmModel, config: str) -> ImportResult:
    """Turn the foreign file ``src`` into ``arm``'s recording by ``cmap`` (see the module's
    docstring). Raises :class:`~armfusion.fusion.importing.to_stream.ImportMapError` (map against
    config or file) or :class:`~armfusion.sensors.foreign.ForeignFileError` (the file), both
    ``ValueError``, naming the stream, the column, the file and the unit."""
    path = Path(src)
    if cmap.is_bag:
        raise ImportMapError(f"column map {cmap.source} names topics and fields (a ROS bag's map), but "
                             f"{path} is not a ROS bag (a rosbag2 directory, .mcap, .db3, or a ROS 1 .bag)")
    targets = check_map_against(cmap, arm, config)
    cols = read_columns(path, cmap.columns(), cmap.scalars())
    n = cols.n_rows
    s = _start_index(cmap, cols.scalars, n, path)
    changes: list[str] = []
    if s:
        changes.append(f"left out the {s} row(s) before the start row {s + 1}")
    t_all, rate_hz = _times(cmap, cols, s, path)
    keep, stamps = increasing_rows(t_all, first_row=s + 1)
    changes.extend(stamps.words())
    dropped = stamps.not_increasing + stamps.no_time
    copies = copies_dropped(keep, [cols.columns[c][s:] for c in cmap.columns()])
    if not keep.any():
        why = (f"none of its {n - s} data row(s) has a usable time" if n > s
               else "no data row after the header")
        raise ImportMapError(f"{path}: no row to import: {why}")
    t_s = t_all[keep]
    rows = np.flatnonzero(keep) + s + 1  # the file's row of each kept row
    streams: dict[str, Stream] = {}
    stream_rows: dict[str, np.ndarray] = {}  # the file's row of each sample of each stream
    stream_summary: dict[str, dict] = {}
    for name, src_cols in cmap.streams.items():
        values = np.stack([cols.columns[c][s:][keep] for c in src_cols.columns], axis=1)
        streams[name], stream_summary[name] = stream_of(name, t_s, values, Origin(rows, "row", str(path)),
                                                        src_cols, targets[name], changes)
        stream_rows[name] = rows[~np.isnan(values).any(axis=1)]
    all_names = targets_of(arm)  # every stream the config describes
    not_mapped = [k for k, tg in all_names.items() if k not in cmap.streams and k not in cmap.absent
                  and not tg.needed]
    dt = np.diff(t_s)
    rec = Recording(streams, meta={"source": str(path), "arm_config": config})
    refuse_what_no_sensor_said(rec, arm, cmap, stream_rows, path)
    summary = {
        "source": str(path), "format": SUFFIXES[path.suffix.lower()], "map": cmap.source, "config": config,
        "rows": {"in_file": n, "start_row": s + 1, "before_start": s, "imported": int(keep.sum())},
        "time": {"column": cmap.time_column, "unit": cmap.time_unit if cmap.time_column else None,
                 "rate_hz": rate_hz, "t_start_s": float(t_s[0]) if t_s.size else None,
                 "t_end_s": float(t_s[-1]) if t_s.size else None,
                 "dt_median_s": float(np.median(dt)) if dt.size else None,
                 "dt_max_s": float(dt.max()) if dt.size else None, **stamps.as_json()},
        "streams": stream_summary,
        "absent": dict(cmap.absent),
        "not_mapped": not_mapped,
        "changes": changes,
        "dropped": {"rows": dropped, "copies": copies, "lost": dropped - copies},
    }
    return ImportResult(rec, summary, tuple(changes), dropped - copies)


def stream_of(name: str, t_s: np.ndarray, values: np.ndarray, origin: Origin,
              src_cols: StreamSource, t: Target, changes: list[str]) -> tuple[Stream, dict]:
    """Stream ``name`` from its source ``values (N, k)`` at ``t_s (N,)``: a row with a NaN is a
    gap (counted in ``changes``), an infinite value refused naming ``origin.rows[i]`` (the
    source's ``origin.row_word``: a file's 1-based row, a bag topic's message from 0), the values
    brought into the config's unit. Returns the stream and its summary (a value past the
    sensor's range is the admission's to refuse, :func:`refuse_what_no_sensor_said`)."""
    rows, row_word, source = origin
    inf = np.isinf(values)
    if inf.any():
        i, j = (int(x[0]) for x in np.nonzero(inf))
        raise ImportMapError(f"{source}: {'column' if row_word == 'row' else 'field'} {src_cols.columns[j]}: "
                             f"{row_word} {rows[i]} holds {clipped_repr(float(values[i, j]))}, not a value "
                             "(a sample not taken is NaN)")
    nan = np.isnan(values)
    gap, partly = nan.all(axis=1), nan.any(axis=1) & ~nan.all(axis=1)
    sampled = ~nan.any(axis=1)
    with np.errstate(over="ignore", invalid="ignore"):  # (said below, once)
        done = convert_values(values[sampled], src_cols, t, source)
    over = ~np.isfinite(done.values)
    if over.any():  # a finite value whose conversion overflows (1e308 deg in counts): not a reading
        i, j = (int(x[0]) for x in np.nonzero(over))
        where = f"{row_word} {rows[np.flatnonzero(sampled)[i]]}"
        what = "fields" if row_word == "message" else "columns"
        value = clipped_repr(float(values[sampled][i, j]))
        raise ImportMapError(f"{source}: {where} ({what} {', '.join(src_cols.columns)}, stream {name}): "
                             f"{t.channels[j]} = {value} {src_cols.unit} "
                             f"is beyond any {t.value_unit} a float holds; no sensor the config describes "
                             "can have said that")
    try:
        stream = Stream(name, t.kind, t_s[sampled], done.values, t.channels)
    except ValueError as e:
        raise ImportMapError(f"{source}: stream {name}: {e}") from None
    if gap.any() or partly.any():
        first = rows[np.flatnonzero(~sampled)[:FIRST_ROWS]].tolist()
        changes.append(f"{name}: {int(gap.sum())} {row_word}(s) NaN in every column and {int(partly.sum())} "
                       f"NaN in some of {', '.join(src_cols.columns)} kept as gaps (not sampled), "
                       f"first {row_word}s {', '.join(map(str, first))}")
    saturated = 0
    if t.model is not None and t.model.counts_min is not None and len(stream):
        saturated = int(t.model.saturated(stream.values).any(axis=1).sum())
    if done.rounding_max_counts is not None and done.rounding_max_counts > 1e-6:  # not float noise
        changes.append(f"{name}: rounded to whole counts by up to {done.rounding_max_counts:.3f} counts "
                       f"(rms {done.rounding_rms_counts:.3f})")
    return stream, {
        "kind": t.kind, "channels": list(t.channels), "columns": list(src_cols.columns),
        "from_unit": src_cols.unit, "to_unit": t.value_unit, "conversion": done.how,
        "samples": int(sampled.sum()), "nan_gaps": int(gap.sum()), "partly_nan": int(partly.sum()),
        "values_dtype": str(stream.values.dtype),
        "rounding_max_counts": done.rounding_max_counts, "rounding_rms_counts": done.rounding_rms_counts,
        "at_range_limit": saturated,
    }
