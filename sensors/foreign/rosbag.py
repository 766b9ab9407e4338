"""The topics of a ROS bag, read as plain numbers: rosbag2 (a bag directory with its
``metadata.yaml``, or one ``.mcap`` or ``.db3`` storage file) and ROS 1 (``.bag``), through
``rosbags`` (pure Python, no ROS install).

A bag knows nothing of arms: :func:`read_topics` reads, for each topic named, the fields
named (``linear_acceleration.x``, ``position[j3]`` by joint name, ``data[2]`` by index),
every message's receive time (the bag's log time) and header stamp, and its frame id,
each field float64 ``(N,)``. Only the message types of :data:`MESSAGE_TYPES` are read.

Fast and checked: the messages of one topic are grouped by their *layout* (the bytes that
fix where every value lies: the encapsulation header, every string and every sequence's
length); within a group each field is at one offset, read for every message at once with
NumPy. The first message of every group is also decoded by ``rosbags``' own deserialiser
and must agree with what is read from its bytes, so a message ``rosbags`` cannot decode
(truncated, of another type) is refused, naming the topic and the message's index.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.sensors.foreign.table import MAX_FILE_BYTES, ForeignFileError, available_words, check_size
from armfusion.sensors.samples import clipped_repr

MESSAGE_TYPES: dict[str, str] = {
    "sensor_msgs/msg/Imu": "orientation, angular_velocity, linear_acceleration (.x .y .z; .w too)",
    "sensor_msgs/msg/MagneticField": "magnetic_field.x .y .z (tesla)",
    "sensor_msgs/msg/JointState": "position, velocity, effort [JOINT NAME or index]",
    "geometry_msgs/msg/Vector3Stamped": "vector.x .y .z",
    "std_msgs/msg/Float64MultiArray": "data[K] (K from 0)",
}
"""The message types read, and their fields."""
BAG_SUFFIXES: dict[str, str] = {".mcap": "rosbag2, MCAP storage", ".db3": "rosbag2, SQLite3 storage",
                                ".bag": "ROS 1 bag"}
"""A bag is a rosbag2 directory (``metadata.yaml`` beside its storage) or one of these files."""
MAX_LAYOUTS = 256
"""Layouts one topic may have (a frame id or the joint names changing from message to message
make new ones); past this the topic is refused rather than read a message at a time."""

_SIZES = {"bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2,
          "int32": 4, "uint32": 4, "float32": 4, "int64": 8, "uint64": 8, "float64": 8}
_KINDS = {"bool": "u", "byte": "u", "char": "u", "uint8": "u", "uint16": "u", "uint32": "u", "uint64": "u",
          "int8": "i", "int16": "i", "int32": "i", "int64": "i", "float32": "f", "float64": "f"}
_FIELD = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)(?:\[([^\[\]]{1,128})\])?")


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` is read as a bag: a directory holding ``metadata.yaml``, or a file
    with a suffix of :data:`BAG_SUFFIXES`."""
    p = Path(path)
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or p.suffix.lower() in BAG_SUFFIXES


def bag_format(path: str | Path) -> str:
    p = Path(path)
    return "rosbag2 directory" if p.is_dir() else BAG_SUFFIXES.get(p.suffix.lower(), "bag")


@dataclass(frozen=True)
class BagTopic:
    """One topic's messages, in the bag's order: ``receive_ns`` (the bag's log time),
    ``stamp_ns`` (the header's stamp; None for a type without a header), ``frame_ids``
    (each frame id seen, with its count and the index of its first message), and
    ``fields[name]`` float64 ``(N,)`` for every field asked for."""

    topic: str
    msgtype: str
    receive_ns: np.ndarray
    stamp_ns: np.ndarray | None
    frame_ids: dict[str, tuple[int, int]]
    fields: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(self.receive_ns.shape[0])


