"""The options that more than one ``armfusion`` command takes, each declared once here.

A command names its parameter and its default; the flag, the help and the check of the
value come from here, so that ``--seed`` or ``--robot`` means the same in every command.
Grouped by what they are about: the arm and the output (every command), the simulated rig
(``simulate``, ``drivers --fake``, ``fleet``, ``demo``), the recordings, and Zenoh (every
node; see docs/reference/service.md, "Zenoh configuration").

The values are checked where they are parsed, before the command's work starts: a bad one
gives the one-line ``error:`` of :func:`armfusion.fusion.cli.common.fail` and exit 2.

Imports typer only (``armfusion --help`` loads it): a check that needs more imports it when
it runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from armfusion.fusion.cli.common import fail


def _positive(option: str):
    """A callback refusing a value that is not > 0 (``None``, an option not given, passes)."""

    def check(value: float | None) -> float | None:
        if value is not None and not value > 0:
            fail(f"{option} {value!r}: expected > 0")
        return value

    return check


MAX_STILL_WINDOW_S = 60.0
"""The longest still-detection or averaging window a command takes: a still stretch is
seconds long, and the detection's work grows with the window times the recording's length
(``--window-s 1e9`` asked for 522 GiB)."""


def window_seconds(option: str):
    """A callback refusing a window that is not a finite number of seconds in
    (0, :data:`MAX_STILL_WINDOW_S`]."""

    def check(value: float) -> float:
        if not 0.0 < value <= MAX_STILL_WINDOW_S:  # (NaN fails too)
            fail(f"{option} {value!r}: expected a window in seconds, > 0 and at most "
                 f"{MAX_STILL_WINDOW_S:g}")
        return value

    return check


def window_holds_samples(rec, window_s: float, option: str = "--window-s") -> None:
    """Exit 2 when ``window_s`` is shorter than two steps of the recording's fastest raw
    stream (its median step): a window must hold samples to judge stillness or to average
    (1e-9 s had judged each sample still alone, and found a longer still stretch)."""
    import numpy as np

    steps = [float(np.median(np.diff(s.t_s))) for s in rec.streams.values()
             if s.kind not in ("truth_joints", "truth_base") and len(s) > 2]
    if steps and window_s < 2.0 * min(steps):
        fail(f"{option} {window_s!r}: shorter than two samples of the recording (one every "
             f"{min(steps):.3g} s); a window must hold samples")


def finite_between(option: str, lo: float, hi: float, what: str, *, lo_open: bool = False,
                   hi_open: bool = False):
    """A callback refusing a value that is not a finite number from ``lo`` to ``hi`` (either end
    left out when ``lo_open``/``hi_open``); ``what`` says what it is (``an angle in degrees``)."""

    def check(value: float) -> float:
        above = value > lo if lo_open else value >= lo
        below = value < hi if hi_open else value <= hi
        if not (above and below and value == value and abs(value) != float("inf")):  # (NaN fails)
            span = (f"{'above' if lo_open else 'at least'} {lo:g}" if hi == float("inf") else
                    f"{'above' if lo_open else 'from'} {lo:g} {'and below' if hi_open else 'to'} {hi:g}")
            fail(f"{option} {value!r}: expected {what}, {span}")
        return value

    return check


def count_at_least(option: str, least: int, what: str):
    """A callback refusing a whole number below ``least`` (``what`` says what it counts)."""

    def check(value: int) -> int:
        if value < least:
            fail(f"{option} {value!r}: expected {what}, at least {least}")
        return value

    return check


def check_robot(value: str | None) -> str | None:
    """The callback of every ``--robot`` that names one robot: a name the key expressions take."""
    if value is not None:
        from armfusion.fusion.service.payloads import check_name

        try:
            check_name(value, "--robot")
        except ValueError as e:
            fail(str(e))
    return value


# --- the arm, the output ---------------------------------------------------------------------
ConfigOpt = Annotated[
    str, typer.Option("--config", "-c", help="Arm config: a shipped name (wmra, crs_a465, imu_rig_roll…) or a YAML path.")
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one machine-readable JSON document.")]
WriteConfigOpt = Annotated[Path | None, typer.Option(
    "--write", help="Write the config with the (last) estimates and their σ here.")]

# --- recordings --------------------------------------------------------------------------------
RecordingArg = Annotated[Path, typer.Argument(help="Recording: .csv (shared spec) or .mcap.")]
RecordingOutOpt = Annotated[Path, typer.Option(
    "--out", "-o", help="Write the recording: REC.csv or REC.mcap (a simulated one also "
    "REC.truth.json beside it).")]

# --- the simulated rig -------------------------------------------------------------------------
ScenarioOpt = Annotated[str, typer.Option(
    "--scenario", "-s", help="The simulated motion: a scenario of armfusion.models.trajectories "
    "(`armfusion simulate --help` lists them).")]
SeedOpt = Annotated[int, typer.Option(
    "--seed", help="Seed: the same seed, the same motion, effects and noise.",
    callback=count_at_least("--seed", 0, "a seed"))]
RealisticOpt = Annotated[bool, typer.Option(
    "--realistic", help="Draw every effect on every target at datasheet-typical magnitudes (seeded).")]
EffectOpt = Annotated[list[str] | None, typer.Option(
    "--effect", help="NAME[:TARGET]=VALUE, vector values comma separated, in the effect's units; "
    "repeatable (`armfusion simulate --help` lists the effects).")]
EffectsFileOpt = Annotated[Path | None, typer.Option(
    "--effects-file", help="Replay the effects of a REC.truth.json (or a config's effects list).")]
NoiseOpt = Annotated[bool, typer.Option(
    "--noise/--no-noise", help="Sensor noise (rounding and saturation always).")]

# --- Zenoh: every node -------------------------------------------------------------------------
ZenohConfigOpt = Annotated[Path | None, typer.Option(
    "--zenoh-config", help="Zenoh JSON5 config (default: config/zenoh.json5).")]
ListenOpt = Annotated[list[str] | None, typer.Option(
    "--listen", help="Listen endpoint, e.g. tcp/127.0.0.1:7447 (repeatable; loopback only).")]
ConnectOpt = Annotated[list[str] | None, typer.Option(
    "--connect", help="Endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; loopback only).")]
ADMITTED_WITHIN_S = 15.0
"""The default of --admitted-within: the fusion node's first status after the first batch
comes within a second, or a few while its startup calibration runs."""


def _seconds_or_zero(option: str):
    """A callback refusing a value that is not a finite number of seconds >= 0."""

    def check(value: float) -> float:
        if not (value >= 0 and value != float("inf")):
            fail(f"{option} {value!r}: expected a number of seconds >= 0 (0: no check)")
        return value

    return check


AdmittedWithinOpt = Annotated[float, typer.Option(
    "--admitted-within", callback=_seconds_or_zero("--admitted-within"),
    help="Exit 1 when the fusion node (its status) has admitted none of the raw samples this long "
         "after the first went out, in s (0: do not check; no fusion node heard: not judged).")]
ModeOpt = Annotated[str | None, typer.Option("--mode", help="peer, client or router.")]
RobotOpt = Annotated[str, typer.Option(
    "--robot", help="The robot's name in the key expressions (1 to 64 letters, digits, '_' or '-').",
    callback=check_robot)]
BatchMsOpt = Annotated[float, typer.Option(
    "--batch-ms", help="Sample time per published batch, in ms.", callback=_positive("--batch-ms"))]
StopAfterOpt = Annotated[float | None, typer.Option(
    "--duration", help="Stop after this long, in s (default: at SIGINT or SIGTERM).",
    callback=_positive("--duration"))]
