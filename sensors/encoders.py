"""Joint encoder counts from the motor controller: the feed interface, UDP and simulated.

The WMRA's motor controller sends one UDP datagram per control cycle with the
seven joints' relative encoder counts. Datagram (network byte order, 48 bytes,
struct ``!4sBBHIQ7i``)::

    offset size type      field
    0      4    char[4]   magic     b"AFEN"
    4      1    uint8     version   1
    5      1    uint8     n_counts  7
    6      2    uint16    flags     bit 0 BOOT: first datagram since the controller
                                    (re)started; other bits 0
    8      4    uint32    seq       +1 per datagram, wraps 2**32 - 1 -> 0
    12     8    uint64    t_us      controller's monotonic clock, microseconds
    20     28   int32[7]  counts    joint 1..7, relative counts

The receiver checks every datagram: wrong size, magic, version or count number
-> counted as ``malformed`` and dropped. Sequence numbers (modulo 2**32): the
next expected one is accepted; a jump ahead is accepted and its gap counted as
``lost``; one already passed (up to ``reorder_window`` behind) is ``late`` and
dropped (it was counted as lost when the gap was seen: the stream stays in
order); an exact repeat is a ``duplicate`` and dropped; BOOT, or a jump back by
more than the window, is a controller ``restart``: the stream resynchronises and
the sample is flagged (its counts start again from the controller's power-up).
"""

from __future__ import annotations

import math
import random
import selectors
import socket
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from armfusion.sensors.samples import Stream, encoder_columns

MAGIC = b"AFEN"
VERSION = 1
N_JOINTS = 7
FLAG_BOOT = 0x0001
DATAGRAM = struct.Struct("!4sBBHIQ7i")
assert DATAGRAM.size == 48
DEFAULT_PORT = 47_100
LOOPBACK = "127.0.0.1"
SEQ_MOD = 1 << 32


class MalformedDatagram(ValueError):
    pass


@dataclass(frozen=True)
class Datagram:
    seq: int
    t_us: int
    counts: tuple[int, ...]
    flags: int = 0


def pack_datagram(seq: int, t_us: int, counts: Sequence[int], flags: int = 0) -> bytes:
    """The controller's side: one datagram (see the module docstring)."""
    if len(counts) != N_JOINTS:
        raise ValueError(f"a datagram carries {N_JOINTS} counts, got {len(counts)}")
    return DATAGRAM.pack(MAGIC, VERSION, N_JOINTS, flags, seq % SEQ_MOD, t_us, *counts)


