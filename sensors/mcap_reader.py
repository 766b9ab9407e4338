"""Reading an armfusion MCAP file (:func:`read_mcap`), also one cut off while recording or
damaged: up to its last complete record, saying in a :class:`ReadReport` what could not be
read. Bounded: a chunk claiming more than the reader takes, or records that do not parse,
are named and refused (``docs/reference/refusals.md``).
"""

from __future__ import annotations

import gc
import io
import json
import struct
import warnings
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import lz4.frame
import numpy as np
import zstandard
from armfusion.sensors.mcap_format import (
    KIND_DOC,
    MAGIC,
    METADATA_NAME,
    RAW_PREFIX,
    READ_FORMAT_VERSIONS,
    TRUTH_PREFIX,
)
from armfusion.sensors.sample_checks import MCAP_TOPICS
from armfusion.sensors.samples import RAW_KINDS, Recording, RecordingError, Stream, clipped_repr
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Metadata


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
    left_out: tuple[tuple[str, int, str], ...] = ()
    """Sample channels not read: ``(topic, messages, why)`` for a ``raw/`` or ``truth/``
    topic of an unknown kind or without the stream's metadata, and for messages on a
    channel id no channel record declares."""

    def left_out_words(self) -> str:
        """The channels left out, for a person (one line)."""
        return "; ".join(f"{clipped_repr(topic)[1:-1]} ({n} messages): {why}"
                         for topic, n, why in self.left_out)


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
    ``truth/*`` are counted in the report but not returned; a ``raw/*`` or ``truth/*`` topic
    of an unknown kind or without metadata, and messages on an undeclared channel, are named
    in the report's ``left_out`` (:func:`armfusion.sensors.recording.read_recording` warns with them).
    """
    with _gc_paused():
        return _read_mcap(Path(path))


class _Records:
    """What the records read so far hold: the channels by id, each channel id's messages,
    the armfusion metadata."""

    def __init__(self) -> None:
        self.channels: dict[int, Channel] = {}
        self.messages: dict[int, list[bytes]] = {}
        self.meta: dict[str, str] = {}
        self.n_messages = 0

    def take(self, op: int, body: bytes) -> None:
        """Keep what record ``op`` with ``body`` holds (raises on a damaged record)."""
        if op == Opcode.CHUNK:
            new_channels, new_messages = _chunk_records(body)
            for ch in new_channels:
                self.channels[ch.id] = ch
            for cid, _, data in new_messages:
                self.messages.setdefault(cid, []).append(data)
            self.n_messages += len(new_messages)
        elif op == Opcode.MESSAGE:
            cid, _, _, _ = _MESSAGE.unpack_from(body)
            self.messages.setdefault(cid, []).append(body[22:])
            self.n_messages += 1
        elif op == Opcode.CHANNEL:
            ch = _parse_record(Channel, body)
            self.channels[ch.id] = ch
        elif op == Opcode.METADATA:
            m = _parse_record(Metadata, body)
            if m.name == METADATA_NAME:
                self.meta = dict(m.metadata)


@dataclass(frozen=True)
class _End:
    """Where the reading stopped: the end of the last record read whole, and why: the
    file is ``complete``, or ends early (``problem``: where), or holds a ``damaged`` record."""

    good_end: int
    complete: bool = False
    problem: str = ""
    damaged: str = ""


def _opening(f: BinaryIO, path: Path, size: int) -> _End | None:
    """Check the opening magic bytes (a ``ValueError`` for a file that is not MCAP): None
    when whole, else where the file ends inside them."""
    head = f.read(len(MAGIC))
    if head != MAGIC[: len(head)]:
        raise ValueError(
            f"{path}: not an MCAP file (it does not start with the MCAP magic bytes "
            f"{MAGIC!r}, but with {head[:8]!r})"
        )
    if len(head) < len(MAGIC):
        return _End(len(head), problem="before anything was written" if size == 0
                    else "inside the opening magic bytes")
    return None


def _record_at(f: BinaryIO, size: int, start: int) -> tuple[int, bytes] | _End:
    """The record starting at byte ``start``: its opcode and body, or where the file ends
    inside it."""
    header = f.read(9)
    if len(header) < 9:
        if header:
            return _End(start, problem=f"inside the header of a {_opcode_name(header[0])} at byte {start}")
        if start == len(MAGIC):
            return _End(start, problem="right after the opening magic bytes")
        return _End(start, problem=f"after the complete record that ends at byte {start}")
    op, length = _HEADER.unpack(header)
    if length > size - start - 9:
        return _End(start, problem=f"inside a {_opcode_name(op)} that starts at byte {start}")
    return op, f.read(length)


def _closing(f: BinaryIO, good_end: int) -> _End:
    """After the footer: the closing magic bytes, whole, cut or damaged."""
    tail = f.read(len(MAGIC))
    if tail == MAGIC:
        return _End(good_end + len(MAGIC), complete=True)
    if MAGIC.startswith(tail):
        return _End(good_end, problem=f"inside the closing magic bytes at byte {good_end}")
    return _End(good_end, damaged=f"damaged closing magic bytes at byte {good_end}")


def _read_records(f: BinaryIO, path: Path, size: int, records: _Records) -> _End:
    """Read the records in file order into ``records`` up to the end of the file, where it
    ends early, or a damaged record."""
    end = _opening(f, path, size)
    if end is not None:
        return end
    good_end = len(MAGIC)
    while True:
        start = good_end
        record = _record_at(f, size, start)
        if isinstance(record, _End):
            return record
        op, body = record
        try:
            records.take(op, body)
        except Exception as e:  # a complete but damaged record ends the reading
            why = str(e) if isinstance(e, _Damaged) else f"{type(e).__name__}: {e}"
            return _End(start, damaged=f"a damaged {_opcode_name(op)} at byte {start} ({why})")
        good_end = start + 9 + len(body)
        if op == Opcode.FOOTER:
            return _closing(f, good_end)


def _report_text(path: Path, size: int, end: _End, n_messages: int, t_last: float | None) -> str:
    """The report's one line: complete, or where the file ends or is damaged and what was
    recovered."""
    unread = size - end.good_end
    span = f" up to t = {t_last:.3f} s" if t_last is not None else ""
    recovered = f"recovered {n_messages} messages{span}"
    lost = f"the last {_kb(unread)} could not be read" if unread else "the file's summary is missing"
    if end.complete:
        text = f"{path}: complete: {n_messages} messages{span}"
    elif end.damaged:
        text = f"{path}: {end.damaged}: {recovered}; {lost}"
    else:
        text = f"{path}: file ends early at byte {size}, {end.problem}: {recovered}; {lost}"
    if "chunk record" in end.problem + end.damaged:
        text += " (the messages of that chunk are lost)"
    return text


def _read_mcap(path: Path) -> tuple[Recording, ReadReport]:
    """:func:`read_mcap`'s work: the records, the streams they hold, the report."""
    size = path.stat().st_size
    records = _Records()
    with open(path, "rb") as f:
        end = _read_records(f, path, size, records)
    rec, ignored, t_last, left_out = _assemble(path, records.channels, records.messages, records.meta)
    text = _report_text(path, size, end, records.n_messages, t_last)
    return rec, ReadReport(end.complete, records.n_messages, size, size - end.good_end, text, t_last,
                           ignored, left_out)


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
            try:
                flat = np.fromstring(plain.decode("ascii"), sep=",") if n else np.zeros(0)
            except ValueError:  # (a word such as true or null: numpy's words; json's below say where)
                flat = np.zeros(0)
        if flat.size == n * (k + 1):
            table = flat.reshape(n, k + 1)
            values = table[:, 1:]
            if not counts:
                return table[:, 0], values
            if np.all(np.abs(values) < 2.0**53):  # every such decimal integer is exact
                whole = np.all(values == np.round(values))
                return table[:, 0], (values.astype(np.int64) if whole else values)
    samples = json.loads(b"[" + b",".join(data) + b"]")
    for i, m in enumerate(samples):  # a number is a JSON number: not "12", not true (the schema's)
        if not (isinstance(m, dict) and _is_number(m.get("t_s")) and isinstance(m.get("values"), list)
                and all(_is_number(v) for v in m["values"])):
            said = json.dumps(m)
            raise ValueError(f"message {i + 1} is not {{\"t_s\": number, \"values\": [numbers]}}: "
                             + (said if len(said) <= 60 else said[:60] + "…"))
    t_s = np.array([m["t_s"] for m in samples], dtype=np.float64)
    return t_s, np.array([m["values"] for m in samples]).reshape(n, k)


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _assemble(
    path: Path, channels: dict[int, Channel], messages: dict[int, list[bytes]], meta: dict[str, str]
) -> tuple[Recording, tuple[str, ...], float | None, tuple[tuple[str, int, str], ...]]:
    streams: dict[str, Stream] = {}
    ignored: list[str] = []
    left_out: list[tuple[str, int, str]] = []
    topics: dict[str, str] = {}
    t_last: float | None = None
    for cid in messages.keys() - channels.keys():
        left_out.append((f"channel id {cid}", len(messages[cid]), "no channel record declares it"))
    for cid, ch in channels.items():
        kind = ch.metadata.get("kind", "")
        is_stream = ch.topic.startswith((RAW_PREFIX, TRUTH_PREFIX)) and kind in KIND_DOC
        data = messages.get(cid, [])
        if not is_stream:
            ignored.append(ch.topic)
            if ch.topic.startswith((RAW_PREFIX, TRUTH_PREFIX)):
                why = (f"unknown stream kind {clipped_repr(kind)}" if kind else
                       "no stream metadata (kind, channels)")
                left_out.append((ch.topic, len(data), why))
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
        if name in streams:
            raise RecordingError(f"{path}: topics {clipped_repr(topics[name])} and {clipped_repr(ch.topic)} "
                                 f"both hold stream {clipped_repr(name)}; a stream is one topic's")
        streams[name] = stream
        topics[name] = ch.topic
        if len(stream):
            t_last = stream.t_s[-1] if t_last is None else max(t_last, float(stream.t_s[-1]))
    rec_meta: dict[str, Any] = {"source": str(path), MCAP_TOPICS: topics}
    if meta and meta.get("format_version", "1") not in READ_FORMAT_VERSIONS:
        raise RecordingError(f"{path}: armfusion MCAP format version "
                             f"{clipped_repr(meta.get('format_version'))}; this armfusion reads "
                             f"{' or '.join(READ_FORMAT_VERSIONS)} (docs/recording-mcap.md)")
    if meta:
        rec_meta["arm_config"] = meta.get("arm_config", "")
        rec_meta["armfusion_version"] = meta.get("armfusion_version", "")
        try:
            rec_meta["t_offset_ns"] = int(meta.get("t_offset_ns", "0")[:24])
        except ValueError:
            raise RecordingError(f"{path}: the armfusion metadata's t_offset_ns is not an "
                                 f"integer: {clipped_repr(meta.get('t_offset_ns'))}") from None
    return (Recording(streams, rec_meta), tuple(ignored), (None if t_last is None else float(t_last)),
            tuple(left_out))
