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
"""

from __future__ import annotations

import gc
import importlib.metadata
import io
import json
import math
import struct
import time
import warnings
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Metadata
from mcap.writer import CompressionType, Writer

from sensors.samples import (
    RAW_KINDS,
    TRUTH_KINDS,
    Recording,
    RecordingError,
    Stream,
    StreamKind,
    clipped_repr,
)

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

MAGIC = b"\x89MCAP0\r\n"
METADATA_NAME = "armfusion"
FORMAT_VERSION = "1"
RAW_PREFIX = "raw/"
TRUTH_PREFIX = "truth/"
DEFAULT_CHUNK_SIZE_BYTES = 64 * 1024
DEFAULT_FLUSH_INTERVAL_S = 1.0


def _armfusion_version() -> str:
    try:
        return importlib.metadata.version("armfusion")
    except importlib.metadata.PackageNotFoundError:
        return "0+unknown"


# ---------------------------------------------------------------------------- schemas

_KIND_DOC: dict[str, tuple[str, int | None, str]] = {
    # kind: (what one sample is, number of values or None if per arm, value type)
    "accel": ("a link accelerometer's x, y, z: signed counts as the device gives them", 3, "integer"),
    "imu_accel": ("the base IMU accelerometer's x, y, z: signed counts", 3, "integer"),
    "gyro": ("the base IMU gyroscope's x, y, z: signed counts", 3, "integer"),
    "mag": ("the base magnetometer's x, y, z in the IMU accelerometer's axes: signed counts", 3, "integer"),
    "temperature": ("the IMU temperature register: signed counts", 1, "integer"),
    "encoder": ("the joint encoders, joint 1 first: relative counts", None, "integer"),
    "truth_joints": ("ground-truth joint angles, joint 1 first, rad", None, "number"),
    "truth_base": ("ground-truth base roll, pitch, yaw, rad", 3, "number"),
}


def schema_for_kind(kind: str) -> dict[str, Any]:
    """The JSON schema (draft 2020-12) of one message of a stream of ``kind``."""
    if kind not in _KIND_DOC:
        raise ValueError(f"unknown stream kind {kind!r}; expected one of {sorted(_KIND_DOC)}")
    doc, n, item = _KIND_DOC[kind]
    values: dict[str, Any] = {"type": "array", "items": {"type": item}, "description": doc}
    if n is not None:
        values["minItems"] = values["maxItems"] = n
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"armfusion.{kind}",
        "description": f"One sample of an armfusion '{kind}' stream.",
        "type": "object",
        "properties": {
            "t_s": {"type": "number", "description": "sample time, s (the recording's own origin)"},
            "values": values,
        },
        "required": ["t_s", "values"],
    }


def topic_for(stream_name: str, kind: str) -> str:
    """``raw/<stream>`` for raw kinds, ``truth/<stream>`` for ground truth."""
    if kind in RAW_KINDS:
        return RAW_PREFIX + stream_name
    if kind in TRUTH_KINDS:
        return TRUTH_PREFIX + stream_name
    raise ValueError(f"unknown stream kind {kind!r}; expected one of {sorted(_KIND_DOC)}")


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


def write_mcap(rec: Recording, path: str | Path, *, arm_config: str | None = None) -> None:
    """Write ``rec`` as an armfusion MCAP file, all streams merged in time order.

    ``arm_config`` defaults to ``rec.meta["arm_config"]`` (or empty). A recording that
    starts before t = 0 gets a whole-second time offset (see :class:`McapRecorder`).
    """
    config = arm_config if arm_config is not None else str(rec.meta.get("arm_config", ""))
    offset_s = float(math.ceil(-rec.t_start_s)) if rec.t_start_s < 0 else 0.0
    with McapRecorder(path, arm_config=config, t_offset_s=offset_s) as recorder:
        recorder.write_streams(list(rec.streams.values()))


# ---------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class ReadReport:
    """How much of an MCAP file could be read.

    ``complete`` is true when the file ends properly (footer and closing magic).
    ``bytes_unread`` counts the bytes after the last record that could be read whole.
    """

    complete: bool
    messages_read: int
    bytes_total: int
    bytes_unread: int
    message: str
    t_last_s: float | None = None
    ignored_topics: tuple[str, ...] = ()


_MAX_CHUNK_BYTES = 1 << 31  # a larger uncompressed size is a damaged chunk header
_HEADER = struct.Struct("<BQ")  # opcode, body length: the framing of every record
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def _opcode_name(op: int) -> str:
    try:
        return Opcode(op).name.replace("_", " ").lower() + " record"
    except ValueError:
        return f"record of unknown opcode 0x{op:02x}"


def _kb(n: int) -> str:
    return f"{n / 1000:.1f} kB" if n >= 1000 else f"{n} byte" + ("s" if n != 1 else "")


class _Damaged(Exception):
    """A record that is complete but cannot be parsed."""


def _parse_record(cls: type, body: bytes) -> Any:
    return cls.read(ReadDataStream(io.BytesIO(body)))


def _chunk_records(body: bytes) -> tuple[list[Channel], list[tuple[int, int, bytes]]]:
    """Channels and messages ``(channel id, log time, data)`` of one chunk record."""
    chunk = _parse_record(Chunk, body)
    if chunk.uncompressed_size > _MAX_CHUNK_BYTES:
        raise _Damaged(f"chunk claims {chunk.uncompressed_size} bytes uncompressed")
    if chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size
        )
    elif chunk.compression == "lz4":
        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise _Damaged(f"unknown chunk compression {chunk.compression!r}")
    if len(data) != chunk.uncompressed_size:
        raise _Damaged(f"chunk holds {len(data)} bytes, its header says {chunk.uncompressed_size}")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise _Damaged("chunk CRC mismatch")
    channels: list[Channel] = []
    messages: list[tuple[int, int, bytes]] = []
    pos, end = 0, len(data)
    unpack_header, unpack_message = _HEADER.unpack_from, _MESSAGE.unpack_from
    while pos < end:
        op, length = unpack_header(data, pos)
        body_start = pos + 9
        pos = body_start + length
        if pos > end:
            raise _Damaged("a record runs past the end of its chunk")
        if op == Opcode.MESSAGE:
            cid, _, log_ns, _ = unpack_message(data, body_start)
            messages.append((cid, log_ns, data[body_start + 22 : pos]))
        elif op == Opcode.CHANNEL:
            channels.append(_parse_record(Channel, data[body_start:pos]))
    return channels, messages


@contextmanager
def _gc_paused() -> Iterator[None]:
    """Millions of small objects (one per message) make the cyclic GC run over and
    over for nothing; pausing it makes reading several times faster."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def read_mcap(path: str | Path) -> tuple[Recording, ReadReport]:
    """Read an armfusion MCAP file: the recording and a report of what was read.

    Reads the records in file order, without seeking and without trusting the summary
    at the end, so it also reads a file whose writer was killed: every message up to
    the last complete record is returned, and the report says where the file ends and
    how much could not be read (the chunk being written when the file was cut is lost
    whole; a damaged record ends the reading the same way). A file that is not MCAP
    raises ``ValueError`` naming the path. Topics other than ``raw/*`` and
    ``truth/*`` are counted in the report but not returned.
    """
    with _gc_paused():
        return _read_mcap(Path(path))