def parse_datagram(data: bytes) -> Datagram:
    if len(data) != DATAGRAM.size:
        raise MalformedDatagram(f"{len(data)} bytes, expected {DATAGRAM.size}")
    magic, version, n, flags, seq, t_us, *counts = DATAGRAM.unpack(data)
    if magic != MAGIC:
        raise MalformedDatagram(f"magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise MalformedDatagram(f"version {version}, expected {VERSION}")
    if n != N_JOINTS:
        raise MalformedDatagram(f"{n} counts, expected {N_JOINTS}")
    return Datagram(seq, t_us, tuple(counts), flags)


@dataclass(frozen=True)
class EncoderSample:
    """One accepted datagram: host receive time, controller time, counts.

    ``restart``: first sample after a controller restart (counts re-zeroed there).
    """

    t_s: float
    t_controller_s: float
    seq: int
    counts: tuple[int, ...]
    restart: bool = False


@dataclass(frozen=True)
class EncoderStats:
    received: int = 0
    accepted: int = 0
    lost: int = 0
    late: int = 0
    duplicate: int = 0
    malformed: int = 0
    foreign: int = 0
    restarts: int = 0

    def summary(self) -> str:
        return ", ".join(f"{k} {v}" for k, v in self.__dict__.items())


class EncoderFeed(Protocol):
    """A source of encoder samples. ``poll`` never blocks longer than ``timeout_s``."""

    def poll(self, timeout_s: float = 0.0) -> list[EncoderSample]: ...

    def stats(self) -> EncoderStats: ...

    def close(self) -> None: ...


class SequenceTracker:
    """Loss / reorder / restart bookkeeping for a stream of sequence numbers."""

    def __init__(self, reorder_window: int = 64):
        self.reorder_window = reorder_window
        self.last: int | None = None
        self.counts = {"accepted": 0, "lost": 0, "late": 0, "duplicate": 0, "restarts": 0}

    def accept(self, seq: int, flags: int = 0) -> tuple[bool, bool]:
        """(accepted, restart) for this sequence number."""
        c = self.counts
        if self.last is None or flags & FLAG_BOOT:
            restart = self.last is not None
            c["restarts"] += restart
            self.last = seq
            c["accepted"] += 1
            return True, restart
        d = (seq - self.last) % SEQ_MOD
        if d == 0:
            c["duplicate"] += 1
            return False, False
        if d < SEQ_MOD // 2:
            c["lost"] += d - 1
            self.last = seq
            c["accepted"] += 1
            return True, False
        if SEQ_MOD - d <= self.reorder_window:
            c["late"] += 1
            return False, False
        c["restarts"] += 1
        self.last = seq
        c["accepted"] += 1
        return True, True


class UdpEncoderFeed:
    """Receive the controller's datagrams on ``host:port`` (default 127.0.0.1).

    ``host`` must be one interface's address: the wildcard (0.0.0.0, "", ::) is
    refused, so the feed is never reachable from every network the Pi is on. On
    the chair, pass the address of the interface that faces the controller;
    ``peer_host`` additionally drops datagrams from any other sender (counted as
    ``foreign``). ``port=0`` picks a free port (see ``address``).
    """

    def __init__(
        self,
        host: str = LOOPBACK,
        port: int = DEFAULT_PORT,
        *,
        peer_host: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        reorder_window: int = 64,
        max_per_poll: int = 1024,
    ):
        if host in ("", "0.0.0.0", "::", "*"):
            raise ValueError(
                f"UdpEncoderFeed will not bind to the wildcard address {host!r}: give the "
                "address of the interface that faces the motor controller (default 127.0.0.1)"
            )
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((host, port))
        except OSError:
            self._sock.close()
            raise
        self._sock.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._sock, selectors.EVENT_READ)
        self.peer_host = peer_host
        self.clock = clock
        self.max_per_poll = max_per_poll
        self._seq = SequenceTracker(reorder_window)
        self._counts = {"received": 0, "malformed": 0, "foreign": 0}
        self._last_t = float("-inf")

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def poll(self, timeout_s: float = 0.0) -> list[EncoderSample]:
        """Every datagram waiting (up to ``max_per_poll``), accepted ones in order."""
        if timeout_s > 0 and not self._sel.select(timeout_s):
            return []
        out: list[EncoderSample] = []
        for _ in range(self.max_per_poll):
            try:
                data, (src, _port) = self._sock.recvfrom(256)
            except BlockingIOError:
                break
            t = max(self.clock(), self._last_t + 1e-6)
            self._counts["received"] += 1
            if self.peer_host is not None and src != self.peer_host:
                self._counts["foreign"] += 1
                continue
            try:
                d = parse_datagram(data)
            except (MalformedDatagram, struct.error):
                self._counts["malformed"] += 1
                continue
            ok, restart = self._seq.accept(d.seq, d.flags)
            if ok:
                self._last_t = t
                out.append(EncoderSample(t, d.t_us * 1e-6, d.seq, d.counts, restart))
        return out

    def stats(self) -> EncoderStats:
        return EncoderStats(**self._counts, **self._seq.counts)

    def close(self) -> None:
        self._sel.close()
        self._sock.close()

    def __enter__(self) -> UdpEncoderFeed:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class UdpEncoderSender:
    """The controller's side, for tests and simulations: numbered datagrams to a feed."""

    def __init__(self, host: str = LOOPBACK, port: int = DEFAULT_PORT, *, first_seq: int = 0):
        self.target = (host, port)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.seq = first_seq
        self._boot = True

    def send(self, counts: Sequence[int], t_us: int) -> int:
        """Send one datagram with the next sequence number; returns that number."""
        seq = self.seq
        self.send_raw(pack_datagram(seq, t_us, counts, FLAG_BOOT if self._boot else 0))
        self._boot = False
        self.seq = (seq + 1) % SEQ_MOD
        return seq

    def send_raw(self, data: bytes) -> None:
        self._sock.sendto(data, self.target)

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> UdpEncoderSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SimulatedEncoderFeed:
    """Encoder samples from ``counts_at(t)`` at ``rate_hz`` on ``clock``'s time.

    Each ``poll`` returns the controller ticks that fell since the last one (at
    most 1 s of them), with sequence numbers and controller time like the UDP feed,
    and optionally drops a seeded fraction of them (counted as ``lost``).
    """

    def __init__(
        self,
        counts_at: Callable[[float], Sequence[int]],
        rate_hz: float = 100.0,
        *,
        clock: Callable[[], float] = time.monotonic,
        drop_probability: float = 0.0,
        seed: int = 0,
    ):
        self.counts_at = counts_at
        self.rate_hz = rate_hz
        self.clock = clock
        self.drop_probability = drop_probability
        self._rng = random.Random(seed)
        self._t0 = clock()
        self._k = 0
        self._seq = SequenceTracker()
        self._received = 0

    def poll(self, timeout_s: float = 0.0) -> list[EncoderSample]:
        now = self.clock()
        k_now = math.floor((now - self._t0) * self.rate_hz + 1e-9)
        first = max(self._k + 1, k_now - int(self.rate_hz) + 1)  # older ticks: lost
        out: list[EncoderSample] = []
        for k in range(first, k_now + 1):
            t = self._t0 + k / self.rate_hz
            if self.drop_probability and self._rng.random() < self.drop_probability:
                continue
            counts = tuple(int(c) for c in self.counts_at(t))
            if len(counts) != N_JOINTS:
                raise ValueError(f"counts_at(t) gave {len(counts)} counts, expected {N_JOINTS}")
            self._received += 1
            ok, restart = self._seq.accept(k)
            if ok:
                out.append(EncoderSample(t, t - self._t0, k, counts, restart))
        self._k = max(self._k, k_now)
        return out

    def stats(self) -> EncoderStats:
        return EncoderStats(received=self._received, **self._seq.counts)

    def close(self) -> None:
        pass


def encoder_stream(samples: Sequence[EncoderSample], name: str = "enc") -> Stream:
    """Accepted samples as the raw ``encoder`` stream (host receive times)."""
    t = np.array([s.t_s for s in samples], dtype=np.float64)
    v = np.array([s.counts for s in samples], dtype=np.int64).reshape(-1, N_JOINTS)
    return Stream(name, "encoder", t, v, encoder_columns(N_JOINTS))
