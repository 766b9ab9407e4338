"""`armfusion calibrate joints` end to end on recordings: still windows, refusals, the
saved prior, JSON; `calibrate sensors` on a ramp recording (stances, the inclinometer)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.startup.pose_store import load_pose
from armfusion.models.kinematics import gravity_in_sensors
from armfusion.models.rotations import DEG, up_from_tilt
from armfusion.sensors.recording import write_recording
from armfusion.sensors.samples import Recording, Stream, accel_columns, encoder_columns
from typer.testing import CliRunner

runner = CliRunner()


def still_recording(arm, segments, rng, rate_hz=100.0, roll_deg=1.0, pitch_deg=-0.5, spoil=None):
    """Still segments of the arm at the given poses (deg) with 2 s of motion between them:
    raw ADXL345 and MPU-9150 counts with datasheet noise, encoders counting from 0."""
    t_parts, q_parts = [], []
    t0 = 0.0
    q_prev = None
    for q_deg, dur in segments:
        q = np.radians(q_deg)
        if q_prev is not None:  # a 2 s smooth move
            tm = t0 + np.arange(0, 2.0, 1 / rate_hz)
            s = 0.5 - 0.5 * np.cos(np.pi * (tm - t0) / 2.0)
            t_parts.append(tm)
            q_parts.append(q_prev + s[:, None] * (q - q_prev))
            t0 += 2.0
        ts = t0 + np.arange(0, dur, 1 / rate_hz)
        t_parts.append(ts)
        q_parts.append(np.tile(q, (len(ts), 1)))
        t0 += dur
        q_prev = q
    t = np.concatenate(t_parts)
    Q = np.concatenate(q_parts)
    up = up_from_tilt(roll_deg * DEG, pitch_deg * DEG)
    f = gravity_in_sensors(arm, Q, up)
    streams = {}
    for i, s in enumerate(arm.link_accelerometers):
        c = np.rint(f[:, i] * 256 + rng.normal(0, [0.75, 0.75, 1.1], (len(t), 3)))
        c = np.clip(c, -512, 511).astype(int)
        if spoil is not None:
            c = spoil(s.name, t, c)
        streams[s.name] = Stream(s.name, "accel", t, c, accel_columns(s.name))
    imu = np.rint(np.tile(up, (len(t), 1)) * 16384 + rng.normal(0, 46, (len(t), 3))).astype(int)
    streams["imu_acc"] = Stream("imu_acc", "imu_accel", t, imu, ("imu_ax", "imu_ay", "imu_az"))
    gyro = np.rint(rng.normal(0, 5, (len(t), 3)) + 150).astype(int)  # a zero-rate offset
    streams["imu_gyro"] = Stream("imu_gyro", "gyro", t, gyro, ("imu_gx", "imu_gy", "imu_gz"))
    enc = np.rint((Q - Q[0]) * arm.counts_per_rad).astype(int)
    streams["enc"] = Stream("enc", "encoder", t, enc, encoder_columns(arm.n_joints))
    streams["true_q"] = Stream("true_q", "truth_joints", t, Q, tuple(f"true_q{i + 1}" for i in range(7)))
    return Recording(streams)


def _calibrated(arm):
    """The WMRA config with perfectly known sensors (no unmodelled-error floor)."""
    import yaml
    from armfusion.fusion.configfile import resolve_config_path

    d = yaml.safe_load(resolve_config_path("wmra").read_text())
    d["calibration"] = {"accel_unmodelled_g": 0.0}
    return d


def test_two_still_segments_each_solved(tmp_path, wmra, rng):
    import yaml

    cfg = tmp_path / "wmra_cal.yaml"
    cfg.write_text(yaml.safe_dump(_calibrated(wmra)))
    q1 = [30, 40, 20, -50, 60, 30, 100]
    q2 = [100, 60, -30, 45, 120, -40, 10]
    rec = still_recording(wmra, [(q1, 4.0), (q2, 4.0)], rng)
    path = tmp_path / "two.csv"
    write_recording(rec, path)
    r = runner.invoke(app, ["calibrate", "joints", str(path), "--config", str(cfg), "--segments",
                            "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert len(d["segments"]) == 2
    for seg, q in zip(d["segments"], (q1, q2), strict=True):
        got = [j["angle_rad"] for j in seg["joints"]]
        flags = [j["flag"] for j in seg["joints"]]
        assert all(f in ("ok", "ambiguous") for f in flags), flags
        for g, want, j in zip(got, q, seg["joints"], strict=True):
            if j["flag"] == "ok":
                assert abs(np.degrees(g) - want) < max(0.15, 4 * np.degrees(j["sigma_rad"]))
        assert abs(np.degrees(seg["base"]["roll_rad"]) - 1.0) < 0.05
        assert seg["residual_rms_g"] < 0.002
    # default: the first still window only, printed for a person
    r2 = runner.invoke(app, ["calibrate", "joints", str(path), "--config", str(cfg)])
    assert r2.exit_code == 0, r2.output
    assert "still segment t = 0.00" in r2.stdout and r2.stdout.count("still segment") == 1


def test_saturated_and_dead_sensors_are_left_out_by_name(tmp_path, wmra, rng):
    def spoil(name, t, c):
        if name == "acc2":
            c[:, 2] = 511  # stuck at the top of its range
        if name == "acc4":
            c[:] = rng.integers(-1, 2, c.shape)  # reads nothing: disconnected
        return c

    rec = still_recording(wmra, [([30, 40, 20, -50, 60, 30, 100], 3.0)], rng, spoil=spoil)
    path = tmp_path / "bad.csv"
    write_recording(rec, path)
    r = runner.invoke(app, ["calibrate", "joints", str(path), "--json"])
    assert r.exit_code == 0, r.output
    seg = json.loads(r.stdout)["segments"][0]
    notes = " | ".join(seg["notes"])
    assert "acc2 in t = " in notes
    assert "axis z saturated (100 of 100 samples at the -512/511 count limit); left out" in notes
    assert "acc4 in t = " in notes and "expected about 1 g: a dead or disconnected sensor" in notes
    # joints 1-2 still come from acc1; 7 (only acc4 sees it) cannot be a confident number
    flags = {j["name"]: j["flag"] for j in seg["joints"]}
    assert flags["j7"] != "ok"


def test_saved_prior_round_trip_and_wrong_arm_prior_ignored(tmp_path, wmra, rng, crs):
    import yaml

    cfg = tmp_path / "wmra_cal.yaml"
    cfg.write_text(yaml.safe_dump(_calibrated(wmra)))
    q = [30, 40, 20, -50, 60, 30, 100]
    rec = still_recording(wmra, [(q, 3.0)], rng)
    path = tmp_path / "s.csv"
    write_recording(rec, path)
    saved = tmp_path / "state" / "pose.json"
    r = runner.invoke(app, ["calibrate", "joints", str(path), "--config", str(cfg),
                            "--save", str(saved), "--json"])
    assert r.exit_code == 0, r.output
    assert any("pose saved" in n for n in json.loads(r.stdout)["notes"])
    pose, why = load_pose(saved, wmra)
    assert why is None and np.allclose(np.degrees(pose.q_rad), q, atol=0.3)
    assert not list(saved.parent.glob("*.tmp"))  # the atomic write left no temporary
    pose2, why2 = load_pose(saved, crs)
    assert pose2 is None and "saved for arm 'WMRA-II', not 'CRS-A465'" in why2


def test_moving_recording_is_refused(tmp_path, wmra, rng):
    t = np.arange(0, 5, 0.01)
    c = np.stack([200 * np.sin(3 * t), 200 * np.cos(3 * t), 100 + 0 * t], 1).astype(int)
    rec = Recording({a: Stream(a, "accel", t, c, accel_columns(a)) for a in ("acc1", "acc2", "acc3", "acc4")})
    path = tmp_path / "moving.csv"
    write_recording(rec, path)
    r = runner.invoke(app, ["calibrate", "joints", str(path)])
    assert r.exit_code == 2
    assert "no still stretch in the recording" in r.stderr and "moving.csv" in r.stderr
    assert "the startup calibration needs a still arm" in r.stderr


def test_the_configs_calibrated_effects_are_applied(tmp_path, wmra):
    """An arm with a biased, rotated accelerometer and a joint zero off by a degree: with
    those effects in the config the startup is right again; without them it is not."""
    import yaml
    from armfusion.fusion.configfile import resolve_config_path
    from armfusion.models.simulator import SimulationOptions, simulate

    effects = [
        {"effect": "accel_bias", "target": "acc2", "params": {"bias_g": [0.03, -0.02, 0.035]}},
        {"effect": "mount_rotation", "target": "acc3", "params": {"rotvec_rad": [0.0, 0.03, 0.0]}},
        {"effect": "joint_offset", "target": "j2", "params": {"offset_rad": [0.017]}},
        {"effect": "accel_scale", "target": "acc4", "params": {"scale_error": [0.01, -0.012, 0.008]}},
    ]
    q = np.radians([30, 40, 20, -50, 60, 30, 100])
    rec, _ = simulate(wmra, "startup", duration_s=4.0, seed=3, effects=effects,
                      options=SimulationOptions(scenario_options={"pose_rad": q}))
    path = tmp_path / "s.csv"
    write_recording(rec, path)
    base = yaml.safe_load(resolve_config_path("wmra").read_text())
    base["calibration"] = {"accel_unmodelled_g": 0.0}
    errs = {}
    for label, eff in (("with", effects), ("without", [])):
        cfg = tmp_path / f"{label}.yaml"
        cfg.write_text(yaml.safe_dump({**base, "effects": eff}))
        r = runner.invoke(app, ["calibrate", "joints", str(path), "--config", str(cfg), "--json"])
        assert r.exit_code == 0, r.output
        d = json.loads(r.stdout)
        seg = d["segments"][0]
        got = np.array([np.nan if j["angle_rad"] is None else j["angle_rad"] for j in seg["joints"]])
        errs[label] = np.degrees(np.abs(got - q))
        if label == "with":
            assert any("applied from the config: acc2.accel_bias" in n for n in d["notes"])
            assert all(j["flag"] in ("ok", "ambiguous") for j in seg["joints"])
    assert np.nanmax(errs["with"]) < 0.15, errs["with"]
    assert np.nanmax(errs["without"]) > 1.0, errs["without"]


@pytest.fixture(scope="module")
def ramp_recording(tmp_path_factory, wmra):
    from armfusion.models.simulator import simulate

    rec, truth = simulate(wmra, "renk-ramp", 125.0, seed=3, effects=[
        {"effect": "accel_bias", "target": "imu", "params": {"bias_g": [0.02, -0.015, 0.01]}},
        {"effect": "base_mount", "target": "imu", "params": {"rotvec_rad": [0.01, -0.008, 0.012]}}])
    path = tmp_path_factory.mktemp("ramp") / "ramp.csv"
    write_recording(rec, path)
    return path, truth


def test_calibrate_sensors_fits_each_stance_and_takes_the_inclinometer(ramp_recording):
    """On a ramp recording `calibrate sensors` gives each parked stance its own attitude,
    and the inclinometer's reading of the first stance's tilt pins the IMU's mount about
    j1's axis (held without it)."""
    path, truth = ramp_recording
    want = [e["tilt_deg"] for e in truth["events"] if e.get("parked")]
    r = runner.invoke(app, ["calibrate", "sensors", str(path), "--effects", "accel_bias,base_mount",
                            "--base-tilt", f"{want[0][0]},{want[0][1]}", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    stances = np.array(d["stance_attitudes_deg"])
    assert stances.shape == (5, 3)
    np.testing.assert_allclose(stances[:, :2], want, atol=0.2)  # every stance's tilt found
    p = {q["name"]: q for q in d["parameters"]}
    y = p["imu.base_mount[y]"]
    assert not y["held"] and abs(y["value"] - (-0.008)) < 3 * y["sigma"], y


@pytest.mark.parametrize("bad", ["1,2,3", "north,2", "0,95"])
def test_calibrate_sensors_refuses_a_malformed_base_tilt(ramp_recording, bad):
    path, _ = ramp_recording
    r = runner.invoke(app, ["calibrate", "sensors", str(path), "--base-tilt", bad])
    assert r.exit_code == 2
    assert "--base-tilt: give ROLL,PITCH in degrees" in r.output


# --------------------------------------------------------------------------------------
# `calibrate sensors --reference`: what gravity can never give
@pytest.fixture(scope="module")
def j7_gauge_recording(tmp_path_factory, wmra):
    """A minute of the sensor-calibration maneuver on an arm whose last sensor is turned 1.5°
    about j7's axis (and a little about the others) and whose joints sit off their zeros; the
    true geometric angle of j7 over the first still segment (no sag or play: controller angle
    plus zero offset)."""
    from armfusion.fusion.startup.static import find_static_segments
    from armfusion.models.simulator import simulate

    offsets = np.radians([0.6, -0.4, 0.8, -0.5, 0.3, -0.7, 0.9])
    entries = [{"effect": "mount_rotation", "target": "acc4",
                "params": {"rotvec_rad": [0.02, -0.015, 0.026]}}]
    entries += [{"effect": "joint_offset", "target": j, "params": {"offset_rad": [float(o)]}}
                for j, o in zip(wmra.joint_names, offsets, strict=True)]
    rec, _ = simulate(wmra, "renk-maneuver", 60.0, seed=4, effects=entries)
    path = tmp_path_factory.mktemp("gauge") / "man.csv"
    write_recording(rec, path)
    seg = find_static_segments(rec)[0]
    tq = rec.get("true_q").between(seg.t_start_s, seg.t_end_s)
    return path, float(np.degrees(tq.values[:, 6].mean() + offsets[6]))


def _sensors(path, *args):
    return runner.invoke(app, ["calibrate", "sensors", str(path), "--effects", "mount_rotation",
                               "--json", *args])


def test_a_j7_reference_pins_the_last_sensors_mount_about_j7s_axis(j7_gauge_recording, tmp_path):
    """Without a reference acc4's mount about j7's axis is held with j7's zero (a gauge);
    with the joint at a known angle once, it is estimated (the truth within 3σ, σ near the
    reference's) and the written config says what the number rests on."""
    path, j7_deg = j7_gauge_recording
    out = tmp_path / "none.yaml"
    r = _sensors(path, "--write", str(out))
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    mount_z = {p["name"]: p for p in d["parameters"]}["acc4.mount_rotation[z]"]
    assert mount_z["held"] and d["references"] == []
    ident = yaml.safe_load(out.read_text())["calibration"]["identified"]
    assert "acc4.mount_rotation[z]" in ident["joint_zero_conventions"] and ident["references"] == []

    out = tmp_path / "ref.yaml"
    r = _sensors(path, "--reference", f"j7={j7_deg:.4f}:0.05", "--write", str(out))
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    mount_z = {p["name"]: p for p in d["parameters"]}["acc4.mount_rotation[z]"]
    assert not mount_z["held"]
    assert abs(mount_z["value"] - 0.026) < 3 * mount_z["sigma"], mount_z
    assert mount_z["sigma"] < np.radians(0.1), mount_z
    text = out.read_text()
    assert "# rests on the one-time reference j7 = " in text
    ident = yaml.safe_load(text)["calibration"]["identified"]
    assert ident["joint_zero_conventions"] == []
    (ref,) = ident["references"]
    assert ref["joint"] == "j7" and ref["sigma_deg"] == 0.05 and ref["where"] == "the first still segment"
    assert abs(ref["angle_deg"] - j7_deg) < 1e-3 and ref["t_start_s"] == 0.0 and not ref["contradicted"]
    # and the startup on that config says what its j7 rests on
    r = runner.invoke(app, ["calibrate", "joints", str(path), "--config", str(out), "--json"])
    assert r.exit_code == 0, r.output
    assert any(n.startswith("j7's zero rests on the one-time reference of the sensors' calibration: j7 = ")
               for n in json.loads(r.stdout)["notes"])


def test_a_reference_that_contradicts_the_data_writes_nothing(j7_gauge_recording, tmp_path):
    """j7's zero is a gauge, so the data alone never see a wrong reference: what they see is
    the mount it implies against the mount's own tolerance (2°). A reference 12° off puts
    acc4 12° round its mount: refused, nothing written. One 1° off is inside the tolerance:
    accepted, and the check says how large an error it could not have seen."""
    path, j7_deg = j7_gauge_recording
    out = tmp_path / "bad.yaml"
    r = _sensors(path, "--reference", f"j7={j7_deg + 12:.4f}", "--write", str(out))
    assert r.exit_code == 2
    assert "contradicts the calibration" in r.output and "not written" in r.output
    assert not out.exists()
    r = _sensors(path, "--reference", f"j7={j7_deg + 1:.4f}")
    assert r.exit_code == 0, r.output
    (ref,) = json.loads(r.stdout)["references"]
    assert not ref["contradicted"] and 1.5 < ref["without_reference_sigma_deg"] < 2.5
    assert "would not be detected" in ref["message"]


@pytest.mark.parametrize(("given", "message"), [
    ("j7", "--reference: give JOINT=DEG"),
    ("j7=north", "--reference: give JOINT=DEG"),
    ("j7=0:abc", "--reference: give JOINT=DEG"),
    ("j9=0", "--reference: no joint 'j9' on WMRA-II"),
    ("j2=130", "--reference j2: 130° is outside its limits"),
    ("j7=0:0", "--reference j7: σ must be a positive number"),
    ("j7=0@seg99", "--reference j7: still segment 99 does not exist"),
    ("j7=0@30", "--reference j7: the arm is not still at t = 30 s"),
])
def test_calibrate_sensors_refuses_a_malformed_reference(j7_gauge_recording, given, message):
    path, _ = j7_gauge_recording
    r = _sensors(path, "--reference", given)
    assert r.exit_code == 2
    assert message in " ".join(r.output.split())


def test_a_drive_gives_the_written_config_its_compass(j7_gauge_recording, tmp_path, wmra):
    """A parked maneuver cannot see the compass's hard iron; ``--compass-drive`` tracks a
    recording of the chair turning with the fitted config and writes the iron its turns
    pinned, with its sigma (the truth within 3 sigma, well under the shipped 15 µT), and
    says so in the file and the JSON."""
    from armfusion.models.simulator import simulate

    path, _ = j7_gauge_recording
    true_iron_ut = np.array([14.0, -14.0, 5.0])
    drive, _ = simulate(wmra, "excitation", 40.0, seed=5, effects=[
        {"effect": "mag_hard_iron", "target": "imu", "params": {"offset_ut": true_iron_ut.tolist()}}])
    drive_path = tmp_path / "drive.csv"
    write_recording(drive, drive_path)
    out = tmp_path / "c2.yaml"
    r = _sensors(path, "--compass-drive", str(drive_path), "--write", str(out))
    assert r.exit_code == 0, r.output
    line = json.loads(r.stdout)["compass_drive"]
    assert line.startswith("compass from the turns in drive.csv") and "heading doubt" in line
    text = out.read_text()
    assert "# compass from the turns in drive.csv" in text
    (hard,) = [e for e in yaml.safe_load(text)["effects"] if e["effect"] == "mag_hard_iron"]
    est, sigma = np.array(hard["params"]["offset_ut"]), np.array(hard["sigma"]["offset_ut"])
    assert np.all(np.abs(est - true_iron_ut) <= 3 * sigma) and np.all(sigma[:2] < 2.0), (est, sigma)
    r = _sensors(path, "--compass-drive", str(tmp_path / "none.csv"))
    assert r.exit_code != 0 and "none.csv" in r.output
