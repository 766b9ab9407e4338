"""Recording MCAP: the native log (layout and recovery in ``docs/recording-mcap.md``).

One channel per stream: topic ``raw/<stream>`` for raw counts, ``truth/<stream>`` for
ground truth; message encoding ``json``, schema encoding ``jsonschema`` (one schema
per stream kind, :func:`schema_for_kind`). Each message is one sample::

    {"t_s": 12.34, "values": [12, -3, 250]}

The channel's metadata names the stream, its kind and its channels (the CSV column
names). ``log_time = publish_time = round(t_s * 1e9) + t_offset_ns``; the offset
(0 unless the recording starts before t = 0) is in the file's ``armfusion`` metadata
record with the arm config name and the armfusion version.

:class:`McapRecorder` writes incrementally in small chunks and flushes at least
every ``flush_interval_s``, so a process killed while recording loses at most the
last chunk. :func:`read_mcap` reads such a cut-off file up to its last complete
record and says in a :class:`ReadReport` what it could not read.

This module is the writer; the reader is :mod:`armfusion.sensors.mcap_reader`, the layout both share
:mod:`armfusion.sensors.mcap_format` (every name importable from here as before).
"""

from __future__ import annotations

import importlib.metadata
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from armfusion.sensors.mcap_format import (
    FORMAT_VERSION,
    METADATA_NAME,
    RAW_PREFIX,
    TRUTH_PREFIX,
    schema_for_kind,
    topic_for,
)
from armfusion.sensors.mcap_reader import ReadReport, read_mcap
from armfusion.sensors.output_files import replaced_when_done
from armfusion.sensors.samples import (
    TRUTH_KINDS,
    Recording,
    Stream,
    StreamKind,
)
from mcap.writer import CompressionType, Writer

__all__ = [
    "FORMAT_VERSION",
    "METADATA_NAME",
    "McapRecorder",
    "ReadReport",
    "read_mcap",
    "schema_for_kind",
    "topic_for",
    "write_mcap",
]

DEFAULT_CHUNK_SIZE_BYTES = 64 * 1024
DEFAULT_FLUSH_INTERVAL_S = 1.0


def _armfusion_version() -> str:
    try:
        return importlib.metadata.version("armfusion")
    except importlib.metadata.PackageNotFoundError:
        return "0+unknown"


# ---------------------------------------------------------------------------- writing


@dataclass
class _StreamChannel:
    channel_id: int
    kind: str
    channels: tuple[str, ...]
    sequence: int = 0
    last_t_s: float = -math.inf


