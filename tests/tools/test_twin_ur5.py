"""The UR5 twin (tools/twin_ur5.py) through a new user's commands, with the shipped config
as written (no hand-set floor): import, calibrate joints, track."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm, read_yaml, resolve_config_path
from armfusion.models.rotations import DEG
from typer.testing import CliRunner

from tools.twin_ur5 import CONTROLLER_RATE_HZ, logged_and_resampled, make_twin, write_csv

runner = CliRunner()


@pytest.fixture(scope="module")
def twin_mcap(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("twin")
    twin = make_twin(seed=3, duration_s=20.0)
    csv = write_csv(twin, tmp / "twin.csv")
    out = tmp / "twin.mcap"
    r = runner.invoke(app, ["import", str(csv), "--map", "ur5-csv", "--config", "ur5_two_imu",
                            "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    return twin, out


def test_the_twin_carries_the_real_errors():
    """What the twin draws is what the real recordings showed: scales 3.5-4.4 % low, mounts
    about 1° off, offsets within ±13 ms that drift, 125 Hz rows, under 1 s still at the start."""
    twin = make_twin(seed=5, duration_s=4.0)
    scales = np.concatenate([e["params"]["scale_error"] for e in twin.effects
                             if e["effect"] == "accel_scale"])
    assert np.all((scales <= -0.035) & (scales >= -0.044))
    mounts = [np.linalg.norm(e["params"]["rotvec_rad"]) / DEG for e in twin.effects
              if e["effect"] == "mount_rotation"]
    assert all(0.1 < m < 3.0 for m in mounts)
    for a, b in twin.offsets_ms.values():
        assert abs(a) <= 13.0 and abs(b) <= 13.0 and 5.0 - 1e-9 <= abs(b - a) <= 10.0 or abs(b) == 13.0
    np.testing.assert_allclose(np.diff(twin.columns["time_s"]), 1.0 / CONTROLLER_RATE_HZ, atol=1e-12)
    assert 0.6 <= twin.still_start_s < 1.0
    # a still accelerometer reads gravity about 4 % low
    g = np.linalg.norm(np.column_stack([twin.columns[f"forearm_a{c}"] for c in "xyz"])[:50], axis=1)
    assert 0.95 < np.mean(g) / 9.80665 < 0.97


def test_the_loggers_clock_reads_each_sample_late_and_resamples_linearly():
    """A ramp logged 10 ms late at 100 Hz and read at 125 Hz: each value is the ramp 10 ms
    earlier; outside the log, no value."""
    t = np.arange(0, 1.0, 0.01)
    v = (2.0 * t)[:, None]
    out = logged_and_resampled(t, v, lambda tt: np.full_like(tt, 0.010), np.arange(0, 1.2, 0.008))
    inside = np.isfinite(out[:, 0])
    tt = np.arange(0, 1.2, 0.008)[inside]
    np.testing.assert_allclose(out[inside, 0][2:], 2.0 * (tt[2:] - 0.010), atol=1e-12)
    assert not inside[-1]


def test_import_calibrate_track_on_the_twin_with_the_config_as_written(twin_mcap):
    """The shipped config as a new user writes it: nothing rejected, every joint within 3σ of
    the controller's angle at least 95 % of the time, wrist 1 (the one joint gravity reads
    alone) to a degree past -180° (not reported at +170°), and the joints no sensor reads
    (the base about the vertical, the wrist beyond the last IMU) with a σ that covers their
    limits, never a number at a few degrees."""
    twin, rec = twin_mcap
    r = runner.invoke(app, ["calibrate", "joints", str(rec), "--config", "ur5_two_imu", "--json"])
    assert r.exit_code == 0, r.output
    seg = json.loads(r.stdout)["segments"][0]
    # at the recording's start, on its under-a-second still stretch, and saying how short it was
    assert seg["t_start"] <= 0.1 and seg["t_end"] - seg["t_start"] < 1.0
    assert any("still stretch of only" in n for n in seg["notes"])
    joints = {j["name"]: j for j in seg["joints"]}
    assert joints["base"]["angle_rad"] is None and joints["wrist3"]["angle_rad"] is None
    # the shoulder and the elbow (parallel axes) each unseen, their sum read, and said so
    assert joints["shoulder"]["flag"] == joints["elbow"]["flag"] == "ill_conditioned"
    combos = {c["name"]: c for c in seg["combinations"]}
    assert "shoulder + elbow" in combos and "gravity reads together shoulder + elbow" in seg["summary"]
    k = int(round(seg["t_end"] * CONTROLLER_RATE_HZ))
    true_sum = twin.columns["q2_deg"][k] + twin.columns["q3_deg"][k]
    c = combos["shoulder + elbow"]
    assert abs(np.degrees(c["angle_rad"]) - true_sum) <= 3.0 * np.degrees(c["sigma_rad"]) < 15.0
    est = rec.with_name("est.csv")
    r = runner.invoke(app, ["track", str(rec), "--config", "ur5_two_imu", "--after-s", "0", "--json",
                            "--out", str(est)])
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["start"]["t_start_s"] <= 0.1 and doc["start"]["t_end_s"] < 1.0  # tracked from the start
    assert not any("chair" in n for n in doc["notes"])  # a bolted base is not a chair
    assert doc["sensor_warnings"] == []
    assert all(v == 0 for v in doc["rejections"].values())
    assert min(doc["within_3_sigma"].values()) >= 0.95, doc["within_3_sigma"]
    assert min(twin.columns["q4_deg"]) < -185.0  # the twin goes past -180°, and wrist 1 runs on:
    assert doc["max_error_deg"]["wrist1"] < 3.0  # no 360° jump (the mounts' 1° and noise only)
    # what gravity reads, once the tracker has read it (the startup sees neither j2 nor j3
    # alone): the forearm's pitch (j2 + j3) and the wrist's (j2 + j3 + j4) to the mounts' 1°
    e = np.genfromtxt(est, delimiter=",", names=True)
    late = e["t"] >= e["t"][0] + 3.0
    truth = {k: np.interp(e["t"], twin.columns["time_s"], twin.columns[k])
             for k in ("q2_deg", "q3_deg", "q4_deg")}
    forearm = np.degrees(e["q_shoulder"] + e["q_elbow"]) - truth["q2_deg"] - truth["q3_deg"]
    wrist = forearm + np.degrees(e["q_wrist1"]) - truth["q4_deg"]
    assert np.sqrt(np.mean(forearm[late] ** 2)) < 1.5 and np.sqrt(np.mean(wrist[late] ** 2)) < 1.5
    # the tracker names that sum itself, in the JSON and the CSV, with a sigma that covers its
    # error (scored here from the CSV against the controller's angles)
    reported = {c["name"]: c for c in doc["combinations"]}
    assert "shoulder + elbow" in reported and reported["shoulder + elbow"]["column"] in e.dtype.names
    col = reported["shoulder + elbow"]["column"]
    have = np.isfinite(e[col]) & late
    assert have.mean() > 0.8 * late.mean()
    err = np.degrees(e[col][have]) - truth["q2_deg"][have] - truth["q3_deg"][have]
    assert np.mean(np.abs(err) <= 3.0 * np.degrees(e["sigma_" + col][have])) >= 0.95
    assert np.sqrt(np.mean(err**2)) < 1.0
    assert any(c["name"] == "shoulder + elbow" for c in doc["final"]["combinations"])
    arm = load_arm("ur5_two_imu")
    span = np.degrees(arm.max_rad - arm.min_rad)
    final = doc["final"]
    for j in ("base", "wrist2", "wrist3"):
        i = final["joint_names"].index(j)
        assert final["flags"][i] in ("gimbal_lock", "unobserved")
        assert np.degrees(final["sigma_rad"][i]) > span[i] / np.sqrt(12.0) * 0.9  # a uniform spread's
    assert any("custom accelerometer, 0.05 g" in n for n in doc["notes"])
    # the bolted base's tilt (read by the IMUs, whose 0.05 g floor stays however long they are
    # read): within its 3 sigma of the table's at the scored instants, never averaged down
    # to a few hundredths of a degree
    for k, nm in enumerate(("roll", "pitch")):
        err = np.degrees(e[nm][late]) - twin.table_tilt_deg[k]
        sg = np.degrees(e["sigma_" + nm][late])
        assert np.mean(np.abs(err) <= 3.0 * sg) >= 0.95, (nm, err[-1], sg[-1])
        assert sg.min() > 0.3


def test_a_floor_set_to_zero_is_said_loudly(twin_mcap, tmp_path):
    """The same recording with ``accel_unmodelled_g: 0`` (the sensors claimed exact): the
    tracker rejects them, and says so, naming each sensor, how often and why."""
    _, rec = twin_mcap
    d = read_yaml(resolve_config_path("ur5_two_imu"))
    d["calibration"] = {"accel_unmodelled_g": 0.0}
    cfg = tmp_path / "exact.yaml"
    cfg.write_text(yaml.safe_dump(d))
    r = runner.invoke(app, ["track", str(rec), "--config", str(cfg), "--after-s", "0", "--json"])
    assert r.exit_code == 0, r.output
    warnings = json.loads(r.stdout)["sensor_warnings"]
    for s in ("forearm", "wrist"):
        said = [w for w in warnings if w.startswith(f"{s}:")]
        assert said and any("0 g, as the config gives it" in w or "implausible" in w for w in said), warnings


def test_a_levelled_base_starts_from_the_tilt_given(twin_mcap, tmp_path):
    """``base: {mount: fixed, roll_deg, pitch_deg}`` as an installer's level read it (the
    twin's table tilt): the tracker's tilt stays with it, within its sigma, and every joint
    keeps within 3σ."""
    twin, rec = twin_mcap
    d = read_yaml(resolve_config_path("ur5_two_imu"))
    roll, pitch = twin.table_tilt_deg
    d["base"] = {"mount": "fixed", "roll_deg": roll, "pitch_deg": pitch, "tilt_sigma_deg": 0.1}
    cfg = tmp_path / "levelled.yaml"
    cfg.write_text(yaml.safe_dump(d))
    r = runner.invoke(app, ["track", str(rec), "--config", str(cfg), "--after-s", "0", "--json"])
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    f = doc["final"]
    for got, sigma, true in ((f["roll_rad"], f["roll_sigma_rad"], roll),
                             (f["pitch_rad"], f["pitch_sigma_rad"], pitch)):
        assert abs(np.degrees(got) - true) <= 3.0 * np.degrees(sigma) + 0.1
        assert np.degrees(sigma) <= 0.1 + 1e-9
    assert min(doc["within_3_sigma"].values()) >= 0.95


def test_the_start_is_where_the_user_says(twin_mcap):
    """``--start-at T``: the startup on the first still stretch from T (the twin's rest, 3 s
    long, once a round), never on the still start before it; past the end, a clear refusal."""
    from armfusion.fusion.tracking.start import NoStillWindowError, choose_start
    from armfusion.sensors.recording import read_recording

    twin, path = twin_mcap
    arm, rec = load_arm("ur5_two_imu"), read_recording(path)
    first = choose_start(arm, rec)
    assert first.segment.t_start_s <= 0.1 and first.short  # the start's under-a-second still
    later = choose_start(arm, rec, start_at_s=rec.t_start_s + 2.0)
    assert later.segment is not None and 2.0 <= later.segment.t_start_s <= 7.0
    assert later.segment.duration_s >= 1.0 and not later.short
    t = np.asarray(twin.columns["time_s"])
    q = np.column_stack([twin.columns[f"q{i}_deg"] for i in range(1, 7)])
    inside = (t >= later.segment.t_start_s) & (t <= later.segment.t_end_s)
    assert np.ptp(q[inside], axis=0).max() < 0.01  # the arm truly stood there
    with pytest.raises(NoStillWindowError, match="outside the recording"):
        choose_start(arm, rec, start_at_s=rec.t_end_s + 1.0)
    # from 12 s the arm never rests again: --moving-start takes the least-moving instants
    # there; without it, a refusal that says so
    assert not np.any((t >= 12.0) & (np.r_[np.abs(np.diff(q, axis=0)).max(axis=1), 1.0] == 0.0))
    moving = rec.between(rec.t_start_s + 12.0, np.inf)
    assert choose_start(arm, moving, moving_start=True).segment is None
    with pytest.raises(NoStillWindowError, match="no still stretch"):
        choose_start(arm, moving)


def test_the_fit_reads_the_joints_where_the_controller_says_and_the_true_effects_fit_to_noise(twin_mcap,
                                                                                            tmp_path):
    """The controller's angles are absolute: the fit's joint angles are theirs (the elbow not
    placed where the still start cannot tell it: 90° off, its tangential acceleration then
    14x the noise of a clean twin), so the twin's own errors (each IMU's scale and mount, its
    clock's offset and drift) added by hand fit it to the noise, and the held-out part too."""
    from armfusion.fusion.identification.identify import data_from_recording
    from armfusion.models.rotations import wrap_angle
    from armfusion.sensors.recording import read_recording

    twin, rec = twin_mcap
    arm = load_arm("ur5_two_imu")
    data = data_from_recording(arm, read_recording(rec), window=10)
    t = data.state.t_s
    truth = np.column_stack([np.interp(t, twin.columns["time_s"], twin.columns[f"q{i}_deg"])
                             for i in range(1, 7)]) * DEG
    off = np.degrees(np.abs(wrap_angle(data.state.q_rad - truth))).max(axis=0)
    assert off.max() < 3.0, off  # wrist 1 read by gravity through a mount 1° off; the others exact
    assert off[[1, 2, 4]].max() < 0.01, off  # the shoulder, the elbow, wrist 2: untold at the start
    adds = [f"--add={e}:{s}" for s in ("forearm", "wrist")
            for e in ("accel_scale", "mount_rotation", "time_offset", "time_drift")]
    r = runner.invoke(app, ["diagnose", str(rec), "--config", "ur5_two_imu", *adds, "--json",
                            "--history", str(tmp_path / "h.json")])
    assert r.exit_code in (0, 1), r.output
    doc = json.loads(r.stdout)
    assert doc["before"]["rms_ratio"] > 20.0  # the shipped config: the scales' 4 % alone
    assert doc["rms_ratio"] < 1.2 and doc["held_out"]["rms_ratio"] < 1.3, (doc["rms_ratio"], doc["held_out"])


