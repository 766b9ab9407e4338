"""Every door of the command line: a recording's samples meet the admission the fusion node
applies, in its words, before any command works on them; no output replaces an input or is
found unwritable after the work; arguments that make no sense are refused in one line."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service.admission import Admission
from armfusion.fusion.service.payloads import RawBatch
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.samples import Stream
from typer.testing import CliRunner

runner = CliRunner()
DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def startup_csv(tmp_path_factory) -> Path:
    from armfusion.fusion.cli.simulate import SimulationOptions, simulate

    path = tmp_path_factory.mktemp("rec") / "startup.csv"
    simulate("wmra", "startup", path, SimulationOptions(duration_s=3.0, seed=1))
    return path


def _with_cell(src: Path, out: Path, column: str, row: int, value: str) -> Path:
    lines = src.read_text().splitlines()
    head = lines[0].split(",")
    cells = lines[row].split(",")
    cells[head.index(column)] = value
    lines[row] = ",".join(cells)
    out.write_text("\n".join(lines) + "\n")
    return out


def _one_line(r) -> str:
    assert "Traceback" not in r.output
    said = " ".join(r.stderr.split())
    assert said.count("error:") == 1, said
    return said


# ---------------------------------------------------------------------------- the admission
@pytest.mark.parametrize("cmd", [["track"], ["calibrate", "joints"], ["calibrate", "sensors"], ["diagnose"],
                                 ["inspect"]], ids=lambda c: c[-1])
def test_one_impossible_encoder_value_is_refused_by_every_command_naming_its_row(
        tmp_path: Path, startup_csv: Path, cmd) -> None:
    # before: track exited 0 with j1 at -72.6° for 90 ms and its σ at 2.56°
    p = _with_cell(startup_csv, tmp_path / "bad.csv", "enc1", 150, str(2**63 - 1))
    r = runner.invoke(app, [*cmd, str(p)])
    assert r.exit_code == 2
    assert (f"{p}: row 150 (line 151), stream enc: enc1 = 9223372036854775807 at t = 1.49 s is beyond the "
            "device's range -2147483648…2147483647") in _one_line(r)


def test_a_file_and_the_wire_refuse_a_value_in_the_same_words(tmp_path: Path, startup_csv: Path) -> None:
    arm = load_arm("wmra")
    p = _with_cell(startup_csv, tmp_path / "acc.csv", "acc2_y", 101, "5000")
    said = _one_line(runner.invoke(app, ["track", str(p)]))
    models = stream_models(arm)
    m = models["acc2"]
    batch = RawBatch("chair1", Stream("acc2", "accel", np.array([1.0]), np.array([[0, 5000, 256]]),
                                         m.channels), 1)
    verdict = Admission(arm).check(batch, 0.0)
    assert verdict.reason == "out_of_range"
    assert verdict.message == "acc2_y = 5000 at t = 1 s is beyond the device's range -512…511"
    assert f"{p}: row 101 (line 102), stream acc2: {verdict.message}; " in said


def test_an_encoder_glitch_within_the_feed_is_refused_and_a_restart_is_not(tmp_path: Path,
                                                                          startup_csv: Path) -> None:
    # before: one enc1 cell of 2^31-1 made track's j1 jump between 90° and 222° for 50 ms (exit 0)
    p = _with_cell(startup_csv, tmp_path / "glitch.csv", "enc1", 150, str(2**31 - 1))
    r = runner.invoke(app, ["track", str(p)])
    assert r.exit_code == 2
    assert (f"{p}: row 150 (line 151), stream enc: enc1 moved 5.83e+04° in 0.01 s at t = 1.49 s, more "
            "than the joint can turn (30 rad/s), and the next sample moves it back: a spike no joint makes, "
            "so the recording is refused") in _one_line(r)
    # the wire says it in the same words
    arm = load_arm("wmra")
    enc = stream_models(arm)["enc"]
    adm = Admission(arm)
    assert adm.check(RawBatch("chair1", Stream("enc", "encoder", np.array([1.48]), np.zeros((1, 7), int),
                                               enc.channels), 1), 0.0).ok
    jump = np.zeros((1, 7), int)
    jump[0, 0] = 2**31 - 1
    verdict = adm.check(RawBatch("chair1", Stream("enc", "encoder", np.array([1.49]), jump, enc.channels), 2),
                        0.0)
    assert verdict.reason == "encoder_jump"  # (the wire's bound is 3 rad/s: it cannot see the next sample)
    assert verdict.message.replace("(3 rad/s)", "(30 rad/s)") in r.stderr.replace("\n", "")
    # a board that restarted: the counts go on from their new baseline
    lines = startup_csv.read_text().splitlines()
    col = lines[0].split(",").index("enc1")
    for k in range(150, len(lines)):
        cells = lines[k].split(",")
        cells[col] = str(int(cells[col]) + 10**6)
        lines[k] = ",".join(cells)
    restarted = tmp_path / "restart.csv"
    restarted.write_text("\n".join(lines) + "\n")
    assert runner.invoke(app, ["calibrate", "joints", str(restarted), "--json"]).exit_code == 0
    # ... but a fit over the whole recording reads angles from counts that do not carry across it
    # (before: calibrate sensors exited 0 at a reduced chi-square of 954510, diagnose with a
    # residual 6e6 times the noise)
    for cmd in (["calibrate", "sensors"], ["diagnose"]):
        r = runner.invoke(app, [*cmd, str(restarted)])
        assert r.exit_code == 2
        assert (f"{restarted}: row 150 (line 151), stream enc: enc1 moved 27.2° in 0.01 s at t = 1.49 s, "
                "more than the joint can turn (30 rad/s); the counts do not carry across such a step "
                "(a board that restarted?), and a fit over the whole recording cannot span it"
                ) in _one_line(r)


def test_a_second_recording_meets_the_same_door(tmp_path: Path, startup_csv: Path) -> None:
    # before: diagnose --validate and calibrate sensors --compass-drive read their second recording
    # without the range screen (acc1_x = 5000 went into the judging or the compass fit)
    p = _with_cell(startup_csv, tmp_path / "acc.csv", "acc1_x", 101, "5000")
    for cmd in (["diagnose", str(startup_csv), "--validate", str(p)],
                ["calibrate", "sensors", str(startup_csv), "--compass-drive", str(p)]):
        r = runner.invoke(app, cmd)
        assert r.exit_code == 2
        assert (f"{p}: row 101 (line 102), stream acc1: acc1_x = 5000 at t = 1 s is beyond the device's "
                "range -512…511") in _one_line(r)


def test_a_compass_drive_that_is_no_recording_is_refused_before_the_fit(tmp_path: Path,
                                                                       startup_csv: Path) -> None:
    # before: read only after the whole fit (a minute of work on a real maneuver), then refused
    fifo = tmp_path / "drive.csv"
    os.mkfifo(fifo)
    for drive, said in (("/dev/zero", "cannot read recording /dev/zero: unknown recording suffix '(none)'"),
                        (str(fifo), f"cannot read recording {fifo}: not a regular file")):
        r = runner.invoke(app, ["calibrate", "sensors", str(startup_csv), "--compass-drive", drive])
        assert r.exit_code == 2 and said in _one_line(r)
        assert "fitting" not in r.stderr


def test_diagnose_never_replaces_a_file_that_is_no_history(tmp_path: Path, startup_csv: Path) -> None:
    # before: --history naming another recording (or any file that is not JSON) was warned about
    # and replaced by a new history, exit 0; /dev/zero was read without end, a FIFO blocked
    other = tmp_path / "other.csv"
    other.write_bytes(startup_csv.read_bytes())
    fifo = tmp_path / "h.json"
    os.mkfifo(fifo)
    device = "not a regular file (a device, a FIFO); diagnose would replace it"
    for history, why in ((other, "holds something other than a workbench history; diagnose would replace "
                                 "it: give another path, or remove the file"),
                         (Path("/dev/zero"), device), (fifo, device)):
        t0 = time.perf_counter()
        r = runner.invoke(app, ["diagnose", str(startup_csv), "--history", str(history)])
        assert r.exit_code == 2 and f"--history {history}: {why}" in _one_line(r)
        assert time.perf_counter() - t0 < 30
    assert other.read_bytes() == startup_csv.read_bytes()


def test_track_writes_its_estimates_into_a_directory_still_to_be_made(tmp_path: Path,
                                                                     startup_csv: Path) -> None:
    # before: the whole run, then "cannot write .../new/sub/est.csv: No such file or directory"
    out = tmp_path / "new" / "sub" / "est.csv"
    r = runner.invoke(app, ["track", str(startup_csv), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert out.read_text().startswith("t")


def test_import_refuses_a_value_no_sensor_of_the_config_reads(tmp_path: Path) -> None:
    src = tmp_path / "log.csv"
    src.write_text("t_ms,ax,ay,az,gx,gy,gz,angle_deg\n0,0,0,1,0,0,0,0\n10,0,0,1,0,0,0,18446744073709551616\n")
    cmap = tmp_path / "m.yaml"
    cmap.write_text(yaml.safe_dump({"time": {"column": "t_ms", "unit": "ms"}, "streams": {
        "shaft": {"columns": ["ax", "ay", "az"], "unit": "g"},
        "imu_gyro": {"columns": ["gx", "gy", "gz"], "unit": "deg/s"},
        "enc": {"columns": ["angle_deg"], "unit": "deg"}}}))
    out = tmp_path / "out.csv"
    r = runner.invoke(app, ["import", str(src), "--map", str(cmap), "--config",
                            str(DATA / "one_joint_rig.yaml"), "--out", str(out)])
    assert r.exit_code == 2 and not out.exists()
    # (2^64 degrees in counts: beyond int64 too, said as the number it is)
    assert (f"cannot import {src}: row 2 (columns angle_deg, stream enc): enc1 = 1.8446744073709552e+21 at "
            "t = 0.01 s is beyond the device's range -2147483648…2147483647") in _one_line(r)


# ---------------------------------------------------------------------------- outputs
def test_track_never_replaces_its_recording_by_any_name(tmp_path: Path, startup_csv: Path) -> None:
    # before: `track in.csv --out in.csv` exited 0 having replaced the recording with estimates
    rec = tmp_path / "in.csv"
    rec.write_bytes(startup_csv.read_bytes())
    (tmp_path / "sub").mkdir()
    for out in (rec, tmp_path / "sub" / ".." / "in.csv"):
        r = runner.invoke(app, ["track", str(rec), "--out", str(out)])
        assert r.exit_code == 2
        said = f"--out {out}: is the input {rec}; an output never replaces a file the command reads"
        assert said in _one_line(r)
    assert rec.read_bytes() == startup_csv.read_bytes()


def test_import_never_replaces_its_source(tmp_path: Path) -> None:
    src = tmp_path / "log.csv"
    src.write_text("t_ms,ax\n0,1\n")
    r = runner.invoke(app, ["import", str(src), "--map", "imu-rig", "--out", str(src)])
    assert r.exit_code == 2 and "is the input" in _one_line(r)
    assert src.read_text() == "t_ms,ax\n0,1\n"


@pytest.mark.parametrize("args", [
    ["diagnose", "{rec}", "--report", "/sys/r.html"], ["simulate", "-s", "startup", "--out", "/sys/x.csv"],
    ["record", "/sys/x.mcap", "--duration", "1"], ["calibrate", "joints", "{rec}", "--save", "/sys/p.json"],
    ["track", "{rec}", "--out", "/sys/e.csv"]], ids=lambda a: a[0])
def test_an_unwritable_place_is_refused_before_the_work(startup_csv: Path, args) -> None:
    # before: a PermissionError traceback, for diagnose after 51 s of work
    t0 = time.perf_counter()
    r = runner.invoke(app, [a.format(rec=startup_csv) for a in args])
    assert r.exit_code == 2 and "cannot create files in /sys (Permission denied)" in _one_line(r)
    assert time.perf_counter() - t0 < 5.0


# ---------------------------------------------------------------------------- arguments
@pytest.mark.parametrize("args, said", [
    (["inspect", "{rec}", "--window-s", "nan"],
     "--window-s nan: expected a window in seconds, > 0 and at most 60"),
    (["inspect", "{rec}", "--window-s", "1e9"], "--window-s 1000000000.0: expected a window in seconds"),
    (["inspect", "{rec}", "--window-s", "0"], "--window-s 0.0: expected a window in seconds"),
    (["calibrate", "joints", "{rec}", "--window-s", "-1"], "--window-s -1.0: expected a window in seconds"),
    # before: exit 0, each sample judged still alone (a still stretch 0.4 s longer than at 1 s)
    (["inspect", "{rec}", "--window-s", "1e-9"],
     "--window-s 1e-09: shorter than two samples of the recording (one every 0.01 s); a window must hold "
     "samples"),
    (["calibrate", "joints", "{rec}", "--window-s", "0.001"],
     "--window-s 0.001: shorter than two samples of the recording (one every 0.01 s)"),
    (["calibrate", "sensors", "{rec}", "--window", "0"],
     "--window 0: expected samples per fit point, at least 1"),
    (["diagnose", "{rec}", "--window", "0"], "--window 0: expected samples per fit point, at least 1"),
    (["diagnose", "{rec}", "--top", "-3"], "--top -3: expected a number of candidates, at least 0"),
    (["simulate", "--scenario", "", "--out", "{tmp}/s.csv"], "--scenario '': give a scenario's name"),
    # before: exit 0, no joint ever gravity-blind (nan) or ill-conditioned (-1)
    (["calibrate", "joints", "{rec}", "--gimbal-lock-deg", "nan"],
     "--gimbal-lock-deg nan: expected an angle in degrees, from 0 and below 90"),
    (["calibrate", "joints", "{rec}", "--sigma-limit-deg", "-1"],
     "--sigma-limit-deg -1.0: expected a sigma in degrees, above 0 to 180"),
    # before: exit 0, every RMS error null and `NaN` (not JSON) in --json
    (["track", "{rec}", "--after-s", "nan", "--json"],
     "--after-s nan: expected a number of seconds, at least 0"),
    # before: numpy's "expected non-negative integer", naming no option
    (["simulate", "-s", "startup", "--seed", "-1", "--out", "{tmp}/s.csv"],
     "--seed -1: expected a seed, at least 0"),
    # before: an OverflowError traceback in the startup's sigmas (1e308 squared)
    (["track", "{rec}", "--unmodelled-g", "1e308"],
     "--unmodelled-g must be from 0 to 1 g (more than gravity itself would make the sensor useless), "
     "not 1e+308"),
    # before: exit 0, a recording of its header alone; one every reader refuses (times too dense)
    (["simulate", "-s", "startup", "--rate", "1e-6", "--duration", "1", "--out", "{tmp}/s.csv"],
     "--duration 1 s at 1e-06 Hz holds no sample (one every 1e+06 s)"),
    (["simulate", "-s", "startup", "--rate", "200000", "--duration", "0.01", "--out", "{tmp}/s.csv"],
     "--rate 200000 Hz is faster than any sensor delivers (100 kHz at most)"),
    # before: a MemoryError traceback (7.28 TiB)
    (["drivers", "--fake", "--duration", "1e9"],
     "--duration 1e+09 s at 100 Hz would need about 351 TB of memory"),
])
def test_arguments_that_make_no_sense_are_refused_in_one_line(tmp_path: Path, startup_csv: Path, args,
                                                              said: str) -> None:
    # before: nan a ValueError, 1e9 an attempt at 522 GiB, --window 0 and --top -3 misleading answers,
    # --scenario '' a maneuver of nothing
    r = runner.invoke(app, [a.format(rec=startup_csv, tmp=tmp_path) for a in args])
    assert r.exit_code == 2 and said in _one_line(r)
    assert not (tmp_path / "s.csv").exists()


@pytest.mark.parametrize("prior", ["/dev/zero", "fifo", "rec", "list"])
def test_a_prior_that_is_not_a_saved_pose_is_said_and_not_used_at_once(tmp_path: Path, startup_csv: Path,
                                                                       prior: str) -> None:
    # before: `--prior /dev/zero` read until the machine's 16 GB were gone (killed), a FIFO blocked,
    # a JSON list was an AttributeError traceback
    import os

    path = {"/dev/zero": Path("/dev/zero"), "fifo": tmp_path / "p.json", "rec": startup_csv,
            "list": tmp_path / "l.json"}[prior]
    if prior == "fifo":
        os.mkfifo(path)
    if prior == "list":
        path.write_text("[1, 2]")
    t0 = time.perf_counter()
    r = runner.invoke(app, ["calibrate", "joints", str(startup_csv), "--prior", str(path)])
    assert time.perf_counter() - t0 < 20.0
    assert r.exit_code == 0 and "Traceback" not in r.output
    said = " ".join(r.output.split())
    assert f"{path}: unreadable saved pose (" in said and "); not used" in said


def test_serve_never_replaces_what_is_not_its_state(tmp_path: Path, startup_csv: Path) -> None:
    # before: `serve --state-file rec.csv` replaced the recording with its state at the first save,
    # and as root `--state-file /dev/zero` would have replaced the device with a file
    import os

    rec = tmp_path / "rec.csv"
    rec.write_bytes(startup_csv.read_bytes())
    os.mkfifo(tmp_path / "p.json")
    for path, said in [(rec, "holds something other than a saved fusion state; the node would replace"),
                       (Path("/dev/zero"), "not a regular file (a device, a FIFO); the node would"),
                       (tmp_path / "p.json", "not a regular file (a device, a FIFO)"),
                       (Path("/sys/s.json"), "cannot create files in /sys (Permission denied)")]:
        r = runner.invoke(app, ["serve", "--state-file", str(path), "--duration", "1"])
        assert r.exit_code == 2 and f"--state-file {path}: {said}" in _one_line(r)
    assert rec.read_bytes() == startup_csv.read_bytes()
