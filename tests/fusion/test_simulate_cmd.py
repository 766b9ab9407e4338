"""`armfusion simulate`: files written, truth replayed, errors a person can act on."""

from __future__ import annotations

import json

import numpy as np
import pytest
import typer
from armfusion.fusion.cli.simulate import (
    SimulationOptions,
    load_effect_entries,
    register,
    simulate,
    truth_path,
)
from armfusion.models.arm_config import ConfigError
from armfusion.sensors.recording import read_recording
from typer.testing import CliRunner


@pytest.fixture(scope="module")
def app():
    a = typer.Typer()

    @a.callback()
    def main() -> None:
        """test app"""

    register(a)
    return a


def test_writes_the_recording_and_its_truth_file(tmp_path):
    out = tmp_path / "rec.csv"
    s = simulate("wmra", "daily-use", out, SimulationOptions(duration_s=15, seed=3, realistic=True,
                                                             effects=("mount_rotation:acc3=0.01,0.02,0",)))
    assert truth_path(out) == tmp_path / "rec.truth.json" and truth_path(out).exists()
    rec = read_recording(out)
    assert set(rec.streams) >= {"acc1", "acc4", "imu_acc", "imu_gyro", "imu_mag", "imu_temp", "enc",
                                "true_q", "true_base"}
    assert len(rec.streams["acc1"]) == 1500 == s["streams"]["acc1"]
    truth = json.loads(truth_path(out).read_text())
    mr = [e for e in truth["effects"] if e["effect"] == "mount_rotation" and e["target"] == "acc3"]
    assert mr[0]["params"]["rotvec_rad"] == [0.01, 0.02, 0.0]  # the option overrides the draw
    assert len(truth["effects"]) == len(s["effects"]) > 60


def test_effects_file_replays_the_same_arm_in_another_scenario(tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.mcap"
    simulate("wmra", "static-poses", a, SimulationOptions(duration_s=10, seed=8, realistic=True))
    simulate("wmra", "startup", b, SimulationOptions(duration_s=3, seed=1, effects_file=truth_path(a)))
    ta, tb = (json.loads(truth_path(p).read_text()) for p in (a, b))
    assert ta["effects"] == tb["effects"]
    assert read_recording(b).streams["acc2"].values.shape == (300, 3)
    # an arm config's effects list works as well
    cfg = tmp_path / "arm_effects.yaml"
    cfg.write_text("effects:\n  - {effect: gyro_bias, params: {bias_rad_s: [0.1, 0, 0]}}\n")
    assert load_effect_entries(cfg)[0]["effect"] == "gyro_bias"


def test_the_command_line(app, tmp_path):
    runner = CliRunner()
    out = tmp_path / "r.csv"
    r = runner.invoke(app, ["simulate", "--config", "wmra", "--scenario", "startup", "--out", str(out),
                            "--duration", "2", "--rate", "50", "--seed", "4", "--no-noise", "--json",
                            "--effect", "accel_bias:acc1=0.1,0,0"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert d["streams"]["acc1"] == 100 and d["effects"] == ["acc1.accel_bias"] and d["noise"] is False
    rec = read_recording(out)
    v = rec.streams["acc1"].values
    assert np.all(v == v[0])  # no noise: a still arm gives constant counts
    r = runner.invoke(app, ["simulate", "--scenario", "startup", "--out", str(out), "--duration", "1"])
    assert r.exit_code == 0 and "Wrote" in r.output


def test_errors_name_the_option_and_the_fix(app, tmp_path):
    runner = CliRunner()
    r = runner.invoke(app, ["simulate", "--scenario", "startup", "--out", str(tmp_path / "r.csv"),
                            "--effect", "acel_bias:acc1=0.1,0,0", "--effect", "accel_bias:acc1=0.1"])
    assert r.exit_code == 2
    assert "--effect[0].effect: unknown effect 'acel_bias'" in r.output
    assert "did you mean 'accel_bias'" in r.output
    assert "--effect[1].params.bias_g: expected 3 values (x, y, z) in g, got 1" in r.output
    r = runner.invoke(app, ["simulate", "--scenario", "lunch", "--out", str(tmp_path / "r.csv")])
    assert r.exit_code == 2 and "unknown scenario 'lunch'; known: startup" in r.output
    r = runner.invoke(app, ["simulate", "--scenario", "startup", "--out", str(tmp_path / "r.txt")])
    assert r.exit_code == 2 and "must end in .csv or .mcap" in r.output
    r = runner.invoke(app, ["simulate", "--config", "nonexistent_arm.yaml", "--scenario", "startup",
                            "--out", str(tmp_path / "r.csv")])
    assert r.exit_code == 2 and "no arm config 'nonexistent_arm.yaml'" in r.output
    bad = tmp_path / "bad.truth.json"
    bad.write_text('{"effects": [{"effect": "gyro_bias", "params": {"bias_rad_s": [1, 2]}}]}')
    with pytest.raises(ConfigError, match=r"bad.truth.json: effects\[0\].params.bias_rad_s: expected 3"):
        simulate("wmra", "startup", tmp_path / "x.csv", SimulationOptions(effects_file=bad))
