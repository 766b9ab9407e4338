"""A joint's encoder made from the gyroscopes on either side of it (the degraded mode of an
arm whose encoder failed): its rate read at the instant the samples were true, its scale,
bias and drift calibrated against the encoder, and the tracker following the joint from it
and gravity. Simulated on the real rig's layout, then on the real rig's slice."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm, resolve_config_path
from armfusion.fusion.tracking.gyro_encoder import (
    calibrate_gyro_encoder,
    gyro_joint_rate,
    with_gyro_encoder,
)
from armfusion.fusion.tracking.process import ProcessModel
from armfusion.fusion.tracking.settings import StateLayout, TrackerSettings
from armfusion.models.effects import model_from_arm
from armfusion.models.sensor_models import stream_models
from armfusion.models.simulator import SimulationOptions, simulate
from armfusion.sensors.samples import Recording, Stream

DATA = Path(__file__).resolve().parents[1] / "data" / "imu-rig"


def _rig_with(tmp_path, effects: list[dict]):
    cfg = yaml.safe_load(resolve_config_path("imu_rig_roll").read_text(encoding="utf-8"))
    cfg["effects"] = effects
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(cfg), encoding="utf-8")
    return load_arm(path)


def _true_rate(rec, t_s):
    q = rec.get("true_q")
    return np.interp(t_s, q.t_s, np.gradient(q.values[:, 0], q.t_s))


def test_each_gyro_is_read_when_its_samples_were_true(tmp_path):
    """The shaft's samples stamped 20 ms late (its calibrated time offset): read at the stamp
    the joint's rate lags the truth; read 20 ms on, as the offset says, it does not."""
    late = {"effect": "time_offset", "target": "shaft", "params": {"offset_s": [0.02]},
            "sigma": {"offset_s": [0.001]}}
    arm = _rig_with(tmp_path, [late])
    rec, _ = simulate(arm, "excitation", 20.0, seed=4, effects=model_from_arm(arm),
                      options=SimulationOptions(noise=False))
    t = rec.get("enc").t_s[50:-50]
    truth = _true_rate(rec, t)
    err_deg_s = np.degrees(np.sqrt(np.mean((gyro_joint_rate(arm, rec, 0, t) - truth) ** 2)))
    unaware = load_arm("imu_rig_roll")  # the same samples read at their stamps
    err_unaware = np.degrees(np.sqrt(np.mean((gyro_joint_rate(unaware, rec, 0, t) - truth) ** 2)))
    assert err_deg_s < 0.3 * err_unaware
    assert err_unaware > 0.2  # deg/s: a 20 ms lag at the excitation's rates


def test_the_gyros_angle_stands_in_for_the_encoder():
    """Calibrated on 40 s where the encoder is known, the gyros' angle over the next 20 s
    stays on the encoder to a fraction of a degree (noise and rounding as the sensors
    give them), and only the withheld joint's counts are replaced."""
    arm = load_arm("imu_rig_roll")
    rec, _ = simulate(arm, "excitation", 60.0, seed=7)
    t0 = rec.t_start_s
    cal = calibrate_gyro_encoder(arm, rec.between(t0, t0 + 40.0), 0)
    assert abs(cal.scale - 1.0) < 0.01 and abs(np.degrees(cal.bias_rad_s)) < 0.1
    later = rec.between(t0 + 40.0, np.inf)
    virtual = with_gyro_encoder(arm, later, 0, cal)
    enc, gyro = later.get("enc"), virtual.get("enc")
    np.testing.assert_array_equal(gyro.t_s, enc.t_s)
    rel_enc = (enc.values[:, 0] - enc.values[0, 0]) / arm.counts_per_rad[0]
    rel_gyro = gyro.values[:, 0] / arm.counts_per_rad[0]
    assert np.degrees(np.max(np.abs(rel_gyro - rel_enc))) < 0.5
    assert np.degrees(np.ptp(rel_enc)) > 20.0  # the joint did turn


