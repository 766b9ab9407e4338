"""Where a recording meets a config: a recording that does not fit the arm is
refused by every command with one line, and `inspect` says when samples are missing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from armfusion.fusion.cli.main import app
from armfusion.models.sensor_models import recording_problems
from armfusion.models.simulator import simulate
from armfusion.sensors.recording import write_recording
from armfusion.sensors.samples import Recording, Stream
from typer.testing import CliRunner

runner = CliRunner()


@pytest.fixture(scope="module")
def seven_joint_recording(wmra, tmp_path_factory) -> Path:
    rec, _ = simulate(wmra, "startup", duration_s=3.0, seed=1)
    p = tmp_path_factory.mktemp("rec") / "wmra.csv"
    write_recording(rec, p)
    return p


def test_a_fitting_recording_has_no_problem(wmra, seven_joint_recording) -> None:
    rec, _ = simulate(wmra, "startup", duration_s=1.0, seed=2)
    assert recording_problems(wmra, rec) == []


@pytest.mark.parametrize("command", [["track"], ["calibrate", "joints"], ["calibrate", "sensors"],
                                     ["diagnose"]])
def test_a_six_joint_config_refuses_a_seven_encoder_recording(seven_joint_recording, command) -> None:
    # before: `track` crashed (broadcast error in angle_truth), `calibrate joints` went on
    # with the first six encoders
    r = runner.invoke(app, [*command, str(seven_joint_recording), "--config", "crs_a465"])
    assert r.exit_code == 2, r.output
    out = " ".join(r.output.split())  # the console wraps long lines
    assert (f"recording {seven_joint_recording} does not fit the arm config" in out
            and "encoder stream 'enc' has 7 channels (enc1..enc7) but the arm has 6 joints" in out
            and "ground truth 'true_q' has 7 joint angles but the arm has 6 joints" in out), out
    assert "Traceback" not in out


def test_inspect_counts_one_missing_sample_in_five_as_gaps(tmp_path: Path) -> None:
    # before: "100 Hz, 0 gaps" (a gap had to span 3 periods; one missing sample makes 2)
    rng = np.random.default_rng(11)
    t = np.arange(1000) * 0.01
    keep = np.arange(1000) % 5 != 3  # one sample in five missing
    mag = Stream("imu_mag", "mag", t[keep], rng.integers(-300, 300, (keep.sum(), 3)),
                 ("imu_mx", "imu_my", "imu_mz"))
    acc = Stream("acc1", "accel", t, rng.integers(-512, 512, (1000, 3)), ("acc1_x", "acc1_y", "acc1_z"))
    p = tmp_path / "gappy.csv"
    write_recording(Recording({"acc1": acc, "imu_mag": mag}), p)
    r = runner.invoke(app, ["inspect", str(p), "--json"])
    assert r.exit_code == 0, r.output
    import json

    streams = {s["name"]: s for s in json.loads(r.stdout)["streams"]}
    assert streams["imu_mag"]["gaps"] == 200 and streams["imu_mag"]["missing_samples"] == 200
    assert streams["imu_mag"]["missing_percent"] == pytest.approx(20.0)
    assert streams["acc1"]["gaps"] == 0 and streams["acc1"]["missing_samples"] == 0
    r = runner.invoke(app, ["inspect", str(p)])
    assert "200 (200)" in r.stdout  # gaps (missing) in the table