def _read_mcap(path: Path) -> tuple[Recording, ReadReport]:
    size = path.stat().st_size
    channels: dict[int, Channel] = {}
    messages: dict[int, list[bytes]] = {}
    meta: dict[str, str] = {}
    n_messages = 0
    complete = False
    problem = ""  # where the file ends early
    damaged = ""  # or which record could not be parsed
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
        if head != MAGIC[: len(head)]:
            raise ValueError(
                f"{path}: not an MCAP file (it does not start with the MCAP magic bytes "
                f"{MAGIC!r}, but with {head[:8]!r})"
            )
        good_end = len(head)
        if len(head) < len(MAGIC):
            problem = "before anything was written" if size == 0 else "inside the opening magic bytes"
        while not (problem or damaged or complete):
            start = good_end
            header = f.read(9)
            if len(header) < 9:
                if header:
                    problem = f"inside the header of a {_opcode_name(header[0])} at byte {start}"
                elif start == len(MAGIC):
                    problem = "right after the opening magic bytes"
                else:
                    problem = f"after the complete record that ends at byte {start}"
                break
            op, length = _HEADER.unpack(header)
            what = _opcode_name(op)
            if length > size - start - 9:
                problem = f"inside a {what} that starts at byte {start}"
                break
            body = f.read(length)
            try:
                if op == Opcode.CHUNK:
                    new_channels, new_messages = _chunk_records(body)
                    for ch in new_channels:
                        channels[ch.id] = ch
                    for cid, _, data in new_messages:
                        messages.setdefault(cid, []).append(data)
                    n_messages += len(new_messages)
                elif op == Opcode.MESSAGE:
                    cid, _, _, _ = _MESSAGE.unpack_from(body)
                    messages.setdefault(cid, []).append(body[22:])
                    n_messages += 1
                elif op == Opcode.CHANNEL:
                    ch = _parse_record(Channel, body)
                    channels[ch.id] = ch
                elif op == Opcode.METADATA:
                    m = _parse_record(Metadata, body)
                    if m.name == METADATA_NAME:
                        meta = dict(m.metadata)
            except Exception as e:  # a complete but damaged record ends the reading
                why = str(e) if isinstance(e, _Damaged) else f"{type(e).__name__}: {e}"
                damaged = f"a damaged {what} at byte {start} ({why})"
                break
            good_end = start + 9 + length
            if op == Opcode.FOOTER:
                tail = f.read(len(MAGIC))
                if tail == MAGIC:
                    complete = True
                    good_end += len(MAGIC)
                elif MAGIC.startswith(tail):
                    problem = f"inside the closing magic bytes at byte {good_end}"
                else:
                    damaged = f"damaged closing magic bytes at byte {good_end}"
    rec, ignored, t_last = _assemble(path, channels, messages, meta)
    unread = size - good_end
    span = f" up to t = {t_last:.3f} s" if t_last is not None else ""
    recovered = f"recovered {n_messages} messages{span}"
    lost = f"the last {_kb(unread)} could not be read" if unread else "the file's summary is missing"
    if complete:
        text = f"{path}: complete: {n_messages} messages{span}"
    elif damaged:
        text = f"{path}: {damaged}: {recovered}; {lost}"
    else:
        text = f"{path}: file ends early at byte {size}, {problem}: {recovered}; {lost}"
    if "chunk record" in problem + damaged:
        text += " (the messages of that chunk are lost)"
    return rec, ReadReport(complete, n_messages, size, unread, text, t_last, ignored)


