"""The import of a ROS bag (rosbag2 with MCAP or SQLite3 storage, ROS 1): a bag, a column map
that names topics and fields (:mod:`~armfusion.fusion.importing.column_map`) and an arm's config in;
the arm's native recording and a summary out (:func:`import_bag`).

Order, as for a table (:mod:`~armfusion.fusion.importing.run`): the map is checked against the config
before the bag is read; the topics' fields are read (:func:`armfusion.sensors.foreign.rosbag.read_topics`);
each message's frame id is checked against the map's; a sample is stamped with the message's
header stamp or its receive time (the map's ``stamp``); within a stream, a message whose
stamp is not after every earlier one is dropped (the later of two stamped alike) and said;
a message with a NaN field is a gap; the values are brought into the config's unit. Each
topic's rate and gaps are reported as ``armfusion inspect`` reports a stream's.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
from armfusion.fusion.importing.column_map import ColumnMap, StreamSource
from armfusion.fusion.importing.run import ImportResult, Origin, refuse_what_no_sensor_said, stream_of
from armfusion.fusion.importing.stamps import FIRST_ROWS, StampReport, copies_dropped, increasing_rows
from armfusion.fusion.importing.to_stream import ImportMapError, Target, check_map_against
from armfusion.fusion.importing.to_stream import targets as targets_of
from armfusion.models.arm import ArmModel
from armfusion.sensors.foreign.rosbag import BagTopic, bag_format, read_topics
from armfusion.sensors.samples import Recording, Stream, clipped_repr, stream_gaps

NS_PER_S = 1_000_000_000


def seconds(t_ns: np.ndarray) -> np.ndarray:
    """Nanoseconds (int64) as seconds: one correctly rounded division, so a time the
    recording held as ``k / 10**d`` s (``d <= 9``) comes back bit for bit."""
    return np.asarray(t_ns, np.int64) / float(NS_PER_S)


def _frame_problem(topic: BagTopic, frame_id: str | None, stream: str) -> str | None:
    if frame_id is None:
        return None
    for frame, (_, first) in topic.frame_ids.items():
        if frame != frame_id:
            return (f"stream {stream}: topic {topic.topic} message {first} (from 0) has frame_id "
                    f"{clipped_repr(frame)}; the map says {clipped_repr(frame_id)}")
    return None


def _topic_report(topic: BagTopic, stamp: str, t_s: np.ndarray) -> dict:
    """A topic's messages, frame ids, rate and gaps (as ``inspect`` reports a stream's)."""
    s = Stream(topic.topic, "temperature", t_s, np.zeros((t_s.size, 1)), ("t",))
    n_gaps, longest, missing = stream_gaps(s)
    return {"type": topic.msgtype, "messages": len(topic), "stamp": stamp,
            "frame_ids": {k: n for k, (n, _) in topic.frame_ids.items()},
            "rate_hz": s.rate_hz, "gaps": n_gaps, "missing_samples": missing,
            "missing_percent": 100.0 * missing / (len(s) + missing) if len(s) else 0.0,
            "longest_gap_s": longest}


class _TopicStream(NamedTuple):
    """One stream read from its topic: the stream and its summary, each sample's message index
    on the topic, the kept messages' times (s), and the messages dropped for their stamp (of
    which ``copies`` repeated the message before them)."""

    stream: Stream
    summary: dict
    rows: np.ndarray
    t_s: np.ndarray
    dropped: int
    copies: int


def _refuse_unmatched_topics(cmap: ColumnMap, topics: dict[str, BagTopic], path: Path) -> None:
    """Refuse, in one message naming every one, a stream whose topic has no header stamp the
    map would stamp it with, or whose messages carry another frame id than the map's."""
    problems = []
    for name, src in cmap.streams.items():
        topic = topics[src.topic]
        stamp = src.stamp or cmap.stamp
        if stamp == "header" and topic.stamp_ns is None:
            problems.append(f"stream {name}: topic {src.topic} ({topic.msgtype}) has no header stamp: "
                            "give the stream stamp: receive")
        why = _frame_problem(topic, src.frame_id, name)
        if why:
            problems.append(why)
    if problems:
        raise ImportMapError(f"{path}: " + "; ".join(problems))