class McapRecorder:
    """Write a recording to an MCAP file as it happens.

    Open it with ``McapRecorder(path, ...)`` (or ``McapRecorder.open(path, ...)``), use
    it as a context manager, and write batches of samples as they come::

        with McapRecorder("run.mcap", arm_config="wmra") as rec:
            rec.write_samples("acc1", "accel", ("acc1_x", "acc1_y", "acc1_z"), t_s, counts)
            rec.write_json("estimates/joints", "armfusion.JointState", {"q_rad": [...]}, t_s=1.2)

    Messages are grouped in zstd-compressed chunks of about ``chunk_size_bytes``
    (uncompressed); a chunk is also closed and the file flushed when
    ``flush_interval_s`` of wall-clock time has passed since the last flush (checked
    at each write; call :meth:`flush` yourself if writes may pause). A process killed
    while recording therefore loses at most the chunk in progress: about one second.

    ``t_offset_s`` shifts MCAP log times (which cannot be negative) so that samples
    with ``t_s >= -t_offset_s`` can be written; ``t_s`` itself is stored unchanged.

    One recorder has one owner: it is not safe to call from several threads at once.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        arm_config: str = "",
        t_offset_s: float = 0.0,
        chunk_size_bytes: int = DEFAULT_CHUNK_SIZE_BYTES,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        compress: bool = True,
    ) -> None:
        if t_offset_s < 0 or not math.isfinite(t_offset_s):
            raise ValueError(f"t_offset_s must be finite and >= 0, got {t_offset_s!r}")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self._t_offset_ns = round(t_offset_s * 1e9)
        self._file: IO[bytes] = open(self.path, "wb")  # closed in close()
        self._writer = Writer(
            self._file,
            chunk_size=chunk_size_bytes,
            compression=CompressionType.ZSTD if compress else CompressionType.NONE,
        )
        self._writer.start(library=f"armfusion/{_armfusion_version()}")
        self._writer.add_metadata(
            METADATA_NAME,
            {
                "format_version": FORMAT_VERSION,
                "armfusion_version": _armfusion_version(),
                "arm_config": arm_config,
                "t_offset_ns": str(self._t_offset_ns),
            },
        )
        self._file.flush()
        self._schemas: dict[str, int] = {}
        self._streams: dict[str, _StreamChannel] = {}
        self._json_channels: dict[str, int] = {}
        self._last_flush = time.monotonic()
        self._closed = False
        self.messages_written = 0

    @classmethod
    def open(cls, path: str | Path, **options: Any) -> McapRecorder:
        """Same as ``McapRecorder(path, **options)``."""
        return cls(path, **options)

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- registration

    def _schema_id(self, name: str, schema: dict[str, Any]) -> int:
        if name not in self._schemas:
            data = json.dumps(schema, indent=1).encode()
            self._schemas[name] = self._writer.register_schema(name, "jsonschema", data)
        return self._schemas[name]

    def _stream(self, name: str, kind: str, channels: tuple[str, ...]) -> _StreamChannel:
        known = self._streams.get(name)
        if known is not None:
            if (known.kind, known.channels) != (kind, channels):
                raise ValueError(
                    f"stream {name!r} was started as kind {known.kind} with channels "
                    f"{list(known.channels)}; now kind {kind} with channels {list(channels)}"
                )
            return known
        topic = topic_for(name, kind)
        schema_id = self._schema_id(f"armfusion.{kind}", schema_for_kind(kind))
        meta = {"stream": name, "kind": kind, "channels": json.dumps(list(channels))}
        cid = self._writer.register_channel(topic, "json", schema_id, meta)
        self._streams[name] = _StreamChannel(cid, kind, channels)
        return self._streams[name]

    # -- writing

    def _log_times_ns(self, t_s: np.ndarray) -> list[int]:
        ns = np.rint(t_s * 1e9).astype(np.int64) + self._t_offset_ns
        if ns.size and ns.min() < 0:
            first = float(t_s[int(np.argmin(ns))])
            raise ValueError(
                f"{self.path}: t_s = {first!r} is before the recorder's time origin "
                f"(MCAP log times cannot be negative): open it with t_offset_s >= {-first!r}"
            )
        return ns.tolist()

    def write_samples(
        self,
        stream_name: str,
        kind: StreamKind,
        channels: tuple[str, ...] | list[str],
        t_s: np.ndarray,
        values: np.ndarray,
    ) -> None:
        """Append samples ``t_s (N,)``, ``values (N, k)`` of one stream (N may be 1).

        Raw kinds take whole-number counts, truth kinds floats. Times must be finite
        and increase, also from one call to the next.
        """
        self.write_streams([Stream(stream_name, kind, t_s, values, tuple(channels))])

    def write_stream(self, stream: Stream) -> None:
        """Append all samples of ``stream`` (see :meth:`write_samples`)."""
        self.write_streams([stream])

    def write_streams(self, streams: list[Stream]) -> None:
        """Append the samples of several streams, merged in time order."""
        self._check_open()
        ids, ts, payloads, seqs = [], [], [], []
        for s in streams:
            if not len(s):
                self._stream(s.name, s.kind, s.channels)
                continue
            if not np.all(np.isfinite(s.t_s)):
                raise ValueError(f"stream {s.name!r}: t_s must be finite")
            ch = self._stream(s.name, s.kind, s.channels)
            if s.t_s[0] <= ch.last_t_s:
                raise ValueError(
                    f"stream {s.name!r}: t_s = {float(s.t_s[0])!r} does not follow the last "
                    f"sample written, t_s = {ch.last_t_s!r}"
                )
            t_list = s.t_s.tolist()
            payloads.extend(_payloads(t_list, s))
            ids.append(np.full(len(s), ch.channel_id))
            seqs.append(ch.sequence + np.arange(len(s)))
            ts.append(s.t_s)
            ch.sequence += len(s)
            ch.last_t_s = t_list[-1]
        if not ts:
            return
        t_all = np.concatenate(ts)
        order = np.argsort(t_all, kind="stable")
        log_ns = self._log_times_ns(t_all[order])
        ids_o = np.concatenate(ids)[order].tolist()
        seq_o = (np.concatenate(seqs)[order] & 0xFFFFFFFF).tolist()
        add = self._writer.add_message
        for n, (i, cid, ns, seq) in enumerate(zip(order.tolist(), ids_o, log_ns, seq_o, strict=True)):
            add(cid, ns, payloads[i], ns, seq)
            if n % 1024 == 1023:
                self._maybe_flush()
        self.messages_written += len(order)
        self._maybe_flush()

    def write_json(
        self,
        topic: str,
        schema_name: str,
        obj: dict[str, Any],
        t_s: float,
        schema: dict[str, Any] | None = None,
    ) -> None:
        """Append one JSON message ``obj`` at time ``t_s`` on ``topic`` (e.g. estimates).

        The channel is created at first use, with ``schema`` (a JSON schema; by
        default any object) registered as ``schema_name``. Topics under ``raw/`` and
        ``truth/`` are reserved for :meth:`write_samples`.
        """
        self._check_open()
        if topic.startswith((RAW_PREFIX, TRUTH_PREFIX)):
            raise ValueError(f"topic {topic!r}: raw/ and truth/ are reserved for sample streams")
        if topic not in self._json_channels:
            sch = schema if schema is not None else {"title": schema_name, "type": "object"}
            sid = self._schema_id(schema_name, sch)
            self._json_channels[topic] = self._writer.register_channel(topic, "json", sid, {})
        t = np.array([float(t_s)])
        if not np.isfinite(t[0]):
            raise ValueError(f"topic {topic!r}: t_s must be finite, got {t_s!r}")
        [ns] = self._log_times_ns(t)
        self._writer.add_message(self._json_channels[topic], ns, json.dumps(obj).encode(), ns, 0)
        self.messages_written += 1
        self._maybe_flush()

    def _maybe_flush(self) -> None:
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Close the chunk in progress and push everything written so far to the file."""
        self._check_open()
        self._writer.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        """Finish the file (summary, footer); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self.path}: the recorder is closed")


def _payloads(t_list: list[float], s: Stream) -> list[bytes]:
    """One JSON message per sample: ``{"t_s":...,"values":[...]}``, shortest exact floats."""
    if s.kind in TRUTH_KINDS:  # json's float text: exact, and NaN/Infinity as json.loads reads them
        per_channel = [json.dumps(col)[1:-1].split(", ") for col in s.values.T.tolist()]
    else:
        per_channel = [list(map(str, col)) for col in s.values.T.tolist()]
    rows = map(",".join, zip(*per_channel, strict=True))
    return [
        b'{"t_s":%s,"values":[%s]}' % (repr(t).encode(), v.encode())
        for t, v in zip(t_list, rows, strict=True)
    ]


WRITE_SLICE_S = 60.0
""":func:`write_mcap` makes the messages of this much time at once."""


def write_mcap(rec: Recording, path: str | Path, *, arm_config: str | None = None) -> None:
    """Write ``rec`` as an armfusion MCAP file, all streams merged in time order.

    ``arm_config`` defaults to ``rec.meta["arm_config"]`` (or empty). A recording that
    starts before t = 0 gets a whole-second time offset (see :class:`McapRecorder`). Written
    under a temporary name and renamed when complete
    (:func:`armfusion.sensors.output_files.replaced_when_done`).
    """
    config = arm_config if arm_config is not None else str(rec.meta.get("arm_config", ""))
    offset_s = float(math.ceil(-rec.t_start_s)) if rec.t_start_s < 0 else 0.0
    streams = list(rec.streams.values())
    with replaced_when_done(path) as tmp, \
            McapRecorder(tmp, arm_config=config, t_offset_s=offset_s) as recorder:
        # a slice of time at a time: the messages of one slice are made in memory, not the
        # whole recording's (an hour at 100 Hz of five sensors is millions of messages)
        edges = [*np.arange(rec.t_start_s, rec.t_end_s, WRITE_SLICE_S)[1:].tolist(), np.inf]
        start = dict.fromkeys(rec.streams, 0)
        for hi in edges:
            part = []
            for s in streams:
                a, b = start[s.name], int(np.searchsorted(s.t_s, hi, side="left"))
                part.append(s if (a, b) == (0, len(s)) else
                            Stream(s.name, s.kind, s.t_s[a:b], s.values[a:b], s.channels))
                start[s.name] = b
            recorder.write_streams(part)
