"""The planned calibration maneuver served by the fusion node (``serve --maneuver``): the plan
on ``armfusion/<robot>/maneuver`` for the arm's controller, the samples kept between its
``start`` and ``done`` requests, the sensor fit run on them in a child process, and what is
refused (a request out of turn, a run that is not the plan, a run that never ends)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.planner import load_maneuver
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.maneuver import ManeuverSettings, ServedManeuver, poses_reached, still_poses_rad
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.fusion.service.requests import request_maneuver
from armfusion.fusion.service.zenoh_config import open_session
from armfusion.fusion.shipped import shipped_config
from armfusion.models.simulator import simulate
from armfusion.models.trajectories.planned import played_scenario
from service_helpers import cut, wait_for

HIDDEN_BIAS_G = (0.0, 0.03, -0.02)
"""acc2's zero-g offset in the simulated arm (30 and 20 mg: several times a fit's σ)."""


@pytest.fixture(scope="module")
def short_plan():
    """The shipped plan's poses within its first 20 s (a still start, then a few poses)."""
    return load_maneuver(shipped_config("maneuvers/wmra-60s.yaml")).until(20.0)


@pytest.fixture(scope="module")
def played(short_plan):
    """The short plan played by the simulated WMRA whose acc2 has :data:`HIDDEN_BIAS_G`."""
    arm = load_arm("wmra")
    effects = [{"effect": "accel_bias", "target": "acc2", "value": list(HIDDEN_BIAS_G)}]
    rec, _ = simulate(arm, played_scenario(arm, short_plan, 4), seed=4, effects=effects)
    return rec


def _settings(tmp_path, **kw) -> ManeuverSettings:
    return ManeuverSettings(tmp_path / "runs", effects="accel_bias", **kw)