def test_a_turn_about_a_joint_s_axis_is_booked_from_the_encoders_zeros_and_tracks_no_worse(twin_mcap, tmp_path):
    """The twin's own errors added by hand and written: the fit holds each mount's turn about
    its own joint's axis at zero (the joint's zero takes it). The UR5's controller reads each
    joint's own angle, so the written config moves the joints' zeros back to the encoders' and
    books the turn to the mount (its header says so); tracked over the held-out part, the
    shoulder and the elbow are then no further off the controller's angles than with the
    shipped config. (Booked to the zeros instead, they were 0.2-0.5 deg further off.)"""
    _, rec = twin_mcap
    adds = [f"--add={e}:{s}" for s in ("forearm", "wrist")
            for e in ("accel_scale", "mount_rotation", "time_offset", "time_drift")]
    out = tmp_path / "written.yaml"
    r = runner.invoke(app, ["diagnose", str(rec), "--config", "ur5_two_imu", *adds, "--write", str(out),
                            "--history", str(tmp_path / "h.json"), "--json"])
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert out.exists() and doc["write_refused"] is None
    assert "from the encoders' zeros" in out.read_text()
    t = doc["tracked_held_out"]
    for joint in ("shoulder", "elbow"):
        # within the write gate's chance floor for one joint (0.01 deg)
        assert t["written"]["encoder_rms_deg"][joint] <= t["as_it_is"]["encoder_rms_deg"][joint] + 0.01, t
