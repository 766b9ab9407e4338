"""A FusionNode over a loopback Zenoh session while its drivers stop in the middle of a
read: the sensors read before the stop are sent after it, next to those read after it
(what a drivers' process starved of CPU does). No genuine batch is refused (the clock
that carried each stream forward from its newest batch's arrival refused those read after
the stop as time_ahead)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.fusion.service.zenoh_config import open_session
from armfusion.sensors.samples import Stream
from service_helpers import cut, wait_for

BATCH_S = 0.01
STALL_AT_S, STALL_S = 4.0, 1.5
"""The drivers stop at this sample time for this long, with the first five sensors (of
nine, in the drivers' order) read and the rest not: most of the streams' newest samples
then arrive 1.5 s after they were read."""
READ_BEFORE = 5


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


def test_sensors_read_before_a_driver_stall_and_sent_after_it_are_not_refused(
        hub_settings, fusion_node, arm, renk_recording):
    listener, connector = hub_settings
    part1, part2 = cut(renk_recording, 0.0, 3.0), cut(renk_recording, 3.0, 6.5)
    streams = {k: s for k, s in part2.raw().items() if len(s)}
    assert len(streams) == 9
    before = list(streams)[:READ_BEFORE]
    with fusion_node(listener, arm, publish_hz=1000.0) as (node, result), open_session(connector) as s:
        sent = sum(replay(s, part1, "chair1",
                          ReplayPacing(speed=None, wait_for_subscribers_s=5.0)).samples.values())
        assert wait_for(lambda: node.report_samples() >= sent, 30.0)
        pubs = {k: s.declare_publisher(pl.raw_key("chair1", k)) for k in streams}
        done, seq = dict.fromkeys(streams, 0), dict.fromkeys(streams, 10**4)

        def send(k: str, upto_s: float) -> int:
            st = streams[k]
            i1 = int(np.searchsorted(st.t_s, upto_s, side="right"))
            if i1 <= done[k]:
                return 0
            part = Stream(k, st.kind, st.t_s[done[k]:i1], st.values[done[k]:i1], st.channels)
            pubs[k].put(pl.encode(pl.RawBatch("chair1", part, seq[k])))
            n, done[k], seq[k] = i1 - done[k], i1, seq[k] + 1
            return n

        wall0 = time.monotonic()
        resumed_s, stalled = STALL_AT_S + STALL_S, 0
        for edge in np.round(np.arange(3.0 + BATCH_S, 6.5 + BATCH_S, BATCH_S), 6):
            if STALL_AT_S <= edge < resumed_s:  # (the batch read when it began goes out after it)
                continue
            time.sleep(max(wall0 + (edge - 3.0) - time.monotonic(), 0.0))
            after = edge == resumed_s  # (the batch read across the stall)
            stalled += after
            sent += sum(send(k, STALL_AT_S if after and k in before else edge) for k in streams)
            if after:  # the next read: the samples of the stall of those read before it, at once
                sent += sum(send(k, edge) for k in before)
        assert stalled == 1
        taken = wait_for(lambda: node.report_samples() >= sent, 10.0)
        assert taken and not node.refused(), (node.report_samples(), sent, node.refused())
    r = result["report"]
    assert r.dropped == {} and r.samples == sent, r