def _decode_samples(data: list[bytes], k: int, counts: bool) -> tuple[np.ndarray, np.ndarray]:
    """``t_s (N,)`` and ``values (N, k)`` of the JSON messages of one stream.

    Messages exactly as this module writes them (``{"t_s":..,"values":[..]}``, no
    spaces) are parsed as one block of numbers by numpy; anything else that is
    valid JSON for the schema goes through ``json`` (slower).
    """
    n = len(data)
    text = b"\n".join(data)
    head, mid, tail = b'{"t_s":', b',"values":[', b"]}"
    if all(text.count(x) == n for x in (head, mid, tail, b"{", b"[")) and text.count(b'"') == 4 * n:
        plain = text.replace(head, b"").replace(mid, b",").replace(tail, b"").replace(b"\n", b",")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # fromstring on bad text
            flat = np.fromstring(plain.decode("ascii"), sep=",") if n else np.zeros(0)
        if flat.size == n * (k + 1):
            table = flat.reshape(n, k + 1)
            values = table[:, 1:]
            if not counts:
                return table[:, 0], values
            if np.all(np.abs(values) < 2.0**53):  # every such decimal integer is exact
                return table[:, 0], values.astype(np.int64)
    samples = json.loads(b"[" + b",".join(data) + b"]")
    t_s = np.array([m["t_s"] for m in samples], dtype=np.float64)
    return t_s, np.array([m["values"] for m in samples]).reshape(n, k)


def _assemble(
    path: Path, channels: dict[int, Channel], messages: dict[int, list[bytes]], meta: dict[str, str]
) -> tuple[Recording, tuple[str, ...], float | None]:
    streams: dict[str, Stream] = {}
    ignored: list[str] = []
    t_last: float | None = None
    for cid, ch in channels.items():
        kind = ch.metadata.get("kind", "")
        is_stream = ch.topic.startswith((RAW_PREFIX, TRUTH_PREFIX)) and kind in _KIND_DOC
        data = messages.get(cid, [])
        if not is_stream:
            ignored.append(ch.topic)
            continue
        name = ch.metadata.get("stream") or ch.topic.split("/", 1)[1]
        try:
            names = tuple(json.loads(ch.metadata.get("channels", "[]")))
            t_s, values = _decode_samples(data, len(names), kind in RAW_KINDS)
            stream = Stream(name, kind, t_s, values, names)  # type: ignore[arg-type]
        except (ValueError, KeyError, TypeError, OverflowError, RecursionError) as e:
            # (a count beyond 64 bits, JSON nested past the recursion limit...): named, short
            raise RecordingError(
                f"{path}: topic {clipped_repr(ch.topic)}: messages do not fit the stream: "
                f"{clipped_repr(f'{type(e).__name__}: {e}', 120)[1:-1]}"
            ) from None
        streams[name] = stream
        if len(stream):
            t_last = stream.t_s[-1] if t_last is None else max(t_last, float(stream.t_s[-1]))
    rec_meta: dict[str, Any] = {"source": str(path)}
    if meta:
        rec_meta["arm_config"] = meta.get("arm_config", "")
        rec_meta["armfusion_version"] = meta.get("armfusion_version", "")
        try:
            rec_meta["t_offset_ns"] = int(meta.get("t_offset_ns", "0")[:24])
        except ValueError:
            raise RecordingError(f"{path}: the armfusion metadata's t_offset_ns is not an "
                                 f"integer: {clipped_repr(meta.get('t_offset_ns'))}") from None
    return Recording(streams, rec_meta), tuple(ignored), (None if t_last is None else float(t_last))
