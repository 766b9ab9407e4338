"""`armfusion calibrate joints` from the command line: with no saved pose
the data alone choose (the seed-11 still poses: j3 and j4 ambiguous in two windows, solved
alone); `--segments` carries each window's answer to the next through the encoder counts,
so no window is then wrong or ambiguous; a stale `--prior` is ignored with a note;
`--assume-parked` says the answer rests on that assumption."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import resolve_config_path
from armfusion.fusion.startup.pose_store import save_pose
from armfusion.models.simulator import angle_truth
from armfusion.sensors.recording import read_recording
from typer.testing import CliRunner

runner = CliRunner()


@pytest.fixture(scope="module")
def seed11(tmp_path_factory):
    d = tmp_path_factory.mktemp("seed11")
    rec = d / "s.csv"
    r = runner.invoke(app, ["simulate", "--config", "wmra", "--scenario", "static-poses", "--seed", "11",
                            "--out", str(rec)])
    assert r.exit_code == 0, r.output
    cfg = yaml.safe_load(resolve_config_path("wmra").read_text())
    cfg["calibration"]["accel_unmodelled_g"] = 0.0
    ideal = d / "ideal.yaml"
    ideal.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return rec, ideal


def _solve(rec, cfg, *extra):
    r = runner.invoke(app, ["calibrate", "joints", "--config", str(cfg), str(rec), "--segments", "--json",
                            *extra])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)["segments"]


def _truth(rec_path, names):
    rec = read_recording(rec_path)
    truth = json.loads(rec_path.with_suffix(".truth.json").read_text())
    return angle_truth(rec.get("true_q"), truth, names)


def test_segments_alone_are_ambiguous_where_the_data_cannot_tell_and_carried_they_are_right(seed11):
    rec, ideal = seed11
    alone = _solve(rec, ideal, "--independent")
    names = [j["name"] for j in alone[0]["joints"]]
    tq = _truth(rec, names)
    by_start = {round(s["t_start"], 1): s for s in alone}
    for t0 in (45.4, 77.3):
        seg = by_start[t0]
        flags = {j["name"]: j["flag"] for j in seg["joints"]}
        assert flags["j3"] == "ambiguous" and flags["j4"] == "ambiguous"
        assert seg["prior"] == "none" and seg["disambiguating_move"] is not None
    carried = _solve(rec, ideal)
    for seg in carried:
        q = tq.values[int(np.searchsorted(tq.t_s, seg["t_end"])) - 1]
        for j, je in enumerate(seg["joints"]):
            assert je["flag"] != "ambiguous", (seg["t_start"], je)
            if je["flag"] == "ok":
                err = abs((je["angle_rad"] - q[j] + np.pi) % (2 * np.pi) - np.pi)
                assert err < 4 * je["sigma_rad"], (seg["t_start"], je["name"], np.degrees(err))
    assert any("carried through the encoder counts fits" in n for n in carried[4]["notes"])


def test_a_stale_saved_pose_is_ignored_and_assume_parked_is_said(seed11, tmp_path, wmra):
    rec, ideal = seed11
    names = list(wmra.joint_names)
    tq = _truth(rec, names)
    saved = tmp_path / "pose.json"
    save_pose(saved, wmra, tq.values[-1])  # where the arm stood at the end, not at the start
    first = _solve(rec, ideal, "--prior", str(saved), "--independent")[0]
    assert first["prior"] == "none"
    assert any(f"the pose saved in {saved} does not fit the still data" in n for n in first["notes"])
    parked = _solve(rec, ideal, "--assume-parked", "--independent")[0]
    assert parked["prior"].startswith("the arm assumed parked")
    assert any("rests on an assumption" in n for n in parked["notes"])