def test_an_encoder_that_reads_later_than_the_gyros_is_measured_and_followed():
    """The encoder's counts read 6 ms after the gyros' samples (the rig's logger read them in
    turn): calibrated where both are known, the stand-in measures the delay, and its angle on
    the next stretch follows the encoder where, read undelayed, it would lead it by the
    joint's rate times 6 ms."""
    arm = load_arm("imu_rig_roll")
    rec, _ = simulate(arm, "excitation", 60.0, seed=7, options=SimulationOptions(noise=False))
    enc = rec.get("enc")
    late_counts = np.interp(enc.t_s - 0.006, enc.t_s, enc.values[:, 0].astype(float))
    late = Recording({**rec.streams, "enc": Stream(enc.name, enc.kind, enc.t_s, late_counts[:, None],
                                                    enc.channels)}, dict(rec.meta))
    t0 = rec.t_start_s
    cal = calibrate_gyro_encoder(arm, late.between(t0, t0 + 40.0), 0)
    assert abs(cal.delay_s - 0.006) < 0.001
    later = late.between(t0 + 40.0, np.inf)
    rel = (later.get("enc").values[:, 0] - later.get("enc").values[0, 0]) / arm.counts_per_rad[0]
    followed = with_gyro_encoder(arm, later, 0, cal).get("enc").values[:, 0] / arm.counts_per_rad[0]
    undelayed = with_gyro_encoder(arm, later, 0, replace(cal, rate_taps=())).get("enc").values[:, 0]
    rate = _true_rate(later, later.get("enc").t_s)

    def lead_s(angle):  # the part of the angle's error that goes with the joint's rate
        err = angle - angle[0] - rel
        return float(np.polyfit(rate, err - err.mean(), 1)[0])

    assert abs(lead_s(followed)) < 0.001
    assert abs(lead_s(undelayed / arm.counts_per_rad[0]) - 0.006) < 0.001


def _rung(rec, phase_rad):
    """``rec`` with the shaft gyro ringing about the shaft's axis at 30 °/s with ``phase_rad``."""
    g = rec.get("shaft_gyro")
    rung = np.array(g.values, dtype=float)
    rung[:, 0] += 30.0 * np.sin(phase_rad(g.t_s - g.t_s[0]))  # deg/s about the shaft's axis
    return Recording({**rec.streams, g.name: Stream(g.name, g.kind, g.t_s, rung, g.channels)}, dict(rec.meta))


def _held_out_deg(arm, rec, split_s: float):
    """Calibrated on the first ``split_s``: the calibration, and the RMS (deg) of the
    stand-in's error against the encoder on the rest, its mean removed."""
    t0 = rec.t_start_s
    cal = calibrate_gyro_encoder(arm, rec.between(t0, t0 + split_s), 0)
    later = rec.between(t0 + split_s, np.inf)
    enc = later.get("enc").values[:, 0]
    stand_in = with_gyro_encoder(arm, later, 0, cal).get("enc").values[:, 0]
    err = (stand_in - (enc - enc[0])) / arm.counts_per_rad[0]
    return cal, float(np.degrees(np.std(err)))


def test_a_vibration_the_gyros_alias_is_learnt_when_steady_and_reported_when_not():
    """The shaft ringing about its axis near 97 Hz (30 °/s), sampled at 100 Hz with no filter
    before the samples: they read a rate near 3 Hz whose integral swings ±1.6° (30 / 2π·3)
    about the encoder, 1.1° RMS. Steady, it is what the encoder reads otherwise than the link
    on every stretch: the taps learn it and the stand-in on the next stretch is within a tenth
    of that. Wandering (97 ± 1 Hz, as a stepper's steps follow its speed), the taps cannot
    follow it: the calibration reports what is left as the stand-in's bounded error, which
    the next stretch's error bears out. Neither is taken for the joint's motion."""
    arm = load_arm("imu_rig_roll")
    rec, _ = simulate(arm, "excitation", 60.0, seed=7)
    clean, clean_err = _held_out_deg(arm, rec, 40.0)
    steady, steady_err = _held_out_deg(arm, _rung(rec, lambda t: 2 * np.pi * 97.0 * t), 40.0)
    def wander(t):  # 97 Hz ± 1 Hz over 20 s
        return 2 * np.pi * (97.0 * t - np.cos(2 * np.pi * 0.05 * t) / (2 * np.pi * 0.05))

    wandering, wandering_err = _held_out_deg(arm, _rung(rec, wander), 40.0)
    aliased = 30.0 / (2 * np.pi * 3.0) / np.sqrt(2.0)
    assert clean.bounded_deg < 0.02 and clean_err < 0.02
    assert steady_err < 0.1 * aliased
    assert wandering.bounded_deg > 0.2 * aliased  # reported, and no smaller than what it does next
    assert 0.7 * wandering_err < wandering.bounded_deg < 1.5 * wandering_err
    for cal in (steady, wandering):
        assert abs(cal.scale - clean.scale) < 0.01  # the ringing is not the joint's motion


