"""Load, CI-sized: four link accelerometers and the IMU (accelerometer, gyro, magnetometer,
temperature) and the encoders, all at 200 Hz, about one sample per message as a driver sends them,
in real time through Zenoh on 127.0.0.1 to the fusion node: no sample is lost, and every
instant after the startup calibration gives a joint state but those the node folded while
it was behind (its lateness policy), each counted. (Latency is measured by tools/soak.py,
not asserted here.)"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session
from armfusion.models.simulator import simulate
from service_helpers import Collected, cut, publish_live, wait_for


def _serve_process(port: int, **popen) -> subprocess.Popen:
    """``armfusion serve`` as its own process on 127.0.0.1:``port``, its JSON report at the end
    (``popen``: more of ``subprocess.Popen``'s arguments)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "armfusion.fusion.cli", "serve", "--robot", "chair1", "--listen",
         f"tcp/127.0.0.1:{port}", "--publish-hz", "1000", "--json"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)


def _when_serving(serve: subprocess.Popen, port: int) -> ZenohSettings:
    """Once ``serve`` says it serves (its stderr read on after, so a full pipe never stalls
    it): the settings of a session that connects to it."""
    line = serve.stderr.readline()
    assert "serving" in line, line + serve.stderr.read()[-2000:]
    threading.Thread(target=serve.stderr.read, daemon=True).start()
    return ZenohSettings(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])


@pytest.fixture(scope="module")
def at_200_hz():
    rec, _ = simulate(load_arm("wmra"), "startup", 2.5, 200.0, seed=21)
    return rec


def test_five_sensors_at_200_hz_lose_no_sample(hub_settings, fusion_node, at_200_hz):
    rec = at_200_hz
    raw = rec.raw()
    assert {"acc1", "acc2", "acc3", "acc4", "imu_acc", "imu_gyro", "imu_mag"} <= set(raw)
    assert all(s.rate_hz == pytest.approx(200.0) for s in raw.values())
    listener, connector = hub_settings
    # the startup calibration after 1 s of samples (not 2): more of the short run is tracking
    with fusion_node(listener, load_arm("wmra"), publish_hz=1000.0, min_data_s=1.0) as (node, result), \
            open_session(connector) as s:
        got = Collected(s)
        report = replay(s, rec, "chair1", ReplayPacing(speed=1.0, batch_s=0.005, wait_for_subscribers_s=5.0))
        published = sum(report.samples.values())
        assert published == sum(len(x) for x in raw.values())
        assert report.batches > 0.85 * published  # nearly one sample per message
        assert wait_for(lambda: node.report_samples() >= published, 30.0)
        t_last = float(raw["enc"].t_s[-1])
        # the reorder stage holds the newest instants until every sensor has sent them
        assert wait_for(lambda: got.snapshot()[0] and got.snapshot()[0][-1].t_s >= t_last - 0.11, 10.0)
    r = result["report"]
    assert r.samples == published and r.dropped == {} and r.out_of_order == 0, r
    assert r.missed_batches == 0
    assert r.startup_t_s is not None, r.message
    joints = got.snapshot()[0]
    t = np.array([j.t_s for j in joints])
    enc_t = raw["enc"].t_s
    # a joint state for every instant after the startup (bar the last ones the reorder stage
    # still held at the stop) but the folded ones, none twice, none out of order
    expected = enc_t[(enc_t > r.startup_t_s + 1e-9) & (enc_t <= t[-1] + 1e-9)]
    assert np.all(np.diff(t) > 0) and np.isin(t, expected).all()
    assert len(expected) - len(t) <= r.folded_instants  # (the last ones folded may come after t[-1])
    # folded or not, a joint state for every fold period of sample time at least, or every
    # tenth of the backlog when that is longer
    lt = node.lateness
    window_s = max(lt.fold_period_s, (r.lag_max_ms / 1e3 + 0.2) / lt.backlog_updates) + 1e-3
    assert t[0] - r.startup_t_s <= window_s and np.diff(t).max() <= window_s
    assert r.estimates >= len(t)


ROOT = Path(__file__).resolve().parents[2]