def test_the_controller_gets_the_plan_and_the_node_fits_the_sensors_on_what_it_played(
        hub_settings, fusion_node, short_plan, played, tmp_path):
    arm = load_arm("wmra")
    listener, connector = hub_settings
    port = listener.listen[0].rsplit(":", 1)[1]
    served = ServedManeuver(arm, "chair1", short_plan, shipped_config("wmra.yaml"), _settings(tmp_path))
    with fusion_node(listener, arm, maneuver=served) as (node, result), open_session(connector) as s:
        published: list = []
        sub = s.declare_subscriber(pl.maneuver_key("chair1"), lambda sample: published.append(
            pl.decode(str(sample.key_expr), sample.payload.to_bytes())))
        # the controller asks for the plan: the poses it must play, in degrees
        shown = request_maneuver(s, "chair1")
        assert shown.state == "ready" and shown.accepted
        assert np.allclose(shown.plan.poses_rad, short_plan.poses_rad, atol=1e-5)
        assert shown.plan.dwell_s.tolist() == pytest.approx(short_plan.dwell_s.tolist())
        # out of turn: refused, saying why, and nothing changes
        early = request_maneuver(s, "chair1", "done")
        assert not early.accepted and "nothing is being recorded" in early.message
        nothing = request_maneuver(s, "chair1", "apply")
        assert not nothing.accepted and "no calibration to apply" in nothing.message
        started = request_maneuver(s, "chair1", "start")
        assert started.accepted and started.state == "recording", started.message
        assert "the node has no joint estimate yet" in started.message
        again = request_maneuver(s, "chair1", "start")
        assert not again.accepted and "recording already" in again.message

        # the controller plays it (here: the simulated arm's samples, replayed)
        report = replay(s, played, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
        assert wait_for(lambda: node.report_samples() >= sum(report.samples.values()), 30.0)
        assert wait_for(lambda: node.tracker is not None, 10.0)
        done = request_maneuver(s, "chair1", "done")
        assert done.accepted and done.state == "fitting", done.message
        assert done.poses_reached == len(short_plan.poses_rad)
        assert done.t_end_s - done.t_start_s == pytest.approx(played.duration_s, abs=0.05)
        assert wait_for(lambda: published and published[-1].state in ("calibrated", "failed"), 240.0)
        final = published[-1]
        assert final.state == "calibrated", final.message
        # the command line shows the same, and exits 0
        out = subprocess.run([sys.executable, "-m", "armfusion.fusion.cli", "maneuver", "show", "--json",
                              "--connect", f"tcp/127.0.0.1:{port}"], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout)["config"] == final.config
        # reviewed, the calibration is applied: the node tracks with it from the still arm
        assert not node.arm.effects
        tracker_before = node.tracker
        applied = request_maneuver(s, "chair1", "apply")
        assert applied.accepted and applied.state == "applied", applied.message
        assert "the calibration of calibrated-chair1-" in applied.message
        assert node.arm.source == final.config and node.arm.effects
        assert node.tracker is not tracker_before and node.tracker.arm is node.arm
        sub.undeclare()
    assert result["report"].errors == 0 and result["report"].estimates > 0  # it tracked throughout

    # the written config holds acc2's offset, found from the plan's poses alone
    cfg = yaml.safe_load(open(final.config, encoding="utf-8"))
    entry = next(e for e in cfg["effects"] if e["effect"] == "accel_bias" and e["target"] == "acc2")
    err = np.asarray(entry["params"]["bias_g"]) - HIDDEN_BIAS_G
    assert np.all(np.abs(err) <= 4 * np.asarray(entry["sigma"]["bias_g"]) + 1e-4), (entry, err)
    assert np.max(np.abs(err)) < 0.005  # under 5 mg of 30


def test_a_run_that_is_not_the_plan_or_never_ends_or_cannot_be_written_is_not_fitted(
        short_plan, played, tmp_path):
    arm = load_arm("wmra")
    # another plan (pose k's j2 turned 10k°: the encoders count relative angles, so a turn of
    # every pose alike would be the same plan) against the samples of the short one
    k = np.arange(len(short_plan.poses_rad))[:, None]
    other = type(short_plan)(short_plan.joint_names,
                             short_plan.poses_rad + np.radians(10.0) * k * np.eye(7)[1], short_plan.dwell_s,
                             short_plan.move_s)
    m = ServedManeuver(arm, "chair1", other, shipped_config("wmra.yaml"), _settings(tmp_path))
    assert m.request("start").accepted
    for s in played.raw().values():
        m.keep(s)
    reply = m.request("done")
    assert m.state == "failed" and reply.poses_reached <= 1
    assert "not this plan played; nothing fitted" in reply.message
    assert not (tmp_path / "runs").exists()  # nothing written, no fit started

    # bounded: samples beyond a plan and a half plus the overrun are not kept
    m = ServedManeuver(arm, "chair1", short_plan, shipped_config("wmra.yaml"),
                       _settings(tmp_path, overrun_s=1.0))
    m.request("start")
    enc = played.raw()["enc"]
    for k in range(0, len(enc), 100):
        m.keep(enc.between(enc.t_s[k] - 1e-9, enc.t_s[min(k + 99, len(enc) - 1)] + 1e-9))
    assert m.state == "recording"  # 20 s of a 20 s plan: within bounds
    late = type(enc)(enc.name, enc.kind, enc.t_s + 1.5 * short_plan.duration_s, enc.values, enc.channels)
    m.keep(late)
    assert m.state == "failed" and "nothing kept" in m.message
    assert not m.request("done").accepted

    # where the run cannot be written (a file where its folder should be): said, nothing started
    (tmp_path / "blocked").write_text("a file")
    m = ServedManeuver(arm, "chair1", short_plan, shipped_config("wmra.yaml"),
                       ManeuverSettings(tmp_path / "blocked" / "runs", effects="accel_bias"))
    m.request("start")
    for s in played.raw().values():
        m.keep(s)
    reply = m.request("done")
    assert m.state == "failed" and "cannot write the run or start its fit" in reply.message


def test_the_poses_held_are_counted_from_relative_encoder_angles(short_plan, played):
    arm = load_arm("wmra")
    enc = played.raw()["enc"]
    # the encoders count from wherever they started: shifted by whole counts, the same poses
    shifted = cut(played, 0.0, played.t_end_s + 1.0, enc=lambda s: type(s)(
        s.name, s.kind, s.t_s, s.values + np.array([5000, -300, 12, 0, 7, -9, 40]), s.channels))
    assert not np.array_equal(shifted.get("enc").values, enc.values)
    held = still_poses_rad(arm, shifted, 0.5)
    assert len(held) == len(short_plan.poses_rad)
    assert poses_reached(short_plan, held, np.radians(1.0)) == len(short_plan.poses_rad)
    # the last pose not reached (the run cut in its move): one fewer
    part = cut(shifted, 0.0, short_plan.schedule()[-1][0] + 0.2)
    assert poses_reached(short_plan, still_poses_rad(arm, part, 0.5), np.radians(1.0)) == \
        len(short_plan.poses_rad) - 1


def test_serve_refuses_a_maneuver_that_is_not_safe_to_play(tmp_path):
    from armfusion.fusion.cli.main import app
    from typer.testing import CliRunner

    doc = yaml.safe_load(shipped_config("maneuvers/wmra-60s.yaml").read_text(encoding="utf-8"))
    doc["poses"][2]["pose_deg"][1] = 150.0  # j2 beyond its limit
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc), encoding="utf-8")
    r = CliRunner().invoke(app, ["serve", "--maneuver", str(bad), "--duration", "1"])
    assert r.exit_code == 2
    assert "--maneuver: bad.yaml: not safe to play on WMRA-II: pose 2: j2 at 150.0°" in r.output, r.output


def test_a_maneuver_payload_reads_back_and_a_malformed_one_is_refused_by_field(short_plan):
    m = pl.Maneuver("chair1", "fitting", True, "4 of 4 poses held", short_plan, 0.0, 20.0, 4, "r.mcap", "")
    data = pl.encode(m)
    back = pl.decode(pl.maneuver_key("chair1", "done"), data)
    assert back.state == "fitting" and back.poses_reached == 4 and back.t_end_s == 20.0
    assert np.allclose(back.plan.poses_rad, short_plan.poses_rad, atol=1e-5)
    doc = json.loads(data)
    doc["plan"]["poses"][1]["pose_deg"] = [0.0, 1.0]
    with pytest.raises(pl.PayloadError, match=r"poses\[1\].pose_deg: expected 7 angles"):
        pl.decode(pl.maneuver_key("chair1"), json.dumps(doc).encode())
    doc = json.loads(data)
    doc["poses_reached"] = 99
    with pytest.raises(pl.PayloadError, match="poses_reached"):
        pl.decode(pl.maneuver_key("chair1"), json.dumps(doc).encode())
    with pytest.raises(pl.PayloadError, match="not an armfusion key"):
        pl.decode("armfusion/chair1/maneuver/go", data)