def test_a_joint_without_gyros_on_both_sides_is_refused_by_name():
    wmra = load_arm("wmra")
    rec, _ = simulate(wmra, "startup", 2.0, seed=1)
    with pytest.raises(ValueError, match=r"joint 'j1': no link gyroscope on link 1"):
        gyro_joint_rate(wmra, rec, 0, rec.get("enc").t_s)
    arm = load_arm("imu_rig_roll")
    short, _ = simulate(arm, "excitation", 8.0, seed=1)
    with pytest.raises(ValueError, match=r"needs at least 10 s with the encoder known, got 8\.0 s"):
        calibrate_gyro_encoder(arm, short, 0)


def test_the_joint_takes_the_gyros_drift_as_its_random_walk():
    arm = load_arm("wmra")
    layout = StateLayout(arm.n_joints)
    st = TrackerSettings(offset_random_walk_by_joint_deg_per_sqrt_s=(("j3", 0.3),))
    q = np.diag(ProcessModel(st, layout, arm.joint_names).Q(1.0, True, False))[layout.offset]
    np.testing.assert_allclose(np.sqrt(q), np.radians([0.0035, 0.0035, 0.3, 0.0035, 0.0035, 0.0035, 0.0035]))
    with pytest.raises(ValueError, match=r"no joint 'j9'"):
        ProcessModel(TrackerSettings(offset_random_walk_by_joint_deg_per_sqrt_s=(("j9", 0.3),)),
                     layout, arm.joint_names)
    with pytest.raises(ValueError, match=r"\['j3'\]: a random walk must be a positive number"):
        ProcessModel(TrackerSettings(offset_random_walk_by_joint_deg_per_sqrt_s=(("j3", -1.0),)),
                     layout, arm.joint_names)


def test_track_withholds_a_failed_encoder_and_says_so(tmp_path):
    """`armfusion track --encoder-withheld shaft@12` on the real rig's slice: the gyros
    calibrated on the first 12 s carry the shaft after it (the JSON says with what), and a
    malformed request is refused naming what it takes."""
    import json

    from armfusion.fusion.cli.main import app
    from armfusion.sensors.recording import read_recording
    from typer.testing import CliRunner

    runner = CliRunner()
    rec = tmp_path / "roll.mcap"
    r = runner.invoke(app, ["import", str(DATA / "raw_roll_slow_20s.mat"), "--map", "imu-rig",
                            "--config", "imu_rig_roll", "--out", str(rec)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["track", str(rec), "--config", "imu_rig_roll", "--moving-start",
                            "--encoder-withheld", "shaft@12", "--json"])
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    w = doc["encoder_withheld"]
    assert w["joint"] == "shaft" and w["from_s"] == 12.0 and abs(w["scale"] - 1.0) < 0.05
    assert any("encoder of shaft withheld from 12 s" in n for n in doc["notes"])
    assert doc["start"]["t_start_s"] >= read_recording(rec).t_start_s + 12.0 - 0.02  # afresh there
    for bad, said in (("shaft", "takes JOINT@SECONDS"), ("j9@5", "takes JOINT@SECONDS"),
                      ("shaft@500", "SECONDS must be a time inside the recording"),
                      ("shaft@4", "needs at least 10 s with the encoder known")):
        r = runner.invoke(app, ["track", str(rec), "--config", "imu_rig_roll", "--moving-start",
                                "--encoder-withheld", bad])
        assert r.exit_code != 0 and said in r.output, (bad, r.output)


def test_the_drift_is_measured_over_the_time_gravity_takes_to_correct_it():
    """A stand-in's error that walks 0.5 °/√s, seen through the shaft accelerometer: the
    tracker's correction takes √(σ² dt / w²), σ the accelerometer's one-sample error in rad.
    Shaken four times as hard (the config's fast error), gravity takes four times as long,
    and the drift is measured over that span."""
    from armfusion.fusion.tracking.gyro_encoder import correction_span_s

    arm = load_arm("imu_rig_roll")
    rec, _ = simulate(arm, "excitation", 30.0, seed=3)
    spacing = float(np.median(np.diff(rec.get("enc").t_s)))
    walk = np.cumsum(np.random.default_rng(5).normal(0.0, np.radians(0.5) * np.sqrt(spacing), 200_000))
    spans = []
    for fast_g in (0.01, 0.04):
        cal = replace(arm.calibration, accel_fast_error_g_per_sensor={"shaft": fast_g})
        shaken = replace(arm, calibration=cal)
        spans.append(correction_span_s(shaken, rec, 0, walk, spacing, 10.0))
        sigma_rad = np.hypot(fast_g, np.max(stream_models(arm)["shaft"].noise_physical_rms()))
        expected = np.sqrt(sigma_rad**2 * spacing / np.radians(0.5) ** 2)
        assert abs(spans[-1] - expected) < 0.1 * expected
    assert 3.0 < spans[1] / spans[0] < 4.2
