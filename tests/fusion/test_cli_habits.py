"""The command line's habits: -h everywhere, a help that imports nothing heavy, output paths
checked before the work starts, progress bars only at a terminal."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from armfusion.fusion.cli.main import COMMANDS, LazyCommands, app
from typer.testing import CliRunner

runner = CliRunner()


@pytest.mark.parametrize("cmd", [[], ["info"], ["track"], ["simulate"], ["calibrate"],
                                 ["calibrate", "sensors"], ["calibrate", "joints"], ["diagnose"],
                                 ["record"]])
def test_dash_h_is_help_everywhere(cmd):
    r = runner.invoke(app, [*cmd, "-h"])
    assert r.exit_code == 0, r.output
    assert "Usage" in r.stdout and "--help" in r.stdout and "-h" in r.stdout


def test_help_imports_neither_the_tracker_nor_scipy_nor_zenoh():
    code = ("import sys; sys.argv = ['armfusion', '--help']\n"
            "from armfusion.fusion.cli.main import app\n"
            "try:\n    app()\nexcept SystemExit:\n    pass\n"
            "import json; print(json.dumps(sorted(sys.modules)))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    loaded = set(json.loads(r.stdout.splitlines()[-1]))
    assert "Commands" in r.stdout and "calibrate" in r.stdout and "track" in r.stdout
    heavy = {"armfusion.fusion.tracking.tracker", "armfusion.fusion.identification.identify", "armfusion.fusion.cli.demo",
             "scipy.stats", "scipy",
             "numpy", "numba", "zenoh", "matplotlib", "armfusion.models.arm_config"}
    assert not heavy & loaded, sorted(heavy & loaded)


def test_the_listing_says_what_each_command_says_of_itself():
    """The root listing comes from COMMANDS without importing the commands; loaded, every
    command's own first help paragraph is its entry, and every command a register function
    adds is in the table."""
    import typer

    group = typer.main.get_command(app)
    assert isinstance(group, LazyCommands)
    for name in COMMANDS:
        group.load(name)
    for name, (text, _where) in COMMANDS.items():
        real = group.commands[name]
        assert " ".join((real.help or "").split("\n\n")[0].split()) == text, name
    assert set(group.commands) == {"info", "inspect", *COMMANDS}


# --------------------------------------------------------------------------------------
# output paths: checked before the work starts, one line, exit 2

@pytest.fixture(scope="module")
def startup_csv(tmp_path_factory):
    from armfusion.fusion.cli.simulate import SimulationOptions, simulate

    path = tmp_path_factory.mktemp("rec") / "startup.csv"
    simulate("wmra", "startup", path, SimulationOptions(duration_s=3.0, seed=1))
    return path


@pytest.mark.parametrize("args,option", [
    (["info", "--plot", "{f}/arm.png"], "--plot"),
    (["simulate", "-s", "daily-use", "--out", "{f}/rec.csv"], "--out"),
    (["diagnose", "{rec}", "--report", "{f}/report.html"], "--report"),
    (["diagnose", "{rec}", "--write", "{f}/c2.yaml"], "--write"),
    (["calibrate", "sensors", "{rec}", "--write", "{f}/c2.yaml"], "--write"),
    (["calibrate", "joints", "{rec}", "--save", "{f}/pose.json"], "--save"),
    (["track", "{rec}", "--out", "{f}/est.csv"], "--out"),
    (["record", "{f}/rec.mcap", "--duration", "0.1"], "OUT"),
    (["drivers", "--fake", "--duration", "1", "--out", "{f}/rec.csv"], "--out"),
])
def test_an_output_under_a_regular_file_is_refused_before_the_work(tmp_path, startup_csv, args, option):
    f = tmp_path / "a_file"
    f.write_text("not a directory")
    argv = [a.format(f=f, rec=startup_csv) for a in args]
    r = runner.invoke(app, argv)
    assert r.exit_code == 2, r.output
    assert f"error: {option} {f}/" in r.stderr
    assert f"{f} is a file, not a directory" in r.stderr
    assert "Traceback" not in r.output and "FileExistsError" not in r.output
    assert len(r.stderr.strip().splitlines()) == 1
    assert f.read_text() == "not a directory"


def test_info_plot_with_an_image_suffix_matplotlib_cannot_write_is_one_line(tmp_path):
    r = runner.invoke(app, ["info", "--plot", str(tmp_path / "arm.txt")])
    assert r.exit_code == 2
    assert "--plot" in r.stderr and "unsupported suffix '.txt'; expected .png or .svg or .pdf" in r.stderr
    assert "Traceback" not in r.output and not (tmp_path / "arm.txt").exists()


def test_simulate_refuses_a_run_larger_than_memory_naming_the_bound(tmp_path):
    r = runner.invoke(app, ["simulate", "-s", "daily-use", "--duration", "1e9", "--out",
                            str(tmp_path / "r.csv")])
    assert r.exit_code == 2
    msg = " ".join(r.stderr.split())
    assert "--duration 1e+09 s at 100 Hz would need about 351 TB of memory" in msg
    assert "the bound is half the memory available now" in msg and "at most" in msg
    assert not list(tmp_path.iterdir())
    for bad in ("nan", "-5", "inf"):
        r = runner.invoke(app, ["simulate", "-s", "daily-use", "--duration", bad, "--out",
                                str(tmp_path / "r.csv")])
        assert r.exit_code == 2 and "--duration must be a positive number of seconds" in r.stderr


def test_the_run_size_bound_is_what_memory_allows():
    from armfusion.fusion.cli.simulate import MEMORY_BYTES_PER_VALUE, check_run_size
    from armfusion.fusion.configfile import load_arm

    arm = load_arm("wmra")
    per_s = 100 * 39 * MEMORY_BYTES_PER_VALUE  # 39 values an instant on the WMRA
    check_run_size(arm, "daily-use", 600.0, 100.0, available_bytes=2 * 600 * per_s)  # fits
    with pytest.raises(ValueError, match=r"at most 500 s at this rate"):
        check_run_size(arm, "daily-use", 600.0, 100.0, available_bytes=2 * 500 * per_s)
    with pytest.raises(ValueError, match=r"--rate must be a positive number of Hz"):
        check_run_size(arm, "daily-use", 10.0, 0.0)


# --------------------------------------------------------------------------------------
def test_track_says_which_span_its_rms_covers_on_a_short_recording(tmp_path):
    import re

    from armfusion.fusion.cli.simulate import SimulationOptions, simulate

    path = tmp_path / "short.csv"
    simulate("wmra", "daily-use", path, SimulationOptions(duration_s=25.0, seed=2))
    r = runner.invoke(app, ["track", str(path)], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "after 60 s" not in r.stdout
    m = re.search(r"RMS error (\d+\.\d)…(\d+\.\d) s \[deg\]", r.stdout)
    assert m is not None, r.stdout
    start, end = float(m.group(1)), float(m.group(2))
    assert 0.0 < start < end <= 25.0
    said = " ".join(r.stderr.split())
    assert "before --after-s 60 s: the RMS errors are over the whole tracked run" in said
    doc = json.loads(runner.invoke(app, ["track", str(path), "--json"]).stdout)
    assert doc["rms_span_s"] == pytest.approx([start, end], abs=0.05) and doc["rms_after_s"] == 0.0
    assert all(v is not None for v in doc["rms_error_deg"].values())
    # a clean recording: every joint's error within 3 of its sigmas nearly always
    assert set(doc["within_3_sigma"]) == set(doc["rms_error_deg"])
    assert all(0.95 <= v <= 1.0 for v in doc["within_3_sigma"].values()), doc["within_3_sigma"]
    # long enough: the span starts at --after-s
    doc = json.loads(runner.invoke(app, ["track", str(path), "--json", "--after-s", "20"]).stdout)
    assert doc["rms_after_s"] == 20.0 and doc["rms_span_s"][0] == pytest.approx(20.0, abs=0.011)


# --------------------------------------------------------------------------------------
# progress bars: with the time left, at a terminal only

BAR = __import__("re").compile(r"━+.*\d+%.*\d:\d\d:\d\d left (\d:\d\d:\d\d|-:--:--)")
"""A rich bar: the bar, per cent done, time elapsed, time left."""


def _at_a_terminal(args: list[str], cwd) -> str:
    """Run ``armfusion ARGS`` with stdout and stderr on a pseudo-terminal; what it showed."""
    import os
    import pty
    import select

    master, slave = pty.openpty()
    env = {**os.environ, "TERM": "xterm", "COLUMNS": "120"}
    env.pop("NO_COLOR", None)
    p = subprocess.Popen([sys.executable, "-m", "armfusion.fusion.cli", *args], stdout=slave, stderr=slave,
                         stdin=subprocess.DEVNULL, cwd=cwd, env=env)
    os.close(slave)
    out = b""
    while True:
        ready, _, _ = select.select([master], [], [], 120)
        if not ready:
            break
        try:
            chunk = os.read(master, 65536)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        out += chunk
    p.wait(timeout=120)
    os.close(master)
    text = __import__("re").sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out.decode(errors="replace"))
    assert p.returncode == 0, text[-2000:]
    return text


def test_simulate_shows_a_bar_with_the_time_left_at_a_terminal_only(tmp_path):
    shown = _at_a_terminal(["simulate", "-s", "daily-use", "--duration", "300", "--out", "r.csv"], tmp_path)
    assert "simulating" in shown or "writing r.csv" in shown
    assert BAR.search(shown), shown[-1500:]
    assert "Wrote r.csv" in shown
    quiet = _at_a_terminal(["simulate", "-s", "daily-use", "--duration", "300", "--out", "r.csv",
                            "--json"], tmp_path)
    assert "simulating" not in quiet and not BAR.search(quiet)
    assert json.loads(quiet[quiet.index("{"):])["duration_s"] == 300.0
    # redirected (a test's pipes): no bar either
    r = runner.invoke(app, ["simulate", "-s", "daily-use", "--duration", "300", "--out",
                            str(tmp_path / "r.csv")])
    assert r.exit_code == 0 and not BAR.search(r.output) and "simulating" not in r.output


def test_track_shows_its_bar_at_a_terminal(tmp_path, startup_csv):
    from armfusion.fusion.cli.simulate import SimulationOptions, simulate

    simulate("wmra", "daily-use", tmp_path / "d.csv", SimulationOptions(duration_s=60.0, seed=4))
    shown = _at_a_terminal(["track", "d.csv"], tmp_path)
    assert "tracking" in shown and BAR.search(shown)
    r = runner.invoke(app, ["track", str(tmp_path / "d.csv")])
    assert r.exit_code == 0 and not BAR.search(r.output)


def test_a_mistyped_command_gets_a_suggestion_among_the_lazy_ones():
    r = runner.invoke(app, ["trak"])
    assert r.exit_code == 2
    assert "No such command 'trak'. Did you mean 'track'?" in " ".join(r.output.split()).replace("│ ", "")


def test_table_headers_keep_their_units(startup_csv):
    """"[deg]" in a rich header is markup unless escaped: the units had vanished."""
    r = runner.invoke(app, ["info"], env={"COLUMNS": "220"})
    assert r.exit_code == 0 and "alpha [deg]" in r.stdout and "d [mm]" in r.stdout
    r = runner.invoke(app, ["inspect", str(startup_csv)], env={"COLUMNS": "220"})
    assert r.exit_code == 0 and "rate [Hz]" in r.stdout and "longest gap [s]" in r.stdout


# --------------------------------------------------------------------------------------
# shared options (armfusion.fusion.cli.options): the same check, before any work, in every command

@pytest.mark.parametrize("args", [
    ["replay", "no-such.csv", "--robot", "chair 1"],
    ["record", "out.mcap", "--robot", "chair/1"],
    ["serve", "--robot", ""],
    ["recalibrate", "--robot", "x" * 65],
    ["drivers", "--fake", "--robot", "chair 1"],
])
def test_a_robot_name_the_key_expressions_cannot_take_is_refused_in_one_line(args):
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert r.stdout == ""
    assert r.stderr.startswith("error: --robot ") and r.stderr.count("\n") == 1, r.stderr
    assert "use 1 to 64 letters, digits, '_' or '-'" in r.stderr


@pytest.mark.parametrize("args,option", [
    (["record", "out.mcap", "--duration", "0"], "--duration 0.0"),
    (["router", "--duration", "-1"], "--duration -1.0"),
    (["replay", "no-such.csv", "--batch-ms", "0"], "--batch-ms 0.0"),
    (["drivers", "--fake", "--batch-ms", "-5"], "--batch-ms -5.0"),
])
def test_a_duration_or_batch_that_is_not_positive_is_refused_before_the_work(args, option):
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == f"error: {option}: expected > 0"
