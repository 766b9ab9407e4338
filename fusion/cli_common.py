"""What every `armfusion` command shares: consoles, the --config/--json options, one-line
failures, JSON output, and loading a config or a recording with a clear error.

Kept apart from ``fusion.cli`` (which registers the commands) so that command modules can
import it without an import cycle.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console

from fusion.configfile import load_arm
from models.arm_config import ConfigError

console = Console()
err_console = Console(stderr=True)

ConfigOpt = Annotated[
    str, typer.Option("--config", "-c", help="Arm config: a shipped name (wmra, crs_a465) or a YAML path.")
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one machine-readable JSON document.")]


def fail(message: str, code: int = 2) -> None:
    err_console.print(f"[bold red]error:[/] {message}", highlight=False, markup=True, soft_wrap=True)
    raise typer.Exit(code)


def emit_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, default=json_default) + "\n")


def json_default(o):
    """``json.dumps`` default for numpy arrays and scalars and paths."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def load_arm_or_exit(config: str):
    try:
        return load_arm(config)
    except (ConfigError, FileNotFoundError) as e:
        fail(str(e))


def read_recording_or_exit(path: Path, arm=None):
    """The recording at ``path``, or a one-line error and exit 2. With ``arm`` (the
    command's config), also exit 2 when the recording does not fit it (an encoder per
    joint, a config sensor's channels: ``models.sensor_models.recording_problems``):
    this is where every command's recording meets its config."""
    from sensors.recording import read_recording

    if not path.exists():
        fail(f"recording not found: {path}")
    import warnings

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rec = read_recording(path)
    except (ValueError, OSError) as e:
        fail(f"cannot read recording {path}: {e}")
    for w in caught:
        err_console.print(f"[yellow]warning:[/] {w.message}", highlight=False)
    if arm is not None:
        from models.sensor_models import recording_problems

        problems = recording_problems(arm, rec)
        if problems:
            fail(f"recording {path} does not fit the arm config {arm.source}: "
                 + "; ".join(problems))
    return rec
