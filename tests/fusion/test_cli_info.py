"""`armfusion info` and `--help`: what a person reads about the arm."""

from __future__ import annotations

import json

import pytest
from armfusion.fusion.cli.main import app
from typer.testing import CliRunner

runner = CliRunner()


def test_info_json_lists_joints_sensors_and_what_each_sensor_sees():
    r = runner.invoke(app, ["info", "--config", "wmra", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["name"] == "WMRA-II" and d["dh_convention"] == "modified"
    assert [j["name"] for j in d["joints"]] == [f"j{i}" for i in range(1, 8)]
    sees = {s["name"]: s["sees_joints"] for s in d["sensors"]}
    assert sees["acc1"] == ["j1", "j2"]
    assert sees["acc2"] == ["j1", "j2", "j3", "j4"]
    assert sees["acc4"] == [f"j{i}" for i in range(1, 8)]
    assert sees["imu"] == []
    # the park pose is gravity-blind in joints 3 and 6, and info says so
    assert [j["name"] for j in d["joints"] if j["vertical_at_ready"]] == ["j3", "j6"]


def test_info_table_and_plot(tmp_path):
    png = tmp_path / "arm.png"
    r = runner.invoke(app, ["info", "--config", "crs_a465", "--plot", str(png)])
    assert r.exit_code == 0, r.output
    assert "CRS-A465" in r.stdout and "triax" in r.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_bad_config_is_one_clear_error(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("arm: {name: x}\nsensors: []\n")
    r = runner.invoke(app, ["info", "--config", str(p)])
    assert r.exit_code == 2
    assert "bad.yaml: arm.joints: required key is missing" in r.stderr
    assert "Traceback" not in r.output


@pytest.mark.parametrize("cmd", [[], ["info"], ["inspect"], ["simulate"], ["drivers"], ["track"],
                                 ["diagnose"], ["serve"], ["replay"], ["record"], ["calibrate", "joints"],
                                 ["calibrate", "sensors"]])
def test_help_everywhere(cmd):
    r = runner.invoke(app, [*cmd, "--help"])
    assert r.exit_code == 0
    assert "Usage" in r.stdout