def test_a_node_that_fell_behind_degrades_says_so_and_refuses_no_catching_up_driver(
        renk_recording, loopback_port):
    """``armfusion serve`` as its own process tracks a live stream; it is stopped outright
    (SIGSTOP, as a starved machine would) for 0.6 s, and later every driver stalls for 0.4 s
    and then sends what it read meanwhile as one batch each. The node says it is degraded,
    with its lag, folds the stale instants instead of fusing them one by one, says when it
    has caught up, and refuses no batch: the drivers' catching up included."""
    rec = cut(renk_recording, 0.0, 6.5)
    port = loopback_port
    serve = _serve_process(port)
    try:
        settings = _when_serving(serve, port)
        with open_session(settings) as s:
            got = Collected(s)
            stopped = []

            def starve(t_s: float) -> None:
                # once the node tracks (its first joint state heard): a node still in its startup
                # (kernels compiling on a fresh install) has no live lag to judge
                if not stopped and t_s >= 4.0 and got.snapshot()[0]:
                    os.kill(serve.pid, signal.SIGSTOP)
                    time.sleep(0.6)
                    os.kill(serve.pid, signal.SIGCONT)
                    stopped.append(t_s)

            put = publish_live(s, rec, batch_s=0.01, stall=(5.2, 0.4), during=starve)
            assert wait_for(lambda: got.snapshot()[0] and got.snapshot()[0][-1].t_s > 6.35, 20.0)
            assert stopped, "the node published no joint state before the stream's end"
            time.sleep(1.2)  # a status after the end
            joints, statuses = got.snapshot()
    finally:
        serve.send_signal(signal.SIGINT)
        out, _ = serve.communicate(timeout=60)
    r = json.loads(out)
    assert r["startup_t_s"] is not None, r["message"]
    assert r["samples"] == put and r["dropped"] == {} and r["missed_batches"] == 0, r
    # it said so, with its lag, and said when it had caught up
    said = [(dict(st.counters), st.message) for st in statuses]
    degraded = [(c, m) for c, m in said if c.get("degraded") == 1]
    assert degraded, (said, {k: r.get(k) for k in ("degraded_periods", "folded_instants", "lag_max_ms")})
    # (degraded until back within 25 ms and last behind a second ago: held, it says so)
    assert all(c["lag_ms"] > 25 or "(held for 1 s after it was last behind)" in m for c, m in degraded)
    assert any(c["lag_ms"] > 50 for c, _ in degraded)
    # (after "stalled: …" when the stop outlasted the stall watch's second)
    assert all(("degraded: " in m) and " ms behind the sensors" in m for _, m in degraded)
    last_bad = max(i for i, (c, _) in enumerate(said) if c.get("degraded") == 1)
    assert any(c.get("degraded") == 0 for c, _ in said[last_bad + 1:]), "never caught up"
    assert r["degraded_periods"] >= 1 and r["folded_instants"] > 0 and r["lag_max_ms"] >= 300
    # the joint states: in order, one at least every fold period (20 ms) after the startup,
    # or every tenth of the backlog when that is longer, and true
    t = np.array([j.t_s for j in joints])
    assert np.all(np.diff(t) > 0)
    # (a backlog is the largest lag measured and at most 0.2 s more: the lag is measured
    # between passes, the reorder stage holds up to 0.1 s)
    window_s = max(0.02, (r["lag_max_ms"] / 1e3 + 0.2) / 10) + 1e-3
    assert np.diff(t[t > r["startup_t_s"] + 0.1]).max() <= window_s
    truth = renk_recording.truth()["true_q"]
    k = np.searchsorted(truth.t_s, t + 1e-9) - 1
    err = np.abs(np.angle(np.exp(1j * (np.array([j.q_rad for j in joints]) - truth.values[k]))))
    assert (err / np.array([j.sigma_rad for j in joints])).max() < 4.0


@pytest.fixture(scope="module")
def four_s_at_200_hz():
    rec, _ = simulate(load_arm("wmra"), "startup", 4.0, 200.0, seed=22)
    return rec


def test_a_node_collecting_for_its_startup_keeps_up_with_the_stream(hub_settings, fusion_node,
                                                                    four_s_at_200_hz):
    """A node that collects samples for its startup calibration (here for longer than the
    stream lasts) takes every batch in as it comes: the cost of a batch does not grow with
    what it has kept (about 1800 messages a second of 200 Hz streams, one sample each)."""
    listener, connector = hub_settings
    with fusion_node(listener, load_arm("wmra"), min_data_s=60.0, startup_keep_s=120.0) as (node, result), \
            open_session(connector) as s:
        got = Collected(s)
        put = publish_live(s, four_s_at_200_hz, batch_s=0.005)
        # (a node that merged its kept batches on every message took tens of seconds more)
        assert wait_for(lambda: node.report_samples() >= put, 3.0), (node.report_samples(), put)
        time.sleep(1.1)  # a status after the end
        statuses = got.snapshot()[1]
    r = result["report"]
    assert r.samples == put and r.dropped == {} and r.startup_t_s is None
    assert "collecting 60 s of samples for the startup calibration" in statuses[-1].message


def test_a_node_waiting_for_a_still_arm_keeps_a_bounded_stretch(hub_settings, fusion_node):
    """An arm that never stops (everything moving at once) gives the startup no still stretch:
    the node waits, and while it waits it keeps only the latest ``startup_keep_s`` of samples
    (a quarter more before it lets the oldest go), however long the stream lasts, taking
    every sample in all the same."""
    rec, _ = simulate(load_arm("wmra"), "excitation", 14.0, 100.0, seed=3)
    rec = rec.between(rec.t_start_s + 2.0, np.inf)  # (it starts still: from its motion on)
    listener, connector = hub_settings
    with fusion_node(listener, load_arm("wmra"), min_data_s=1.0, startup_keep_s=3.0) as (node, result), \
            open_session(connector) as s:
        got = Collected(s)
        put = publish_live(s, rec, batch_s=0.02)
        assert wait_for(lambda: node.report_samples() >= put, 5.0), (node.report_samples(), put)
        kept_s = node.startup_kept_s
        time.sleep(1.1)  # a status after the end
        statuses = got.snapshot()[1]
    r = result["report"]
    assert r.samples == put and r.startup_t_s is None
    assert 2.0 < kept_s <= 1.25 * 3.0 + 0.05, kept_s
    assert "waiting for a still arm" in statuses[-1].message


