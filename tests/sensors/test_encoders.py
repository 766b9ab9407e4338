"""Encoder feed: datagram layout, loss / reorder / malformed handling, simulated feed.

The UDP tests use the loopback interface only (127.0.0.1, a free port)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from armfusion.sensors.encoders import (
    DATAGRAM,
    FLAG_BOOT,
    MalformedDatagram,
    SequenceTracker,
    SimulatedEncoderFeed,
    UdpEncoderFeed,
    UdpEncoderSender,
    encoder_stream,
    pack_datagram,
    parse_datagram,
)
from armfusion.sensors.fakes import FakeClock

COUNTS = (1, -2, 300_000, -400_000, 2**31 - 1, -(2**31), 0)


def test_datagram_layout_is_the_documented_one():
    d = pack_datagram(0x01020304, 0x1122334455667788, COUNTS, FLAG_BOOT)
    assert len(d) == DATAGRAM.size == 48
    assert d[0:4] == b"AFEN" and d[4] == 1 and d[5] == 7
    assert d[6:8] == b"\x00\x01"  # flags, big-endian
    assert d[8:12] == b"\x01\x02\x03\x04"  # sequence, big-endian u32
    assert d[12:20] == bytes.fromhex("1122334455667788")  # controller µs, u64
    assert struct.unpack("!7i", d[20:48]) == COUNTS
    p = parse_datagram(d)
    assert (p.seq, p.t_us, p.counts, p.flags) == (0x01020304, 0x1122334455667788, COUNTS, 1)


@pytest.mark.parametrize("data, why", [
    (pack_datagram(1, 0, COUNTS)[:-1], "47 bytes, expected 48"),
    (b"XXXX" + pack_datagram(1, 0, COUNTS)[4:], "magic b'XXXX'"),
    (pack_datagram(1, 0, COUNTS)[:4] + b"\x02" + pack_datagram(1, 0, COUNTS)[5:], "version 2"),
    (pack_datagram(1, 0, COUNTS)[:5] + b"\x06" + pack_datagram(1, 0, COUNTS)[6:], "6 counts"),
])
def test_malformed_datagrams_are_rejected(data, why):
    with pytest.raises(MalformedDatagram, match=why):
        parse_datagram(data)


@pytest.mark.parametrize("seqs, accepted, lost, late, dup, restarts", [
    ([0, 1, 2, 3], [0, 1, 2, 3], 0, 0, 0, 0),
    ([0, 1, 4, 5], [0, 1, 4, 5], 2, 0, 0, 0),
    ([0, 1, 3, 2, 4], [0, 1, 3, 4], 1, 1, 0, 0),  # 2 came late: counted lost, then late
    ([0, 1, 1, 2], [0, 1, 2], 0, 0, 1, 0),
    ([2**32 - 2, 2**32 - 1, 0, 1], [2**32 - 2, 2**32 - 1, 0, 1], 0, 0, 0, 0),  # wraps
    ([5000, 5001, 3, 4], [5000, 5001, 3, 4], 0, 0, 0, 1),  # far behind: restart
])
def test_sequence_tracking(seqs, accepted, lost, late, dup, restarts):
    tr = SequenceTracker(reorder_window=64)
    got = [s for s in seqs if tr.accept(s)[0]]
    assert got == accepted
    c = tr.counts
    assert (c["lost"], c["late"], c["duplicate"], c["restarts"]) == (lost, late, dup, restarts)


@pytest.fixture
def feed():
    with UdpEncoderFeed("127.0.0.1", 0) as f:
        yield f


def receive(feed: UdpEncoderFeed, n: int):
    got = []
    for _ in range(50):
        got += feed.poll(timeout_s=0.05)
        if feed.stats().received >= n:
            break
    return got


def test_udp_in_order(feed):
    with UdpEncoderSender(*feed.address) as tx:
        for i in range(20):
            tx.send([i * j for j in range(7)], t_us=1000 * i)
    got = receive(feed, 20)
    assert [s.seq for s in got] == list(range(20))
    assert got[5].counts == tuple(5 * j for j in range(7)) and got[5].t_controller_s == 0.005
    assert got[0].restart is False  # the first BOOT is the start, not a restart
    st = feed.stats()
    assert (st.received, st.accepted, st.lost, st.late, st.malformed) == (20, 20, 0, 0, 0)
    assert np.all(np.diff([s.t_s for s in got]) > 0)
    stream = encoder_stream(got)
    assert stream.kind == "encoder" and stream.values.shape == (20, 7)


def test_udp_loss_reorder_duplicates_and_garbage_are_counted_and_dropped(feed):
    with UdpEncoderSender(*feed.address) as tx:
        for seq in [0, 1, 2, 5, 4, 6, 6, 7]:  # 3 lost, 4 late, 6 twice
            tx.send_raw(pack_datagram(seq, seq * 1000, COUNTS))
        tx.send_raw(b"hello")
        tx.send_raw(b"XXXX" + pack_datagram(8, 0, COUNTS)[4:])
        tx.send_raw(pack_datagram(8, 8000, COUNTS))
    got = receive(feed, 11)
    assert [s.seq for s in got] == [0, 1, 2, 5, 6, 7, 8]
    st = feed.stats()
    assert (st.received, st.accepted, st.lost, st.late, st.duplicate, st.malformed) == (
        11, 7, 2, 1, 1, 2)


def test_controller_restart_is_flagged(feed):
    with UdpEncoderSender(*feed.address) as tx:
        for i in range(3):
            tx.send(COUNTS, t_us=i)
    with UdpEncoderSender(*feed.address) as tx:  # rebooted controller: seq 0 with BOOT
        tx.send((0,) * 7, t_us=0)
    got = receive(feed, 4)
    assert [(s.seq, s.restart) for s in got] == [(0, False), (1, False), (2, False), (0, True)]
    assert feed.stats().restarts == 1


def test_datagrams_from_another_sender_are_dropped():
    with UdpEncoderFeed("127.0.0.1", 0, peer_host="127.0.0.2") as f:
        with UdpEncoderSender(*f.address) as tx:
            tx.send(COUNTS, t_us=0)
        assert receive(f, 1) == [] and f.stats().foreign == 1


@pytest.mark.parametrize("host", ["0.0.0.0", ""])
def test_never_binds_to_every_interface(host):
    with pytest.raises(ValueError, match="will not bind to the wildcard address"):
        UdpEncoderFeed(host, 0)


def test_default_host_is_loopback():
    with UdpEncoderFeed(port=0) as f:
        assert f.address[0] == "127.0.0.1"


def test_simulated_feed_follows_its_clock():
    clock = FakeClock()

    def counts_at(t):
        return [round(1000 * t) + j for j in range(7)]

    feed = SimulatedEncoderFeed(counts_at, rate_hz=100, clock=clock.monotonic)
    got = []
    for _ in range(100):
        clock.sleep(0.01)
        got += feed.poll()
    assert [s.seq for s in got] == list(range(1, 101))
    assert all(s.counts == tuple(counts_at(s.t_s)) for s in got)
    assert feed.stats().lost == 0


def test_simulated_feed_drops_are_counted_as_lost():
    clock = FakeClock()
    feed = SimulatedEncoderFeed(lambda t: [0] * 7, rate_hz=100, clock=clock.monotonic,
                                drop_probability=0.2, seed=4)
    got = []
    for _ in range(200):
        clock.sleep(0.01)
        got += feed.poll()
    seqs = [s.seq for s in got]
    # every missing sequence number between the first and last accepted is counted
    assert feed.stats().lost == (seqs[-1] - seqs[0] + 1) - len(seqs) > 10