def _stamps_dropped_words(name: str, topic_name: str, stamp: str, report: StampReport) -> str:
    """The sentence for a stream's messages dropped because their stamp is not after every
    earlier one."""
    back = (f", the largest step back {report.largest_step_back_s * 1e3:.3f} ms"
            if report.largest_step_back_s > 0 else " (each a repeat of the one before)")
    first = ", ".join(f"{r} (t = {t:.6f} s)" for r, t in zip(report.not_increasing_rows,
                                                              report.not_increasing_t_s, strict=True))
    more = " …" if report.not_increasing > FIRST_ROWS else ""
    return (f"{name}: dropped {report.not_increasing} message(s) of {topic_name} whose {stamp} "
            f"stamp is not after every earlier one{back}: messages {first}{more} (from 0)")


def _stream_from_topic(name: str, src: StreamSource, topic: BagTopic, stamp: str, target: Target,
                       path: Path, changes: list[str]) -> _TopicStream:
    """Stream ``name`` from the fields of its topic, stamped by ``stamp`` (``header`` or
    ``receive``): the messages whose stamp is not after every earlier one dropped and said in
    ``changes``, then gaps and units as for a table (:func:`~armfusion.fusion.importing.run.stream_of`)."""
    t_all = seconds(topic.stamp_ns if stamp == "header" else topic.receive_ns)
    keep, report = increasing_rows(t_all, first_row=0)
    copies = copies_dropped(keep, [t_all] + [topic.fields[f] for f in src.columns])
    if report.not_increasing:
        changes.append(_stamps_dropped_words(name, src.topic, stamp, report))
    values = np.stack([topic.fields[f] for f in src.columns], axis=1)[keep]
    messages = np.flatnonzero(keep)
    origin = Origin(messages, "message", f"{path}: topic {src.topic}")
    stream, summary = stream_of(name, t_all[keep], values, origin, src, target, changes)
    summary["topic"] = src.topic
    return _TopicStream(stream, summary, messages[~np.isnan(values).any(axis=1)], t_all[keep],
                        report.not_increasing + report.no_time, copies)


def import_bag(src: str | Path, cmap: ColumnMap, arm: ArmModel, config: str) -> ImportResult:
    """Turn the bag ``src`` into ``arm``'s recording by ``cmap`` (a bag's map: topics and
    fields; see the module's docstring). Raises :class:`~armfusion.fusion.importing.to_stream.ImportMapError`
    or :class:`~armfusion.sensors.foreign.ForeignFileError` (both ``ValueError``) naming the stream, the
    topic, the message's index and the unit."""
    path = Path(src)
    if not cmap.is_bag:
        raise ImportMapError(f"{path} is a ROS bag, but column map {cmap.source} names columns: a bag's "
                             "map names topics and fields, with time: {stamp: header|receive}")
    targets = check_map_against(cmap, arm, config)
    topics = read_topics(path, cmap.topics())
    _refuse_unmatched_topics(cmap, topics, path)
    changes: list[str] = []
    read: dict[str, _TopicStream] = {}
    reports: dict[str, dict] = {}
    for name, source in cmap.streams.items():
        stamp = source.stamp or cmap.stamp
        read[name] = _stream_from_topic(name, source, topics[source.topic], stamp, targets[name], path,
                                        changes)
        if source.topic not in reports:
            reports[source.topic] = _topic_report(topics[source.topic], stamp, read[name].t_s)
    streams = {name: r.stream for name, r in read.items()}
    rec = Recording(streams, meta={"source": str(path), "arm_config": config})
    refuse_what_no_sensor_said(rec, arm, cmap, {name: r.rows for name, r in read.items()}, path,
                               row_word="message")
    dropped = sum(r.dropped for r in read.values())
    copies = sum(r.copies for r in read.values())
    ts = [s.t_s for s in streams.values() if len(s)]
    summary = {
        "source": str(path), "format": bag_format(path), "map": cmap.source, "config": config,
        "time": {"stamp": cmap.stamp, "t_start_s": float(min(t[0] for t in ts)) if ts else None,
                 "t_end_s": float(max(t[-1] for t in ts)) if ts else None},
        "topics": reports,
        "streams": {name: r.summary for name, r in read.items()},
        "absent": dict(cmap.absent),
        "not_mapped": [k for k, tg in targets_of(arm).items()
                       if k not in cmap.streams and k not in cmap.absent and not tg.needed],
        "changes": changes,
        "dropped": {"messages": dropped, "copies": copies, "lost": dropped - copies},
    }
    return ImportResult(rec, summary, tuple(changes), dropped - copies)
