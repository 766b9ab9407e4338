"""What every `armfusion` command shares: consoles, one-line failures, JSON output, loading a
config and a recording with a clear error, checked output paths and progress bars (the
shared options are in ``armfusion.fusion.cli.options``).

Kept apart from ``armfusion.fusion.cli.main`` (which registers the commands) so that command modules can
import it without an import cycle. It imports typer and rich only: ``armfusion --help``
loads it, so numpy, the config loader and the recording readers are imported by the
functions that use them.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import typer
from rich.console import Console

console = Console()
err_console = Console(stderr=True)


def fail(message: str, code: int = 2) -> None:
    """Say ``message`` on stderr, ``error:`` before each of its lines (taken as text, not
    markup), and exit with ``code``."""
    from rich.markup import escape

    for line in message.splitlines() or [""]:
        err_console.print(f"[bold red]error:[/] {escape(line)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def choice_or_exit(value: str, option: str, choices: Sequence[str]) -> str:
    """``value`` if it is one of ``choices``, else exit 2 naming ``option`` and the choices."""
    if value not in choices:
        fail(f"{option} must be {' or '.join(repr(c) for c in choices)}, not {value!r}")
    return value


def emit_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, default=json_default) + "\n")


def json_default(o):
    """``json.dumps`` default for numpy arrays and scalars and paths."""
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def load_arm_or_exit(config: str):
    from armfusion.fusion.configfile import load_arm
    from armfusion.models.arm_config import ConfigError

    try:
        return load_arm(config)
    except (ConfigError, FileNotFoundError) as e:
        fail(str(e))


def read_recording_or_exit(path: Path, arm=None):
    """The recording at ``path``, or a one-line error and exit 2. With ``arm`` (the
    command's config), also exit 2 when the recording does not fit it (an encoder per
    joint, a config sensor's channels: ``armfusion.models.sensor_models.recording_problems``):
    this is where every command's recording meets its config."""
    from armfusion.sensors.recording import read_recording

    if not path.exists():
        fail(f"recording not found: {path}")
    import warnings

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rec = read_recording(path)
    except (ValueError, OSError) as e:
        said = str(e)  # (a reader's message names the file first: not twice)
        fail(f"cannot read recording {said}" if said.startswith(f"{path}: ") else
             f"cannot read recording {path}: {said}")
    for w in caught:
        err_console.print(f"[yellow]warning:[/] {w.message}", highlight=False)
    if arm is not None:
        from armfusion.models.sensor_models import recording_problems

        problems = recording_problems(arm, rec)
        if problems:
            fail(f"recording {path} does not fit the arm config {arm.source}: "
                 + "; ".join(problems))
    return rec


def screen_or_exit(arm, rec, path: Path, required: Sequence[str], needed_by: str,
                   json_out: bool = False, encoder_steps: bool = False):
    """The one treatment of range and saturation (``armfusion.models.sample_admission.screen_samples``)
    for a command: exit 2 with one line when ``rec`` lacks a stream of ``required`` (what
    ``needed_by`` needs) or holds a value past its device's range, naming the place; else
    say on stderr how many saturated samples are left out, and return the screen.
    ``encoder_steps``: a command whose fit spans the whole recording refuses an encoder step no
    joint makes, too (``screen_samples``)."""
    from armfusion.models.sample_admission import MissingSensorError, OutOfRangeError, screen_samples

    try:
        screen = screen_samples(arm, rec, required, needed_by, encoder_steps)
    except (MissingSensorError, OutOfRangeError) as e:
        fail(f"{path}: {e}")
    if screen.any_saturated and not json_out:
        err_console.print(f"[yellow]{screen.words()}[/]", highlight=False)
    return screen


def arm_and_recording_or_exit(config: str, path: Path, required: Callable[[Any], Sequence[str]],
                              needed_by: str, json_out: bool = False, encoder_steps: bool = False):
    """``(arm, recording, screen)`` for a command that reads a recording with a config: the
    config (:func:`load_arm_or_exit`), the recording fitting it (:func:`read_recording_or_exit`)
    and its range screen (:func:`screen_or_exit`) of the streams ``required(arm)`` names, for
    what ``needed_by`` says (``{source}`` in it becomes the config's path)."""
    arm = load_arm_or_exit(config)
    rec = read_recording_or_exit(path, arm)
    screen = screen_or_exit(arm, rec, path, required(arm), needed_by.format(source=arm.source),
                            json_out, encoder_steps)
    return arm, rec, screen


def config_file(config: str) -> Path | None:
    """The file a ``--config`` names (a shipped name or a path), or ``None`` when it names
    none (the command's own loading then says why)."""
    from armfusion.fusion.configfile import resolve_config_path

    try:
        return resolve_config_path(config)
    except (FileNotFoundError, OSError, ValueError):
        return None


def output_path_problem(path: Path, suffixes: Sequence[str] | None = None,
                        inputs: Sequence[Path | str | None] = ()) -> str | None:
    """Why ``path`` cannot be written (a suffix not among ``suffixes``, a directory in its
    place, a parent that is a file, a directory where no file can be created: tried, by a
    file made and removed there) or must not be (it is one of the command's ``inputs``, by
    any name: a recording, a config), or ``None``. Leaves nothing behind."""
    from armfusion.sensors.output_files import cannot_create_in, same_file

    path = Path(path)
    if suffixes is not None and path.suffix.lower() not in suffixes:
        return (f"unsupported suffix {path.suffix or '(none)'!r}; expected "
                + " or ".join(suffixes))
    if path.is_dir():
        return "is a directory"
    given = same_file(path, inputs)
    if given is not None:
        return f"is the input {given}; an output never replaces a file the command reads"
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                return f"{parent} is a file, not a directory"
            break
    return cannot_create_in(path)


def check_output_path(path: Path, option: str, suffixes: Sequence[str] | None = None,
                      inputs: Sequence[Path | str | None] = ()) -> None:
    """Exit 2 with one line before any work when ``path`` cannot or must not be written
    (see :func:`output_path_problem`); ``option`` names it (``--out``)."""
    why = output_path_problem(path, suffixes, inputs)
    if why is not None:
        fail(f"{option} {path}: {why}")


def prepare_output_path(path: Path, option: str, suffixes: Sequence[str] | None = None,
                        inputs: Sequence[Path | str | None] = ()) -> Path:
    """:func:`check_output_path`, then create the missing parent directories."""
    check_output_path(path, option, suffixes, inputs)
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        fail(f"{option} {path}: cannot create its directory: {e.strerror or e}")
    return Path(path)


def beside_existing(path: Path, option: str) -> Path:
    """``path``, or where it already holds a file, the first free ``NAME-1.EXT``,
    ``NAME-2.EXT``, … beside it, said on stderr under ``option``: a recording restarted under
    its old name never replaces the one it would have overwritten (a compound suffix such as
    ``.ros2.mcap`` is kept whole)."""
    path = Path(path)
    if not path.exists():
        return path
    free = _free_beside(path)
    err_console.print(f"{option} {path} exists and is kept: recording to {free}")
    return free


def _free_beside(path: Path) -> Path:
    suffix = "".join(path.suffixes[-2:]) if path.name.lower().endswith(".ros2.mcap") else path.suffix
    stem = path.name[: len(path.name) - len(suffix)]
    n = 1
    while (path.parent / f"{stem}-{n}{suffix}").exists():
        n += 1
    return path.parent / f"{stem}-{n}{suffix}"


# --------------------------------------------------------------------------------------
def progress_shown(json_out: bool) -> bool:
    """Progress bars only for a person at a terminal: not with --json, not when stdout or
    stderr is redirected (a pipe, a file, a test)."""
    if json_out or os.environ.get("TERM") == "dumb":
        return False
    return sys.stdout.isatty() and err_console.is_terminal


@contextlib.contextmanager
def progress_bar(description: str, json_out: bool) -> Iterator[Callable[[float, str | None], None]]:
    """A progress bar on stderr with the time elapsed and the time left (rich), shown only
    when :func:`progress_shown`; yields ``advance(fraction_done, description=None)``."""
    if not progress_shown(json_out):
        yield lambda _f, _d=None: None
        return
    from rich.progress import (
        BarColumn,
        Progress,
        TaskProgressColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
                  TimeElapsedColumn(), TextColumn("left"), TimeRemainingColumn(),
                  console=err_console, transient=True) as bar:
        task = bar.add_task(f"{description:<32.32}", total=1.0)

        def advance(fraction: float, text: str | None = None) -> None:
            kw = {} if text is None else {"description": f"{text:<32.32}"}
            bar.update(task, completed=min(max(float(fraction), 0.0), 1.0), **kw)

        yield advance


def png_img(figs: dict[str, bytes], name: str) -> str:
    """The figure ``name`` of ``figs`` (PNG bytes) as an HTML ``<img>`` holding it inline, for a
    report that is one file; nothing when there is no such figure."""
    import base64

    if name not in figs:
        return ""
    return f'<img alt="{name}" src="data:image/png;base64,{base64.b64encode(figs[name]).decode()}">'