def test_a_node_refuses_a_startup_stretch_shorter_than_its_collection():
    from armfusion.fusion.service.serve_settings import NodeSettings

    with pytest.raises(ValueError,
                       match=r"startup_keep_s must be at least twice min_data_s \(4 s\), not 3.0"):
        NodeSettings(min_data_s=2.0, startup_keep_s=3.0)


def test_a_node_starved_from_the_streams_start_says_it_is_degraded_while_behind(
        four_s_at_200_hz, loopback_port):
    """``armfusion serve`` as its own process, starved of CPU from the stream's first batch
    (stopped 150 ms of every 250 ms, SIGSTOP/SIGCONT, as a machine whose cores other work
    takes): while the stream is still published, its status says ``degraded`` with its lag
    (the node does not first take seconds of the stream in one instant at a time), it
    folds, and it refuses no genuine batch, neither as ahead of the sensors' clock nor as
    too dense; what waited too long in its channel it sheds, counted."""
    rec = four_s_at_200_hz
    port = loopback_port
    serve = _serve_process(port)
    done = threading.Event()

    def starve() -> None:
        while not done.is_set():
            os.kill(serve.pid, signal.SIGSTOP)
            time.sleep(0.15)
            os.kill(serve.pid, signal.SIGCONT)
            time.sleep(0.1)

    starver = threading.Thread(target=starve, daemon=True)
    try:
        settings = _when_serving(serve, port)
        with open_session(settings) as s:
            got = Collected(s)
            # (from the first batch on: the first window's callback starts the starving)
            put = publish_live(s, rec, batch_s=0.005,
                               during=lambda _t: None if starver.ident else starver.start())
            while_published = got.snapshot()[1]
            done.set()
            starver.join()
            os.kill(serve.pid, signal.SIGCONT)
            assert wait_for(lambda: got.snapshot()[0] and got.snapshot()[0][-1].t_s > 3.8, 20.0)
    finally:
        done.set()
        os.kill(serve.pid, signal.SIGCONT)
        serve.send_signal(signal.SIGINT)
        out, _ = serve.communicate(timeout=60)
    r = json.loads(out)
    # every sample admitted, or shed unread while it waited too long (counted, not missed)
    assert r["samples"] + r["shed_samples"] == put and r["missed_batches"] == 0, r
    assert r["dropped"] == {} and r["refused_samples"] == {}, r
    said = [(dict(st.counters), st.message) for st in while_published]
    degraded = [(c, m) for c, m in said if c.get("degraded") == 1]
    assert degraded, said
    assert all((c["lag_ms"] > 25 or "(held for 1 s after it was last behind)" in m)
               and " ms behind the sensors" in m for c, m in degraded)
    assert any(c["lag_ms"] > 50 for c, _ in degraded)
    assert r["folded_instants"] > 0


SPIN = "import time\nt = time.monotonic() + {s}\nwhile time.monotonic() < t:\n    pass\n"


def test_a_node_short_of_cpu_for_its_messages_keeps_its_lag_bounded(four_s_at_200_hz, loopback_port):
    """``armfusion serve`` on one core that three spinning processes share with it (a
    quarter of a core, less than taking 1800 messages a second in costs on a slow machine):
    its lag stays bounded while the stream lasts (what waited too long in its channel is
    shed unread, counted; the rest admitted), and no genuine batch is refused or counted as
    missed."""
    rec = four_s_at_200_hz
    port = loopback_port
    core = {min(os.sched_getaffinity(0))}
    serve = _serve_process(port, preexec_fn=lambda: os.sched_setaffinity(0, core))
    spinners = []
    try:
        settings = _when_serving(serve, port)
        spinners = [subprocess.Popen([sys.executable, "-c", SPIN.format(s=30.0)],
                                     preexec_fn=lambda: os.sched_setaffinity(0, core)) for _ in range(3)]
        with open_session(settings) as s:
            got = Collected(s)
            put = publish_live(s, rec, batch_s=0.005)
            lags = [dict(st.counters).get("lag_ms", 0) for st in got.snapshot()[1]]
            for p in spinners:
                p.kill()
            assert wait_for(lambda: got.snapshot()[0] and got.snapshot()[0][-1].t_s > 3.8, 20.0)
    finally:
        for p in spinners:
            p.kill()
            p.wait()
        serve.send_signal(signal.SIGINT)
        out, _ = serve.communicate(timeout=60)
    r = json.loads(out)
    assert r["samples"] + r["shed_samples"] == put and r["missed_batches"] == 0, r
    assert r["dropped"] == {} and r["refused_samples"] == {}, r
    # (a node that took every message in one by one fell further behind the longer the stream
    # lasted: seconds by its end)
    assert lags and max(lags) < 1500, (lags, {k: r[k] for k in ("lag_max_ms", "shed_samples")})
