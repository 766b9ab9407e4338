"""A rosbag2 MCAP file: ROS 2 messages, CDR-encoded, in one ``.mcap`` file as ``ros2 bag
record -s mcap`` writes them, so that ``ros2 bag play``, Foxglove and any MCAP reader with ROS 2
support take it as it is.

Each topic is a channel with message encoding ``cdr`` and a schema of encoding ``ros2msg``
whose text is the type's definition with every nested type's after it (the
``====...`` separated form ``ros2 bag`` writes), made by ``rosbags``' type store (ROS 2
Humble's standard messages); the messages are serialised by the same store.
``log_time = publish_time =`` the message's time in ns. Knows nothing of arms: a caller
builds the messages (:meth:`Ros2McapWriter.make`) and writes them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

PROFILE = "ros2"
"""The MCAP profile of a rosbag2 file."""


def typestore():
    """ROS 2 Humble's standard message types (rosbags' store)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


class Ros2McapWriter:
    """Writes ROS 2 messages to one MCAP file; use in a ``with`` block. ``make(msgtype,
    **fields)`` builds a message of a type of the store, ``write(topic, msgtype, t_ns, msg)``
    writes it (the topic's channel and schema made at its first message)."""

    def __init__(self, path: str | Path, library: str = "armfusion"):
        self._store = typestore()
        self._fh = open(Path(path), "wb")
        self._writer = Writer(self._fh, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=library)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self.counts: dict[str, int] = {}
        """Messages written per topic."""

    def __enter__(self) -> Ros2McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def make(self, msgtype: str, **fields: Any) -> Any:
        """A message of ``msgtype`` (``sensor_msgs/msg/Imu``) from its fields."""
        return self._store.types[msgtype](**fields)

    def _channel(self, topic: str, msgtype: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != msgtype:
                raise ValueError(f"topic {topic} carries {known[1]}, not {msgtype}")
            return known[0]
        if msgtype not in self._schemas:
            text, _ = self._store.generate_msgdef(msgtype, ros_version=2)
            self._schemas[msgtype] = self._writer.register_schema(msgtype, "ros2msg", text.encode("utf-8"))
        cid = self._writer.register_channel(topic, "cdr", self._schemas[msgtype])
        self._channels[topic] = (cid, msgtype)
        self.counts[topic] = 0
        return cid

    def write(self, topic: str, msgtype: str, t_ns: int, message: Any) -> None:
        cid = self._channel(topic, msgtype)
        data = bytes(self._store.serialize_cdr(message, msgtype))
        self._writer.add_message(cid, log_time=int(t_ns), publish_time=int(t_ns), data=data,
                                 sequence=self.counts[topic])
        self.counts[topic] += 1

    def close(self) -> None:
        if self._fh.closed:
            return
        try:
            self._writer.finish()
        finally:
            self._fh.close()
