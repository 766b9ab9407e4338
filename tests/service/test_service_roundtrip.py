"""replay -> Zenoh (127.0.0.1, ephemeral port) -> record: every raw sample arrives unchanged."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.record import Recorder
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.fusion.service.zenoh_config import open_session
from armfusion.sensors.recording import read_recording
from armfusion.sensors.samples import Stream


def _wait(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not pred() and time.monotonic() < deadline:
        time.sleep(0.02)
    return pred()


def _rig_slice():
    """The first 3 s of the real rig's slice as `armfusion import` makes it: values in g and
    deg/s with decimals (tests/data/imu-rig)."""
    from pathlib import Path

    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.importing.column_map import load_column_map
    from armfusion.fusion.importing.run import import_recording

    src = Path(__file__).resolve().parents[1] / "data" / "imu-rig" / "raw_roll_slow_20s.mat"
    arm = load_arm("imu_rig_roll")
    rec = import_recording(src, load_column_map("imu-rig"), arm, "imu_rig_roll").recording
    return rec.between(rec.t_start_s, rec.t_start_s + 3.0)


@pytest.mark.parametrize("source", ["simulated counts", "an imported recording's decimals"])
def test_replay_to_record_loses_no_sample(hub_settings, startup_recording, tmp_path, source):
    rec = read_recording(startup_recording) if source == "simulated counts" else _rig_slice()
    assert source == "simulated counts" or rec.get("shaft").values.dtype == np.float64
    listener, connector = hub_settings
    out = tmp_path / "recorded.mcap"
    stop = threading.Event()
    result = {}
    with open_session(listener) as rec_session:
        recorder = Recorder(rec_session, out, "chair1")
        th = threading.Thread(target=lambda: result.setdefault("r", recorder.run(stop)))
        th.start()
        try:
            assert recorder.ready.wait(5.0)
            with open_session(connector) as pub_session:
                report = replay(pub_session, rec, "chair1",
                                ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
                assert report.unmatched == ()
                assert _wait(lambda: recorder.counts() == report.samples, 10.0), \
                    (recorder.counts(), report.samples)
        finally:
            stop.set()
            th.join(10.0)
    got = read_recording(out)
    rr = result["r"]
    assert rr.dropped == {}
    raw = rec.raw()
    assert set(got.raw()) == set(raw)
    for k, s in raw.items():
        g = got.raw()[k]
        assert g.kind == s.kind and g.channels == s.channels
        np.testing.assert_array_equal(g.t_s, s.t_s)
        np.testing.assert_array_equal(g.values, s.values)


def test_replay_keeps_the_recording_timing(hub_settings, startup_recording):
    """At speed 4, 4 s of recording take about 1 s of wall time (not less: it is paced)."""
    rec = read_recording(startup_recording)
    _, connector = hub_settings
    with open_session(connector) as s:
        report = replay(s, rec, "chair1", ReplayPacing(speed=4.0))
    assert 0.95 <= report.wall_s <= 2.0
    assert sum(report.samples.values()) == sum(len(x) for x in rec.raw().values())


def test_recorder_drops_bad_payloads_and_keeps_recording(hub_settings, tmp_path):
    listener, connector = hub_settings
    stop = threading.Event()
    result = {}
    with open_session(listener) as rec_session:
        recorder = Recorder(rec_session, tmp_path / "r.mcap", "chair1")
        th = threading.Thread(target=lambda: result.setdefault("r", recorder.run(stop)))
        th.start()
        try:
            assert recorder.ready.wait(5.0)
            with open_session(connector) as s:
                key = pl.raw_key("chair1", "acc1")
                pub = s.declare_publisher(key)
                assert _wait(lambda: pub.matching_status, 5.0)
                pub.put(b"not json")
                pub.put(b'{"v": 99, "type": "raw"}')
                good = pl.RawBatch("chair1", Stream("acc1", "accel", [0.5], [[1, 2, 3]],
                                                       ("acc1_x", "acc1_y", "acc1_z")), 0)
                pub.put(pl.encode(good))
                assert _wait(lambda: recorder.counts() == {"acc1": 1}, 5.0)
        finally:
            stop.set()
            th.join(10.0)
    assert result["r"].dropped == {"malformed": 1, "unknown_version": 1}


def test_recorder_flushes_within_a_second_while_it_runs(hub_settings, tmp_path):
    """What a SIGKILL would leave: the file as it is while recording holds what came >1 s ago."""
    import shutil
    import warnings

    listener, connector = hub_settings
    stop = threading.Event()
    out = tmp_path / "live.mcap"
    with open_session(listener) as rec_session:
        recorder = Recorder(rec_session, out, "chair1")
        th = threading.Thread(target=recorder.run, args=(stop,))
        th.start()
        try:
            assert recorder.ready.wait(5.0)
            with open_session(connector) as s:
                pub = s.declare_publisher(pl.raw_key("chair1", "acc1"))
                assert _wait(lambda: pub.matching_status, 5.0)
                t = 0.01 * np.arange(1, 51)
                batch = Stream("acc1", "accel", t, np.tile([1, 2, 3], (50, 1)),
                               ("acc1_x", "acc1_y", "acc1_z"))
                pub.put(pl.encode(pl.RawBatch("chair1", batch, 0)))
                assert _wait(lambda: recorder.counts() == {"acc1": 50}, 5.0)
                time.sleep(1.3)  # nothing more arrives: the recorder must flush by itself
                shutil.copy(out, tmp_path / "killed.mcap")
        finally:
            stop.set()
            th.join(10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the copy ends early: that is the point
        got = read_recording(tmp_path / "killed.mcap")
    assert not got.meta["read_report"].complete
    assert len(got.raw()["acc1"]) == 50


def test_replay_waits_for_subscribers_and_names_the_sensors_nobody_hears(hub_settings, startup_recording):
    """Without a subscriber, replay waits the time it was given, then publishes anyway and
    reports every raw stream as unmatched (a subscriber that joins late would miss samples)."""
    rec = read_recording(startup_recording)
    _, connector = hub_settings
    with open_session(connector) as s:
        t0 = time.monotonic()
        report = replay(s, rec, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=0.5))
        waited = time.monotonic() - t0
    assert set(report.unmatched) == set(rec.raw())
    assert waited >= 0.5
