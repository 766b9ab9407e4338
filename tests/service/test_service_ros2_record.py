"""The live service's estimates into ROS 2: ``armfusion record OUT.mcap --ros2-out
EST.ros2.mcap`` writes, when it stops, the same bag ``track --out EST.ros2.mcap`` writes for
the same estimates; a record that is not one is refused by topic and index."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from armfusion.fusion.cli.track import write_estimates
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.ros2.from_records import RecordsError, run_from_records, write_ros2_from_records
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.tracking.estimate import HEADING_STATUS
from armfusion.fusion.tracking.settings import JOINT_FLAGS, SENSOR_STATUS
from armfusion.fusion.tracking.tracker import StartOptions, start_from_recording
from armfusion.models.simulator import simulate
from mcap.reader import make_reader

ROOT = Path(__file__).resolve().parents[2]


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as f:
        return [(c.topic, m.log_time, bytes(m.data)) for _s, c, m in make_reader(f).iter_messages()]


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A simulated WMRA turning on the spot (its heading's status changes), tracked."""
    arm = load_arm("wmra")
    rec, _ = simulate(arm, "compass-turn", seed=2)
    tr, _ = start_from_recording(arm, rec, options=StartOptions(propose_unlock=False))
    return arm, tr.run(rec), tmp_path_factory.mktemp("ros2rec")


def test_recorded_records_become_the_same_bag_as_the_tracked_run(tracked) -> None:
    """Through armfusion's own records (JSON, as the recorder writes them) and back, every
    ROS 2 message is byte for byte the one written from the run itself."""
    arm, run, d = tracked
    write_estimates(run, d / "direct.ros2.mcap", arm.source)
    write_estimates(run, d / "est.mcap", arm.source)  # the records a recorder writes
    back, left_out, counts = write_ros2_from_records(d / "est.mcap", d / "via.ros2.mcap",
                                                     Path(arm.source).stem)
    assert back.steps == run.steps and left_out == 0
    assert back.joint_names == tuple(run.joint_names) and back.sensor_names == tuple(run.sensor_names)
    np.testing.assert_array_equal(back.flags, run.flags)
    np.testing.assert_array_equal(back.heading_status, run.heading_status)
    direct, via = _messages(d / "direct.ros2.mcap"), _messages(d / "via.ros2.mcap")
    assert len(via) == len(direct) == sum(counts.values())
    assert via == direct


def test_a_record_that_is_not_one_is_refused_by_topic_and_index(tracked) -> None:
    arm, run, _ = tracked
    heading = {"t_s": 1.0, "roll_rad": 0.0, "pitch_rad": 0.0, "heading_rad": 0.0, "roll_sigma_rad": 0.1,
               "pitch_sigma_rad": 0.1, "heading_sigma_rad": 0.1, "gyro_bias_rad_s": [0.0, 0.0, 0.0],
               "magnetic_disturbance": False, "magnetic_recovery": False, "heading_status": "gyro_only"}
    joints = {"t_s": 1.0, "joint_names": ["j1"], "q_rad": [0.1], "sigma_rad": [0.01], "flags": ["ok"],
              "sensors": {"acc1": "ok"}}
    assert run_from_records([joints], [heading])[0].steps == 1
    with pytest.raises(RecordsError,
                       match=r"estimates/heading message 1: heading_status 'lost' is not one of"):
        run_from_records([joints], [heading, {**heading, "t_s": 2.0, "heading_status": "lost"}])
    with pytest.raises(RecordsError, match=r"estimates/joints message 0: flag 'fine' is not one of"):
        run_from_records([{**joints, "flags": ["fine"]}], [heading])
    with pytest.raises(RecordsError, match=r"estimates/heading message 0: not a heading record \(KeyError"):
        run_from_records([joints], [{k: v for k, v in heading.items() if k != "roll_rad"}])
    # a heading whose joints record never came is left out and counted, not invented
    lone, left_out = run_from_records([joints], [heading, {**heading, "t_s": 2.0}])
    assert (lone.steps, left_out) == (1, 1)


def test_the_record_command_writes_a_ros2_bag_of_the_estimates_it_heard(tracked, tmp_path,
                                                                         loopback_port) -> None:
    """``record --ros2-out`` as a process on loopback: a node's joint states and headings
    published over Zenoh come out, when the recorder stops, as the same ROS 2 messages a
    tracked run's bag holds for them."""
    from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session

    arm, run, _ = tracked
    n = 60
    out, bag = tmp_path / "live.mcap", tmp_path / "live.ros2.mcap"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    recorder = subprocess.Popen([sys.executable, "-m", "armfusion.fusion.cli", "record", str(out), "--ros2-out",
                                 str(bag), "--config", "wmra", "--listen", f"tcp/127.0.0.1:{loopback_port}",
                                 "--json"],
                                cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "recording armfusion/chair1/raw/*" in recorder.stderr.readline()
        settings = ZenohSettings(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{loopback_port}"])
        with open_session(settings) as s:
            pj = s.declare_publisher(pl.joints_key("chair1"))
            ph = s.declare_publisher(pl.heading_key("chair1"))
            time.sleep(1.0)  # the link to the recorder up
            for i in range(n):
                t = float(run.t_s[i])
                r, p, h = (float(v) for v in run.rpy_rad[i])
                sr, sp, sh = (float(v) for v in run.rpy_sigma_rad[i])
                pj.put(pl.encode(pl.JointState(
                    "chair1", t, tuple(run.joint_names), tuple(map(float, run.q_rad[i])),
                    tuple(map(float, run.sigma_rad[i])), tuple(JOINT_FLAGS[f] for f in run.flags[i]),
                    tuple((nm, SENSOR_STATUS[c]) for nm, c in zip(run.sensor_names, run.sensor_status[i],
                                                                  strict=True)))))
                ph.put(pl.encode(pl.Heading(
                    "chair1", t, h, sh, r, sr, p, sp, tuple(map(float, run.gyro_bias_rad_s[i])),
                    bool(run.magnetic[i] & 1), bool(run.magnetic[i] & 2),
                    HEADING_STATUS[run.heading_status[i]], bool(run.true_north))))
            time.sleep(1.0)
    finally:
        recorder.send_signal(signal.SIGTERM)
        rout, rerr = recorder.communicate(timeout=60)
    assert recorder.returncode == 0, rerr
    report = json.loads(rout)
    assert report["ros2"]["instants"] == n and report["ros2"]["left_out"] == 0
    with open(bag, "rb") as f:
        assert make_reader(f).get_header().profile == "ros2"
    got = [m for m in _messages(bag) if m[0] == "/armfusion/joint_states"]
    assert len(got) == n
    # the same messages a tracked run's bag holds for those instants
    direct = tmp_path / "direct.ros2.mcap"
    write_estimates(run, direct, "wmra")
    want = [m for m in _messages(direct) if m[0] == "/armfusion/joint_states"][:n]
    assert got == want


def test_the_record_command_refuses_a_ros2_name_it_would_not_write(tmp_path) -> None:
    from armfusion.fusion.cli.main import app
    from typer.testing import CliRunner

    r = CliRunner().invoke(app, ["record", str(tmp_path / "a.mcap"), "--ros2-out", str(tmp_path / "b.mcap")])
    assert r.exit_code == 2 and "a ROS 2 bag's name ends in .ros2.mcap" in r.output
