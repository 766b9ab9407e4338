"""One treatment of range and saturation in every command that reads samples (track,
calibrate joints, calibrate sensors, diagnose): a value past its device's range refuses the
recording naming the place; saturated samples are left out and counted; a recording that
lacks a sensor the command needs is refused."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.models.sample_admission import MissingSensorError, OutOfRangeError, screen_samples
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.recording import read_recording
from typer.testing import CliRunner

runner = CliRunner()
COMMANDS = [["track"], ["calibrate", "joints"], ["calibrate", "sensors"], ["diagnose"]]
NEEDS = {"track": "track needs", "joints": "calibrate joints needs", "sensors": "calibrate sensors fits",
         "diagnose": "diagnose fits"}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A 30 s calibration maneuver (parked chair), and three spoilt copies of its CSV: one
    5000-count cell on acc2_y (row 501), acc3_z at its 511 rail for 100 rows (1000-1099),
    every link accelerometer's columns gone."""
    from armfusion.fusion.cli.simulate import SimulationOptions, simulate

    d = tmp_path_factory.mktemp("samples")
    good = d / "m30.csv"
    simulate("wmra", "renk-maneuver", good, SimulationOptions(duration_s=30.0, seed=3))
    with open(good, newline="") as fh:
        rows = list(csv.reader(fh))
    head = rows[0]

    def write(name, rs):
        with open(d / name, "w", newline="") as fh:
            csv.writer(fh).writerows(rs)
        return d / name

    r = [list(x) for x in rows]
    r[501][head.index("acc2_y")] = "5000"
    out = {"range": write("range.csv", r)}
    r = [list(x) for x in rows]
    for k in range(1000, 1100):
        r[k][head.index("acc3_z")] = "511"
    out["saturated"] = write("saturated.csv", r)
    keep = [c for c, n in enumerate(head) if not n.startswith("acc")]
    out["no_accel"] = write("no_accel.csv", [[x[c] for c in keep] for x in rows])
    out["good"] = good
    return out


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c[-1])
def test_a_value_past_the_device_range_refuses_the_recording_naming_the_place(recordings, cmd):
    r = runner.invoke(app, [*cmd, str(recordings["range"])])
    assert r.exit_code == 2, r.output
    said = " ".join(r.stderr.split())
    # the place in the file, then the fusion node's own words for the same refusal
    assert ("range.csv: row 501 (line 502), stream acc2: acc2_y = 5000 at t = 5 s is beyond the "
            "device's range -512…511; no such sensor can read that, so the recording is refused") in said
    assert "Traceback" not in r.output and said.count("error:") == 1


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c[-1])
def test_a_recording_without_the_link_accelerometers_is_refused(recordings, cmd):
    r = runner.invoke(app, [*cmd, str(recordings["no_accel"]), "--json"])
    assert r.exit_code == 2, r.output
    said = " ".join(r.stderr.split())
    assert f"the recording has no samples of acc1, acc2, acc3, acc4, which {NEEDS[cmd[-1]]}" in said
    assert "(it has: imu_acc, imu_gyro, imu_mag, imu_temp, enc)" in said
    assert r.stdout == ""  # no "calibrated" parameters, no estimates


@pytest.mark.parametrize("cmd,windows", [(["track"], None), (["calibrate", "joints"], None),
                                         (["calibrate", "sensors"], 5), (["diagnose"], 11)],
                         ids=["track", "joints", "sensors", "diagnose"])
def test_saturated_samples_are_left_out_and_counted_alike(recordings, cmd, windows, tmp_path):
    if cmd == ["diagnose"]:  # its error ladder, out of the working directory
        cmd = [*cmd, "--history", str(tmp_path / "h.json")]
    r = runner.invoke(app, [*cmd, str(recordings["saturated"]), "--json"])
    assert r.exit_code == 0, r.output
    left = json.loads(r.stdout)["saturated_left_out"]
    if windows is None:
        assert left == {"acc3": 100}
    else:  # the windows (25 samples for calibrate sensors, 10 for diagnose) rows 1000-1099 touch
        assert left == {"samples": {"acc3": 100}, "windows": windows}
    r = runner.invoke(app, [*cmd, str(recordings["saturated"])], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert ("saturated samples (a channel at its register limit), left out: acc3 100 of 3,000 (3.3 %)"
            in r.stderr)


def test_a_clean_recording_reports_nothing_left_out(recordings):
    r = runner.invoke(app, ["calibrate", "sensors", str(recordings["good"]), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["saturated_left_out"] == {"samples": {}, "windows": 0}


def test_the_fit_data_leaves_out_exactly_the_windows_that_hold_saturation(recordings):
    from armfusion.fusion.identification.identify import data_from_recording

    arm = load_arm("wmra")
    clean = data_from_recording(arm, read_recording(recordings["good"]), window=25)
    spoilt = data_from_recording(arm, read_recording(recordings["saturated"]), window=25)
    assert clean.n == 120 and spoilt.n == 115 and spoilt.saturated_windows == 5
    # windows 39..43 (samples 975-1099) are gone, the rest identical
    kept = np.r_[0:39, 44:120]
    np.testing.assert_array_equal(spoilt.counts["acc3"], clean.counts["acc3"][kept])
    assert "5 of 120 windows left out: they hold saturated samples (acc3 100)" in spoilt.note


def test_saturated_and_beyond_range_per_channel():
    arm = load_arm("wmra")
    m = stream_models(arm)["acc1"]
    c = np.array([[0, 511, -3], [-512, 0, 0], [600, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(m.saturated(c).any(1), [True, True, True, False])
    np.testing.assert_array_equal(m.beyond_range(c).any(1), [False, False, True, False])
    enc = stream_models(arm)["enc"]  # unbounded: nothing saturates
    assert not enc.saturated(np.full((2, 7), 2**40)).any()


def test_screen_names_the_first_value_past_range_and_what_is_missing(recordings):
    arm = load_arm("wmra")
    place = r"^row 501 \(line 502\), stream acc2: acc2_y = 5000 at t = 5 s is beyond the device's range"
    with pytest.raises(OutOfRangeError, match=place):
        screen_samples(arm, read_recording(recordings["range"]))
    with pytest.raises(MissingSensorError, match=r"no samples of acc1, acc2, acc3, acc4, which X needs"):
        screen_samples(arm, read_recording(recordings["no_accel"]), ["enc", "acc1", "acc2", "acc3", "acc4"],
                       "X needs")
    s = screen_samples(arm, read_recording(recordings["saturated"]))
    assert s.saturated["acc3"] == 100 and s.samples["acc3"] == 3000 and not s.saturated["acc1"]
