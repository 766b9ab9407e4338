"""Automatic model discovery (`armfusion diagnose --discover`): the ladder walked by itself.
Two effects hidden at once are found, one after the other, down to the noise floor with
estimates within 3σ of the truth; a clean recording is left alone; effects the recording
cannot tell apart come as one finding with the motion that would separate them; a ladder
that stops above the noise says what the rest follows."""

import json

import numpy as np
import pytest
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.data import data_from_recording
from armfusion.fusion.workbench.diagnose import DiagnoseSettings
from armfusion.fusion.workbench.discover import STOP_NOISE, STOP_NOTHING, DiscoverSettings, discover
from armfusion.models.effects import model_from_arm
from armfusion.models.simulator import simulate
from typer.testing import CliRunner

WINDOW = 10


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


def _data(arm, hidden, seed, duration_s=60.0):
    rec, _ = simulate(arm, "renk-maneuver", duration_s, seed=seed,
                      effects=[{"effect": e, "target": t, "params": {k: v}} for e, t, k, v in hidden])
    return data_from_recording(arm, rec, window=WINDOW)


TWO = [("accel_bias", "acc2", "bias_g", [0.032, -0.027, 0.041]),
       ("mount_rotation", "acc3", "rotvec_rad", [0.021, -0.031, 0.012])]


def test_two_hidden_effects_are_discovered_to_the_noise_floor(arm):
    disc = discover(model_from_arm(arm), _data(arm, TWO, seed=11))
    assert disc.stop == STOP_NOISE and disc.final.fits_to_noise
    assert disc.final.rms_ratio <= 1.1 and disc.rungs[0].rms_ratio > 5
    assert [f.added for f in disc.findings] == ["accel_bias:acc2", "mount_rotation:acc3"]
    ladder = [r.rms_ratio for r in disc.rungs]
    assert all(b < a for a, b in zip(ladder, ladder[1:], strict=False)), ladder
    # the turned board is also its three axes turned together: one finding, said so
    mount = disc.findings[1]
    assert mount.members == ("mount_rotation:acc3", "accel_axes:acc3")
    assert "no motion separates them" in mount.separate_by
    # every rung carries its estimate ± σ, and the last fit's estimates match the truth
    assert set(disc.rungs[1].estimate) == {"acc2.accel_bias[x]", "acc2.accel_bias[y]", "acc2.accel_bias[z]"}
    fit = disc.final.fit
    for e, t, _, v in TWO:
        sl = fit.model.index[f"{t}.{e}"]
        z = (fit.x[sl] - np.asarray(v)) / fit.sigma[sl]
        assert np.all(np.abs(z) < 3.0), (e, z.round(2))
    assert disc.remaining == ()


def test_a_clean_recording_is_left_alone(arm):
    disc = discover(model_from_arm(arm), _data(arm, [], seed=12))
    assert disc.findings == () and len(disc.rungs) == 1
    assert disc.stop == STOP_NOISE and disc.final.rms_ratio <= 1.1


def test_effects_the_recording_cannot_tell_apart_are_one_finding(arm):
    """On a parked chair Earth's field is constant in the IMU's axes: soft iron acting on it is
    a constant offset, hard iron's. Hidden soft iron comes back as one finding naming both and
    the turn of the chair that would separate them, not as a guess."""
    hidden = [("mag_soft_iron", "imu", "matrix_error", [0.05, -0.04, 0.03, 0.02, -0.02, 0.015])]
    disc = discover(model_from_arm(arm), _data(arm, hidden, seed=33, duration_s=30.0))
    assert len(disc.findings) == 1 and disc.final.fits_to_noise
    f = disc.findings[0]
    assert set(f.members) == {"mag_hard_iron:imu", "mag_soft_iron:imu"} and f.added == "mag_hard_iron:imu"
    assert "full circle" in f.separate_by
    assert "cannot tell them apart" in f.words()


def test_a_ladder_that_stops_above_the_noise_says_what_the_rest_follows(arm):
    """With the library narrowed to effects that cannot explain acc2's bias, nothing is
    significant; the discovery stops above the noise and names the sensor and the inputs
    the residual follows."""
    hidden = [("accel_bias", "acc2", "bias_g", [0.032, -0.027, 0.041])]
    st = DiscoverSettings(diagnose=DiagnoseSettings(effects=("gyro_bias", "mag_hard_iron")))
    disc = discover(model_from_arm(arm), _data(arm, hidden, seed=14, duration_s=30.0), st)
    assert disc.findings == () and disc.stop == STOP_NOTHING
    assert disc.final.rms_ratio > 5
    assert disc.remaining[0].startswith("worst sensors: acc2")
    assert disc.remaining[1].startswith("against the noise the recording itself shows")
    assert any("follows" in w or "not white" in w for w in disc.remaining[2:]), disc.remaining