@dataclass(frozen=True)
class _Layout:
    """Where one message's values lie: ``numbers[path] = (offset, dtype)`` for a single number,
    ``arrays[path] = (offset, dtype, count)`` for an array or sequence of numbers (element
    ``path[k]`` at ``offset + k * itemsize``); its strings; the structural byte spans
    (``(start, stop)``) that fix the layout."""

    numbers: dict[str, tuple[int, np.dtype]]
    arrays: dict[str, tuple[int, np.dtype, int]]
    strings: dict[str, str]
    spans: list[tuple[int, int]]

    def locate(self, path: str) -> tuple[int, np.dtype] | None:
        """The offset and type of the number at ``path`` (``a.b``, ``a[k]``), or None."""
        if path in self.numbers:
            return self.numbers[path]
        m = re.fullmatch(r"(.*)\[(\d+)\]", path)
        if m is None or m.group(1) not in self.arrays:
            return None
        off, dt, n = self.arrays[m.group(1)]
        k = int(m.group(2))
        return (off + k * dt.itemsize, dt) if k < n else None

    def fields(self) -> list[str]:
        """The numbers' paths for a message, an array's as ``path[K]``."""
        names = [re.sub(r"\[\d+\]", "[K]", k) for k in self.numbers]
        return list(dict.fromkeys([*names, *(f"{k}[K]" for k in self.arrays)]))


