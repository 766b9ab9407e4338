"""`armfusion record` and `armfusion replay` as processes: SIGTERM closes the file cleanly."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

from armfusion.fusion.cli.main import app
from armfusion.sensors.recording import read_recording
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[2]


def _cli(*args: str, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "armfusion.fusion.cli", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _first_line(proc: subprocess.Popen, timeout_s: float = 300.0) -> str:
    """The process's first line on stderr; a failure, not a hang, when none comes within
    ``timeout_s`` (the first node of a run compiles its kernels: minutes on a busy machine)."""
    import threading

    got: list[str] = []
    reader = threading.Thread(target=lambda: got.append(proc.stderr.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    assert got, f"nothing on stderr within {timeout_s:.0f} s"
    return got[0]


def test_record_and_replay_processes_round_trip_and_sigterm_closes(startup_recording, tmp_path,
                                                                   loopback_port):
    port = loopback_port
    out = tmp_path / "rec.mcap"
    recorder = _cli("record", str(out), "--listen", f"tcp/127.0.0.1:{port}", "--json")
    try:
        line = _first_line(recorder)
        assert "recording armfusion/chair1/raw/*" in line, line
        player = _cli("replay", str(startup_recording), "--speed", "max", "--wait", "10",
                      "--connect", f"tcp/127.0.0.1:{port}", "--json")
        pout, perr = player.communicate(timeout=60)
        assert player.returncode == 0, perr
        published = json.loads(pout)
        assert published["unmatched"] == []
        # only a recorder listens: no fusion node's admission to judge by
        assert published["admission"]["state"] == "unknown"
    finally:
        recorder.send_signal(signal.SIGTERM)
        rout, rerr = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, rerr
    recorded = json.loads(rout)
    assert recorded["samples"] == published["samples"]
    assert recorded["dropped"] == {}
    got = read_recording(out)  # a complete file: no RecordingWarning (pytest would show it)
    assert got.meta["read_report"].complete
    assert {k: len(s) for k, s in got.raw().items()} == published["samples"]


def test_a_non_loopback_endpoint_is_refused_before_anything_is_sent(startup_recording):
    r = CliRunner().invoke(app, ["replay", str(startup_recording), "--connect", "tcp/10.1.2.3:7447"])
    assert r.exit_code == 2
    assert "'tcp/10.1.2.3:7447': 10.1.2.3 is not a loopback address" in r.output


def test_bad_speed_is_refused(startup_recording):
    r = CliRunner().invoke(app, ["replay", str(startup_recording), "--speed", "fast"])
    assert r.exit_code == 2
    assert "expected a factor > 0 (1 = real time) or 'max'" in r.output


def test_serve_process_calibrates_on_a_replay_and_stops_on_sigint(startup_recording, loopback_port):
    from armfusion.fusion.service.replay import ReplayPacing, replay
    from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session

    server = _cli("serve", "--listen", f"tcp/127.0.0.1:{loopback_port}", "--json")
    try:
        line = _first_line(server)
        assert "as chair1: armfusion/chair1/raw/* in" in line, line
        rec = read_recording(startup_recording)
        settings = ZenohSettings(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{loopback_port}"])
        with open_session(settings) as s:
            report = replay(s, rec, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=10.0))
        assert report.unmatched == ()
    finally:
        server.send_signal(signal.SIGINT)
        out, err = server.communicate(timeout=30)
    assert server.returncode == 0, err
    doc = json.loads(out)
    assert doc["startup_t_s"] is not None, doc["message"]
    assert doc["estimates"] > 0 and doc["dropped"] == {}


def test_replay_to_an_endpoint_nobody_listens_on_exits_1_saying_so(startup_recording, loopback_port):
    r = CliRunner().invoke(app, ["replay", str(startup_recording), "--speed", "max", "--wait", "1",
                                 "--connect", f"tcp/127.0.0.1:{loopback_port}"])
    assert r.exit_code == 1, r.output
    assert "nothing subscribes to armfusion/chair1/raw/* (waited 1 s)" in r.output
    assert "Nothing was published" in r.output


def test_replay_to_a_node_that_listens_for_another_robot_exits_1(startup_recording, hub_settings):
    from armfusion.fusion.service.zenoh_config import open_session

    listener, _ = hub_settings
    with open_session(listener) as s:
        s.declare_subscriber("armfusion/chair2/raw/*", lambda sample: None)
        r = CliRunner().invoke(app, ["replay", str(startup_recording), "--speed", "max", "--wait", "1",
                                     "--connect", listener.listen[0]])
    assert r.exit_code == 1, r.output
    assert "nothing subscribes to armfusion/chair1/raw/*" in r.output


def test_replay_counts_what_went_out_after_its_subscriber_left(startup_recording, hub_settings):
    import threading
    import time

    from armfusion.fusion.service.replay import ReplayPacing, replay
    from armfusion.fusion.service.zenoh_config import open_session
    from armfusion.sensors.recording import read_recording

    listener, connector = hub_settings
    rec = read_recording(startup_recording)
    with open_session(listener) as node, open_session(connector) as s:
        sub = node.declare_subscriber("armfusion/chair1/raw/*", lambda sample: None)
        threading.Timer(2.0, sub.undeclare).start()  # the subscriber leaves after 2 s of the 4 s
        start = time.monotonic()
        report = replay(s, rec, "chair1",
                        ReplayPacing(speed=1.0, wait_for_subscribers_s=5.0, require_subscriber=True))
    assert report.unmatched == () and time.monotonic() - start > 3.5
    total = sum(report.samples.values())
    unheard = sum(report.unheard.values())
    assert 0.2 * total < unheard < 0.8 * total, (unheard, total)


def _replayed(path, hub_settings):
    """``replay`` of ``path`` at full speed to a listener on the hub: its result and the raw
    samples the listener heard."""
    from armfusion.fusion.service.zenoh_config import open_session

    listener, _ = hub_settings
    heard = []
    with open_session(listener) as s:
        s.declare_subscriber("armfusion/chair1/raw/*", heard.append)
        r = CliRunner().invoke(app, ["replay", str(path), "--speed", "max", "--wait", "5",
                                     "--connect", listener.listen[0]])
    return r, heard


def test_replay_of_a_cut_mcap_replays_what_it_can_read_and_exits_1(startup_recording, hub_settings, tmp_path):
    # before: exit 0, the lost chunk said in a warning only
    data = startup_recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    r, heard = _replayed(cut, hub_settings)
    assert r.exit_code == 1, r.output
    assert f"replayed only what could be read: {cut}: file ends early at byte" in " ".join(r.stderr.split())
    assert heard  # what could be read went out


def test_replay_of_an_mcap_with_a_topic_it_cannot_take_says_so_and_exits_1(startup_recording, hub_settings,
                                                                          tmp_path):
    # before: exit 0, the topic of an unknown kind left out with a warning only
    import json as _json

    from armfusion.sensors.mcap_format import schema_for_kind, topic_for
    from mcap.writer import Writer

    rec = read_recording(startup_recording)
    odd = tmp_path / "odd.mcap"
    with open(odd, "wb") as fh:
        w = Writer(fh)
        w.start()
        w.add_metadata("armfusion", {"format_version": "2", "armfusion_version": "x", "arm_config": "",
                                     "t_offset_ns": "0"})
        for k, s in enumerate(s for s in rec.streams.values() if s.name in ("acc1", "acc2")):
            schema = _json.dumps(schema_for_kind(s.kind)).encode()
            sid = w.register_schema(f"armfusion.{s.kind}", "jsonschema", schema)
            kind = "bogus" if k == 0 else s.kind
            meta = {"stream": s.name, "kind": kind, "channels": _json.dumps(list(s.channels))}
            cid = w.register_channel(topic_for(s.name, s.kind), "json", sid, meta)
            for i in range(len(s)):
                ns = int(s.t_s[i] * 1e9)
                body = _json.dumps({"t_s": float(s.t_s[i]), "values": s.values[i].tolist()}).encode()
                w.add_message(cid, ns, body, ns, i)
        w.finish()
    r, heard = _replayed(odd, hub_settings)
    assert r.exit_code == 1, r.output
    said = " ".join(r.stderr.split())
    n = len(rec.get("acc1"))
    assert (f"replayed only what could be read: {odd}: left out raw/acc1 ({n} messages): unknown stream "
            "kind 'bogus'") in said
    assert heard  # acc2 went out


def test_a_record_under_an_existing_name_keeps_the_recording_there(tmp_path, loopback_port):
    """A service restarted with the same `record chair1.mcap` (as the deployment runs it)
    writes beside the earlier recording, which stays byte for byte, and says where."""
    earlier = tmp_path / "chair1.mcap"
    earlier.write_bytes(b"an earlier session's recording")
    (tmp_path / "chair1-1.mcap").write_bytes(b"and the one after it")
    r = CliRunner().invoke(app, ["record", str(earlier), "--listen", f"tcp/127.0.0.1:{loopback_port}",
                                 "--duration", "0.5", "--json"])
    assert r.exit_code == 0, r.output
    assert earlier.read_bytes() == b"an earlier session's recording"
    assert (tmp_path / "chair1-1.mcap").read_bytes() == b"and the one after it"
    assert json.loads(r.stdout)["path"] == str(tmp_path / "chair1-2.mcap")
    assert read_recording(tmp_path / "chair1-2.mcap").meta["read_report"].complete
    said = r.stderr.replace("\n", "")  # the console wraps long paths
    assert f"OUT {earlier} exists and is kept: recording to {tmp_path / 'chair1-2.mcap'}" in said