def test_cli_discover_json_write_report(arm, tmp_path):
    runner = CliRunner()
    rec = tmp_path / "rec.csv"
    r = runner.invoke(app, ["simulate", "--scenario", "renk-maneuver", "--duration", "30", "--seed", "15",
                            "--effect", "accel_scale:acc1=0.012,-0.01,0.015", "--out", str(rec)])
    assert r.exit_code == 0, r.output
    cfg = tmp_path / "wmra.yaml"
    from armfusion.fusion.configfile import resolve_config_path

    cfg.write_text(resolve_config_path("wmra").read_text(encoding="utf-8"), encoding="utf-8")
    out, report = tmp_path / "wmra2.yaml", tmp_path / "r.html"
    r = runner.invoke(app, ["diagnose", "--config", str(cfg), str(rec), "--discover", "--json",
                            "--write", str(out), "--report", str(report)])
    doc = json.loads(r.stdout)
    disc = doc["discovery"]
    assert disc["stop"] == STOP_NOISE and doc["verdict"] == "fits to noise"
    assert [f["added"] for f in disc["findings"]] == ["accel_scale:acc1"]
    assert doc["added"] == ["acc1.accel_scale"]
    rung = disc["rungs"][1]
    assert rung["label"] == "+ accel_scale:acc1" and rung["rms_ratio"] <= 1.1
    assert abs(rung["estimate"]["acc1.accel_scale[x]"]["value"] - 0.012) < 3 * rung["estimate"][
        "acc1.accel_scale[x]"]["sigma"]
    assert [x["label"] for x in doc["ladder"]] == ["wmra", "+ accel_scale:acc1"]
    html = report.read_text(encoding="utf-8")
    assert "Discovery: 1 effect found in 1 rung " in html and "+ accel_scale:acc1" in html
    # the scale is found, yet the config with it tracks j3 further off its encoder on the
    # held-out part than the config as it is, beyond chance; the simulator's j3 encoder reads
    # the true angle, so that is further off the truth: nothing is written, the reason said
    assert r.exit_code == 1 and doc["written"] is None and not out.exists(), r.output
    assert "j3's tracked angle is" in doc["write_refused"] and "(chance " in doc["write_refused"]
    t = doc["tracked_held_out"]
    assert (t["written"]["encoder_rms_deg"]["j3"] - t["as_it_is"]["encoder_rms_deg"]["j3"]
            > 3 * t["as_it_is"]["chance_deg"]["j3"])
    sim, _ = simulate(arm, "renk-maneuver", 5.0, seed=15)
    enc, true_q = sim.get("enc"), sim.get("true_q")
    j3 = np.interp(enc.t_s, true_q.t_s, true_q.values[:, 2])
    assert np.max(np.abs(enc.values[:, 2] / arm.counts_per_rad[2] - j3)) < 2.0 / arm.counts_per_rad[2]


def test_cli_discover_and_add_are_refused_together(tmp_path):
    r = CliRunner().invoke(app, ["diagnose", str(tmp_path / "none.csv"), "--discover",
                                 "--add", "accel_bias:acc2"])
    assert r.exit_code != 0
    assert "give --discover or --add, not both" in r.output


def test_the_revisit_swaps_an_effect_taken_while_another_was_missing(arm):
    """acc3's board turned and j2's sag hidden together (with acc2's bias): while the sag is
    missing, acc3's six axis angles fit better than its board's three turns, so the forward
    walk adds them; taken out again once the sag is in, the board's turn comes back as the
    simpler equal fit and replaces them."""
    hidden = [*TWO, ("link_compliance", "j2", "compliance_rad_per_nm", [2.5e-4])]
    disc = discover(model_from_arm(arm), _data(arm, hidden, seed=11, duration_s=40.0))
    labels = [r.label for r in disc.rungs]
    assert "accel_axes:acc3 -> mount_rotation:acc3" in labels, labels
    assert sorted(f.added for f in disc.findings) == sorted(f"{e}:{t}" for e, t, _, _ in hidden)
    assert disc.final.fits_to_noise and disc.final.rms_ratio <= 1.1
    assert "acc3.accel_axes" not in disc.final.fit.model.index


def test_cli_discover_on_a_moving_chair_cannot_write(tmp_path):
    """A driving chair goes to the tracker's innovations, which name no effect: nothing to write."""
    runner = CliRunner()
    rec = tmp_path / "du.csv"
    r = runner.invoke(app, ["simulate", "--scenario", "daily-use", "--duration", "20", "--seed", "2",
                            "--out", str(rec)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["diagnose", str(rec), "--discover", "--write", str(tmp_path / "c2.yaml")])
    assert r.exit_code != 0 and "the chair moves in this recording" in r.output
    assert not (tmp_path / "c2.yaml").exists()


TURNED_IMU = [("base_mount", "imu", "rotvec_rad", [-0.0264, 0.0179, 0.0203]),
              ("encoder_scale", "j7", "scale_error", [-0.00194])]


def test_a_turned_imu_is_found_first_not_through_the_links(arm):
    """The IMU turned by 1.5° on the chair, with j7's encoder scale. The first fit takes the base
    attitude from the IMU and leaves the turn on the links (5.3x the noise); identify then
    scales the link streams down (acc1 69x), so its optimum is not the datasheet χ²'s the score
    tests measure. Tested without the fitted parameters' gradient there, the turn scored 5e3
    instead of 2e5 and the ladder ran through ten link effects to the rung limit at 1.31x.
    With it: the turn (its equals on a parked chair named with it) first, then the scale, to
    the noise."""
    disc = discover(model_from_arm(arm), _data(arm, TURNED_IMU, seed=3026))
    assert disc.rungs[0].rms_ratio > 5 and disc.first.verdict == "missing effect: base_mount on imu"
    assert [f.added for f in disc.findings] == ["base_mount:imu", "encoder_scale:j7"]
    assert set(disc.findings[0].members) == {"base_mount:imu", "accel_bias:imu", "accel_axes:imu"}
    assert disc.stop == STOP_NOISE and disc.final.fits_to_noise and disc.final.rms_ratio <= 1.1
    # the turn about x is what a parked chair sees (about y it is j1's zero, about z the
    # heading: held at their priors); it is found within 3σ
    fit = disc.final.fit
    i = fit.names.index("imu.base_mount[x]")
    assert abs(fit.x[i] - TURNED_IMU[0][3][0]) < 3 * fit.sigma[i], (fit.x[i], fit.sigma[i])