class _Walker:
    """Walks one serialised message over its type's field definitions (rosbags' typestore):
    ROS 2's CDR (a 4-byte encapsulation header, values aligned to their size from its end,
    strings NUL-terminated) or ROS 1's (no header, no alignment, no NUL)."""

    def __init__(self, fielddefs, buf: bytes, ros1: bool):
        self.defs, self.buf, self.ros1 = fielddefs, buf, ros1
        self.numbers: dict[str, tuple[int, np.dtype]] = {}
        self.arrays: dict[str, tuple[int, np.dtype, int]] = {}
        self.strings: dict[str, str] = {}
        if ros1:
            self.pos, self.little, self.spans = 0, True, []
        else:
            if len(buf) < 4 or buf[0] != 0 or buf[1] not in (0, 1):
                raise ValueError("not CDR (its encapsulation header is not 00 00 or 00 01)")
            self.pos, self.little, self.spans = 4, buf[1] == 1, [(0, 4)]

    def align(self, n: int) -> None:
        if not self.ros1:
            self.pos = 4 + -(-(self.pos - 4) // n) * n

    def take(self, n: int) -> int:
        start = self.pos
        if start + n > len(self.buf):
            raise ValueError(f"ends at byte {len(self.buf)}, before its fields do")
        self.pos += n
        return start

    def count(self) -> int:
        self.align(4)
        start = self.take(4)
        self.spans.append((start, start + 4))
        return int.from_bytes(self.buf[start:start + 4], "little" if self.little else "big")

    def base(self, path: str, name: str) -> None:
        if name == "string":
            n = self.count()
            i = self.take(n)
            self.spans[-1] = (self.spans[-1][0], self.pos)  # the length and the characters
            raw = self.buf[i:i + n]
            if not self.ros1:
                if n == 0 or raw[-1] != 0:
                    raise ValueError(f"string {path} is not NUL-terminated")
                raw = raw[:-1]
            self.strings[path] = raw.decode("utf-8", "replace")
            return
        size = _SIZES.get(name)
        if size is None:
            raise ValueError(f"field {path} has a type ({name}) the reader does not take")
        self.align(size)
        self.numbers[path] = (self.take(size), np.dtype(f"{'<' if self.little else '>'}{_KINDS[name]}{size}"))

    def node(self, path: str, node) -> None:
        kind, detail = int(node[0]), node[1]
        if kind == 1:  # a base type
            self.base(path, detail[0])
        elif kind == 2:  # a message
            self.message(path, detail)
        else:  # 3: an array of fixed length, 4: a sequence
            inner, n = detail
            if kind == 4:
                n = self.count()
                if n > len(self.buf):
                    raise ValueError(f"sequence {path} claims {n} elements in {len(self.buf)} bytes")
            if int(inner[0]) == 1 and inner[1][0] in _SIZES:  # numbers: where they start, at once
                size = _SIZES[inner[1][0]]
                if n:
                    self.align(size)
                self.arrays[path] = (self.take(size * n), np.dtype(
                    f"{'<' if self.little else '>'}{_KINDS[inner[1][0]]}{size}"), n)
                return
            for k in range(n):
                self.node(f"{path}[{k}]", inner)

    def message(self, prefix: str, typename: str) -> None:
        for name, node in self.defs[typename][1]:
            self.node(f"{prefix}.{name}" if prefix else name, node)


def _layout(fielddefs, typename: str, buf: bytes, ros1: bool) -> _Layout:
    w = _Walker(fielddefs, buf, ros1)
    w.message("", typename)
    if len(buf) - w.pos > (0 if ros1 else 3):  # CDR may pad the end to 4 bytes
        raise ValueError(f"holds {len(buf) - w.pos} bytes after its last field")
    return _Layout(w.numbers, w.arrays, w.strings, w.spans)


def _field_path(field: str, layout: _Layout) -> str | None:
    """A map's field (``linear_acceleration.x``, ``position[j3]``, ``data[2]``) as a path of
    the layout, a joint named in ``[...]`` looked up in the message's ``name``; None if absent."""
    parts = field.split(".")
    out = []
    for p in parts:
        m = _FIELD.fullmatch(p)
        if m is None:
            return None
        name, index = m.groups()
        if index is not None and not index.isdigit():
            names = [v for k, v in layout.strings.items() if re.fullmatch(r"name\[\d+\]", k)]
            if index not in names:
                return None
            index = str(names.index(index))
        out.append(name if index is None else f"{name}[{int(index)}]")
    path = ".".join(out)
    return path if layout.locate(path) is not None else None


def check_field(field: str) -> str | None:
    """Why ``field`` is not a field address, or None."""
    if not isinstance(field, str) or not all(_FIELD.fullmatch(p) for p in field.split(".")):
        return (f"{clipped_repr(field)} is not a field: write NAME.NAME (linear_acceleration.x), "
                "NAME[K] (data[2]) or NAME[JOINT] (position[j3])")
    return None


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def read_topics(path: str | Path, wanted: Mapping[str, Sequence[str]]) -> dict[str, BagTopic]:
    """For each topic of ``wanted`` its messages' times, frame ids and the fields named (see
    :class:`BagTopic`). :class:`ForeignFileError` naming the bag, the topic and the message's
    index for a bag that cannot be opened, a topic it lacks, a type not in
    :data:`MESSAGE_TYPES`, a message that does not decode, a field a message lacks."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    p = Path(path)
    if not p.exists():
        raise ForeignFileError(f"{p}: no such file or bag directory")
    if p.is_file():
        check_size(p)
    elif not p.is_dir():  # (a FIFO would block, /dev/zero not end)
        raise ForeignFileError(f"{p}: not a regular file or a bag directory (a device, a FIFO); a bag is "
                               "a file or a directory")
    else:  # a rosbag2 directory: its storage files together
        size = sum(f.stat().st_size for f in p.iterdir() if f.is_file())
        if size > MAX_FILE_BYTES:
            raise ForeignFileError(f"{p}: {size / 1e9:.1f} GB of storage is more than the import reads "
                                   f"({MAX_FILE_BYTES / 1e9:.1f} GB); split the bag")
    try:
        reader = AnyReader([p], default_typestore=_typestore())
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as e:
        why = clipped_repr(str(e), 120)[1:-1]
        raise ForeignFileError(f"{p}: not a readable {bag_format(p)} ({why})") from None
    try:
        present = {c.topic: c for c in reader.connections}
        problems = []
        for topic in wanted:
            c = present.get(topic)
            if c is None:
                problems.append(f"no topic {clipped_repr(topic)}; the bag has "
                                f"{available_words(sorted(present)) or 'none'}")
            elif c.msgtype not in MESSAGE_TYPES:
                problems.append(f"topic {topic} is {c.msgtype}; the import reads "
                                + ", ".join(MESSAGE_TYPES))
        if problems:
            raise ForeignFileError(f"{p}: " + "; ".join(problems))
        conns = [c for c in reader.connections if c.topic in wanted]
        raw: dict[str, list] = {t: [] for t in wanted}
        log: dict[str, list] = {t: [] for t in wanted}
        try:
            for c, t_ns, data in reader.messages(connections=conns):
                raw[c.topic].append(data)
                log[c.topic].append(t_ns)
        except Exception as e:  # the storage's own errors (a damaged chunk, a bad row)
            raise ForeignFileError(f"{p}: the bag's storage cannot be read ({type(e).__name__}: "
                                   f"{clipped_repr(str(e), 120)[1:-1]})") from None
        return {t: _decode(p, reader, present[t].msgtype, t, raw[t], log[t], wanted[t]) for t in wanted}
    finally:
        reader.close()


def _decode(path: Path, reader, msgtype: str, topic: str, raws: list, log_ns: list,
            fields: Sequence[str]) -> BagTopic:
    ros1 = not reader.is2
    defs = reader.typestore.fielddefs
    n = len(raws)
    lengths = np.fromiter((len(r) for r in raws), np.int64, n)
    values = {f: np.empty(n) for f in fields}
    has_header = defs[msgtype][1][0][0] == "header"
    stamp = np.empty(n, np.int64) if has_header else None
    frames: dict[str, list[int]] = {}
    where = f"{path}: topic {topic} ({msgtype})"
    layouts = 0
    for length in np.unique(lengths):
        idx = np.flatnonzero(lengths == length)
        block = np.frombuffer(b"".join(bytes(raws[i]) for i in idx), np.uint8).reshape(idx.size, int(length))
        while idx.size:
            layouts += 1
            if layouts > MAX_LAYOUTS:
                raise ForeignFileError(f"{where}: more than {MAX_LAYOUTS} message layouts (frame ids "
                                       "or joint names that change from message to message); the import "
                                       "takes a topic whose messages keep theirs")
            first = int(idx[0])
            buf = bytes(raws[first])
            try:
                lay = _layout(defs, msgtype, buf, ros1)
                decoded = reader.deserialize(buf, msgtype)
            except Exception as e:
                raise ForeignFileError(f"{where}: message {first} (from 0) does not decode: "
                                       f"{clipped_repr(str(e), 120)[1:-1]}") from None
            same = np.ones(idx.size, bool)
            for a, b in lay.spans:
                same &= (block[:, a:b] == block[0, a:b]).all(axis=1)
            rows = idx[same]
            part = block[same]
            for f in fields:
                fp = _field_path(f, lay)
                if fp is None:
                    have = ", ".join(k for k in lay.fields() if not k.startswith("header."))
                    names = [v for k, v in lay.strings.items() if k.startswith("name[")]
                    joints = f"; its joints {', '.join(names)}" if names else ""
                    raise ForeignFileError(f"{where}: message {first} (from 0) has no field "
                                           f"{clipped_repr(f)}{joints}; its numbers: "
                                           f"{clipped_repr(have, 200)[1:-1]}")
                off, dt = lay.locate(fp)
                col = part[:, off:off + dt.itemsize].copy().view(dt).reshape(-1).astype(np.float64)
                if not _agrees(decoded, fp, col[0]):
                    raise ForeignFileError(f"{where}: message {first} (from 0): field {f} reads "
                                           f"{col[0]!r} from its bytes but rosbags decodes otherwise")
                values[f][rows] = col
            if stamp is not None:
                (o_s, d_s), (o_n, d_n) = lay.numbers["header.stamp.sec"], lay.numbers["header.stamp.nanosec"]
                sec = part[:, o_s:o_s + 4].copy().view(d_s).reshape(-1).astype(np.int64)
                nsec = part[:, o_n:o_n + 4].copy().view(d_n).reshape(-1).astype(np.int64)
                stamp[rows] = sec * 1_000_000_000 + nsec
            frame = lay.strings.get("header.frame_id")
            if frame is not None:
                frames.setdefault(frame, []).extend(rows.tolist())
            idx, block = idx[~same], block[~same]
    frame_ids = {k: (len(v), min(v)) for k, v in sorted(frames.items(), key=lambda kv: min(kv[1]))}
    return BagTopic(topic, msgtype, np.asarray(log_ns, np.int64), stamp, frame_ids, values)


def _agrees(decoded, path: str, value: float) -> bool:
    """Whether rosbags' decoded message holds ``value`` at ``path``."""
    obj = decoded
    for part in path.split("."):
        m = _FIELD.fullmatch(part)
        obj = getattr(obj, m.group(1))
        if m.group(2) is not None:
            obj = obj[int(m.group(2))]
    v = float(obj)
    return v == value or (np.isnan(v) and np.isnan(value))
