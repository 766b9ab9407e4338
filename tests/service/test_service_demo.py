"""`armfusion demo`, CI-sized, end to end: a short sensor calibration on the shipped planned
maneuver's first poses with the simulated installer's references, then fake drivers ->
serve -> record as processes over Zenoh on 127.0.0.1; the summary holds real figures
against the truth, every sample published reaches the fusion node and the recorder, the
report and the recording are written, and no node is left running. The shipped maneuver
is still safe to play; a maneuver that is not, or too short, is refused before any work."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.demo import MANEUVER, REFERENCE_JOINTS
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.planner import load_maneuver, maneuver_problems
from armfusion.fusion.shipped import shipped_config
from typer.testing import CliRunner


def _processes_mentioning(text: str) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            if text in cmd:
                out.append(int(d.name))
    return out


def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    run = subprocess.run([sys.executable, "-m", "armfusion.fusion.cli", "demo", "--duration", "8",
                          "--calibration-duration", "20", "--no-workbench", "--seed", "2",
                          "--out", str(out), "--json"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    doc = json.loads(run.stdout)
    # the calibrated config served, after the identification on the calibration maneuver
    assert doc["config"] == str(out / "calibrated.yaml") and Path(doc["config"]).exists()
    assert doc["calibration"]["chi2_red"] < 3.0
    # on the shipped planned maneuver's poses within its first 20 s, with the installer's
    # one-time references of j1 and j7, which the calibrated config records with the fit's check
    cal = doc["calibration"]
    assert Path(cal["maneuver"]) == shipped_config(MANEUVER)
    played = load_maneuver(cal["played"])
    assert 15.0 <= played.duration_s <= 20.0 and cal["poses"] == len(played.poses_rad) >= 3
    assert np.array_equal(played.poses_rad, load_maneuver(shipped_config(MANEUVER)).poses_rad[:cal["poses"]])
    assert [r["joint"] for r in cal["references"]] == ["j1", "j7"]
    written = yaml.safe_load(Path(doc["config"]).read_text())["calibration"]["identified"]["references"]
    assert [(r["joint"], r["sigma_deg"], r["where"]) for r in written] == [
        ("j1", 0.05, "the first still segment"), ("j7", 0.05, "the first still segment")]
    for given, kept in zip(cal["references"], written, strict=True):
        assert kept["angle_deg"] == pytest.approx(given["angle_deg"], abs=1e-6)
        # the fit agrees with the installer (a contradiction would have written nothing)
        assert abs(kept["fitted_deg"] - kept["angle_deg"]) < 0.5
    assert "startup calibration on the still stretch" in doc["startup"]["message"]
    rms = doc["tracking"]["rms_error_deg"]
    assert set(rms) == {f"j{k}" for k in range(1, 8)}
    # calibrated sensors, even from 20 s of the maneuver: no joint on a wrong branch
    # (uncalibrated, j3 ends ~100 deg off in a seed-0 run), and the sigmas say how far a 20 s
    # calibration reaches (j3 and j6 wait at gimbal lock, held at their prior with a sigma
    # that says so, until the arm reaches): every joint within 3 sigma of the truth (the
    # angle with its true zero offset)
    assert all(math.isfinite(v) and v < 10.0 for v in rms.values()), rms
    within = doc["tracking"]["within_3_sigma"]
    assert min(within.values()) >= 0.95, within
    # from each joint's first ok estimate on: j2, ok at the startup, from the first estimate;
    # a joint first ok later is scored on fewer estimates, never before the tracking starts
    first_ok = doc["tracking"]["from_first_ok"]
    assert set(first_ok) == set(rms)
    if doc["startup"]["joints"]["j2"]["flag"] == "ok":
        assert first_ok["j2"]["t_s"] == doc["tracking"]["t_start_s"]
        assert first_ok["j2"]["rms_error_deg"] == pytest.approx(rms["j2"])
    for n, f in first_ok.items():
        assert f is None or (f["t_s"] >= doc["tracking"]["t_start_s"] and 0 <= f["within_3_sigma"] <= 1
                             and math.isfinite(f["rms_error_deg"])), (n, f)
    assert doc["tracking"]["heading_rms_deg"] is not None
    # the compass's iron learnt from the chair's one turn on the spot, written into the config
    assert cal["compass"].startswith("compass from the turns in compass-turn.mcap"), cal["compass"]
    assert "# compass from the turns in compass-turn.mcap" in Path(doc["config"]).read_text()
    # the heading's statuses, as the feed published them, share the run between them
    statuses = doc["tracking"]["heading_status"]
    assert set(statuses) <= {"compass_fused", "gyro_only", "disturbed", "calibrating"}
    assert abs(sum(statuses.values()) - 1.0) < 1e-9
    assert 0.0 <= doc["tracking"]["heading_within_3_sigma"] <= 1.0
    s = doc["samples"]
    assert s["published"] > 5000
    # every sample published reaches the node and the recorder, or the node says why it
    # refused it: on a quiet machine none is refused; on a loaded one the drivers fall
    # behind and read bursts, which the node refuses as denser than any sensor (counted),
    # and a node behind sheds what waited too long in its channel (counted)
    refused = s["refused_by_serve"]
    assert s["published"] == s["received_by_serve"] + sum(refused.values()) + s["shed_by_serve"] \
        == s["recorded"], s
    assert set(refused) <= {"too_dense"} and sum(refused.values()) <= 0.05 * s["published"], s
    assert s["estimates_received"] == s["estimates_published"] > 100
    assert s["serve_errors"] == 0  # (the compass read at instants of its own once raised on each)
    assert doc["latency"]["p50_ms"] > 0 and doc["latency"]["count"] == s["estimates_received"]
    report = Path(doc["report"]).read_text(encoding="utf-8")
    assert report.count("<img") >= 2 and "Accuracy against the simulator" in report
    assert (out / "demo.mcap").stat().st_size > 100_000
    assert json.loads((out / "summary.json").read_text())["samples"] == s
    assert _processes_mentioning(str(out)) == []


def test_the_shipped_maneuver_is_still_safe_to_play_and_starts_still_at_the_ready_pose():
    """The demo's calibration maneuver, planned once and shipped: inside the WMRA's limits, its
    moves within the unlock move's checks, its joint rates and tool speed those for a person
    beside the arm (``maneuver_problems``), 60 s; its first pose is the ready pose held 5 s,
    the still start where the installer's references stand; cut to 20 s, still safe."""
    arm = load_arm("wmra")
    plan = load_maneuver(shipped_config(MANEUVER))
    assert plan.joint_names == tuple(arm.joint_names)
    assert plan.duration_s == pytest.approx(60.0, abs=0.01)
    assert maneuver_problems(arm, plan) == []
    assert np.allclose(plan.poses_rad[0], arm.ready_pose_rad) and plan.dwell_s[0] >= 5.0
    assert set(REFERENCE_JOINTS) <= set(arm.joint_names)
    short = plan.until(20.0)
    assert short.duration_s <= 20.0 and len(short.poses_rad) >= 3 and maneuver_problems(arm, short) == []
    assert plan.until(1.0).duration_s == pytest.approx(plan.dwell_s[0])  # at least the still start


def test_a_maneuver_the_demo_cannot_play_is_refused_before_any_work(tmp_path):
    plan = yaml.safe_load(shipped_config(MANEUVER).read_text())
    r = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "a"), "--calibration-duration", "90"])
    assert r.exit_code == 2
    assert "--calibration-duration 90: the maneuver wmra-60s.yaml lasts 60 s" in " ".join(r.output.split())
    plan["poses"][2]["pose_deg"][1] = 400.0  # j2 far outside its limits
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(plan))
    r = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "b"), "--maneuver", str(bad)])
    assert r.exit_code == 2
    said = " ".join(r.output.split())
    assert "the calibration maneuver bad.yaml: not safe to play on WMRA-II: pose 2: j2" in said, said
    assert not (tmp_path / "b" / "calibration.mcap").exists()
