"""The command line's habits: -h everywhere, a help that imports nothing heavy, output paths
checked before the work starts, progress bars only at a terminal."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from fusion.cli import COMMANDS, LazyCommands, app

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
            "from fusion.cli import app\n"
            "try:\n    app()\nexcept SystemExit:\n    pass\n"
            "import json; print(json.dumps(sorted(sys.modules)))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    loaded = set(json.loads(r.stdout.splitlines()[-1]))
    assert "Commands" in r.stdout and "calibrate" in r.stdout and "track" in r.stdout
    heavy = {"fusion.tracker", "fusion.identify", "fusion.service.demo", "scipy.stats", "scipy",
             "numpy", "numba", "zenoh", "matplotlib", "models.arm_config"}
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
