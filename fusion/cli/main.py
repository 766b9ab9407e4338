"""The ``armfusion`` command line.

Every command that computes something takes ``--json`` and then prints exactly one JSON
document on stdout (see docs/cli.md). Errors go to stderr as one clear message, exit 2.

Commands are registered explicitly: ``info`` and ``inspect`` here, every other one by the
``register`` function :data:`COMMANDS` names, called when that command runs or its help is
asked for (the root group, :class:`LazyCommands`, lists them from the table). So
``armfusion --help`` imports typer and rich, not the tracker, the fits or Zenoh.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Annotated

import typer
from armfusion.fusion.cli.common import (
    check_output_path,
    config_file,
    console,
    emit_json,
    fail,
    load_arm_or_exit,
    read_recording_or_exit,
)
from armfusion.fusion.cli.options import (
    ConfigOpt,
    JsonOpt,
    RecordingArg,
    window_holds_samples,
    window_seconds,
)
from typer.core import TyperGroup

from armfusion import __version__

# command name -> (its first help paragraph, "module:function" that registers it on the app);
# one function may register several commands (the service's)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("Simulate a recording of the arm's sensors (raw counts, truth columns, truth file).",
                 "armfusion.fusion.cli.simulate:register"),
    "drivers": ("Read the sensors through the drivers (or, with --fake, the simulator-fed fakes) and "
                "report read time, jitter, errors and samples per device; with --robot, publish the raw "
                "samples over Zenoh as they are read.", "armfusion.fusion.cli.drivers:register"),
    "replay": ("Publish a recording's raw samples on armfusion/<robot>/raw/<sensor>, with their timing.",
               "armfusion.fusion.cli.nodes:register"),
    "record": ("Record a robot's raw samples and estimates from Zenoh to MCAP until stopped.",
               "armfusion.fusion.cli.nodes:register"),
    "serve": ("The fusion node: startup calibration on the first still window (or resume from "
              "--state-file), then the tracker; publishes armfusion/<robot>/state/joints, "
              "state/heading and status; answers armfusion/<robot>/calibrate (and, with --maneuver, "
              "serves a planned calibration maneuver on armfusion/<robot>/maneuver).",
              "armfusion.fusion.cli.nodes:register"),
    "recalibrate": ("Ask the fusion node (armfusion serve) to re-run the startup calibration now, on the "
                    "latest still stretch; it refuses, saying why, while the arm moves. Exits 1 when "
                    "refused.", "armfusion.fusion.cli.nodes:register"),
    "maneuver": ("The planned calibration maneuver the fusion node serves (serve --maneuver), as the arm's "
                 "controller sees it: show it, or say the controller starts it, is done with it (the "
                 "node then fits the sensors on it) or aborts it; apply the fit's config. Exits 1 when the "
                 "node refuses.",
                 "armfusion.fusion.cli.nodes:register"),
    "demo": ("The whole service on this machine, no hardware, loopback only: the simulated WMRA "
             "calibrates its sensors, then fake drivers → fusion node → recorder run as processes "
             "over Zenoh; a summary against the truth and an HTML report.",
             "armfusion.fusion.cli.demo:register"),
    "router": ("A Zenoh router on loopback for the nodes of several robots: it listens where --listen "
               "says, else where --zenoh-config's file says (default tcp/127.0.0.1:7447), and connects "
               "where its file says (or --connect); runs until SIGINT or SIGTERM.",
               "armfusion.fusion.cli.fleet:register"),
    "deploy": ("Write a fleet's certificates, credentials and Zenoh configs: each chair's (its certificate, "
               "its nodes' users and passwords, its router's and nodes' configs) and, the first time, the "
               "fleet's CA and the base station's; the base router's policy admits every chair of the fleet.",
               "armfusion.fusion.cli.deploy:register"),
    "fleet": ("N simulated chairs as separate processes (fake drivers → serve each), connected "
              "through one Zenoh router; watch them with `armfusion monitor --connect <router>`.",
              "armfusion.fusion.cli.fleet:register"),
    "monitor": ("A live table of every robot: joints (deg, sigma, flags), heading, node states, "
                "samples and drops, age of the last update. Subscribes armfusion/*/state/*, status "
                "and the liveliness tokens.", "armfusion.fusion.cli.fleet:register"),
    "diagnose": ("Compare the model with a recording: where it fails, which physical effect is missing.",
                 "armfusion.fusion.cli.diagnose:register"),
    "track": ("Track the joint angles and the heading through a recording: startup calibration on "
              "its first still stretch (or, with --moving-start, on its least-moving instants), then "
              "the unscented Kalman filter on every sample.",
              "armfusion.fusion.cli.track:register"),
    "import": ("Turn a foreign recording (CSV, MATLAB .mat, HDF5, a ROS bag) into the arm's native one: each "
               "stream from the columns the map names, in the unit the config declares; rows whose time "
               "does not increase dropped, NaN kept as gaps, every change said.",
               "armfusion.fusion.cli.import_cmd:register"),
    "plan-maneuver": ("Plan the self-calibration maneuver: poses, dwells and safe moves that make the "
                      "fit's parameters best known in the time given; the sigma each parameter and each "
                      "joint's startup will have after it.", "armfusion.fusion.cli.plan_maneuver:register"),
    "calibrate": ("Calibrate: joint angles from a still arm, or the sensors.",
                  "armfusion.fusion.cli.main:register_calibrate"),
}


def register_calibrate(app: typer.Typer) -> None:
    """``calibrate joints`` (armfusion.fusion.cli.calibrate_joints) and ``calibrate sensors``
    (armfusion.fusion.cli.calibrate_sensors) under ``calibrate``."""
    from armfusion.fusion.cli.calibrate_joints import calibrate_app
    from armfusion.fusion.cli.calibrate_sensors import calibrate_sensors

    if not any(c.name == "sensors" for c in calibrate_app.registered_commands):
        calibrate_app.command("sensors")(calibrate_sensors)
    app.add_typer(calibrate_app, name="calibrate")


class LazyCommands(TyperGroup):
    """The root group: lists every command of :data:`COMMANDS` from its table entry and
    builds the real one (importing its module) when it is resolved, i.e. run or asked for
    its help."""

    def list_commands(self, ctx) -> list[str]:
        return [*super().list_commands(ctx), *(n for n in COMMANDS if n not in self.commands)]

    def get_command(self, ctx, cmd_name: str):
        cmd = super().get_command(ctx, cmd_name)
        if cmd is None and cmd_name in COMMANDS:  # for the listing only
            from typer.core import TyperCommand

            cmd = TyperCommand(cmd_name, help=COMMANDS[cmd_name][0])
        return cmd

    def resolve_command(self, ctx, args):
        if args and args[0] in COMMANDS and args[0] not in self.commands:
            self.load(args[0])
        try:
            return super().resolve_command(ctx, args)
        except typer._click.exceptions.UsageError as e:  # a typo: suggest from every command
            from difflib import get_close_matches

            near = get_close_matches(args[0], self.list_commands(ctx)) if args else []
            if near and "Did you mean" not in e.message:
                e.message = f"{e.message.rstrip('.')}. Did you mean {', '.join(map(repr, near))}?"
            raise

    def load(self, cmd_name: str) -> None:
        """Build the commands that ``cmd_name``'s register function adds, and keep them."""
        module, func = COMMANDS[cmd_name][1].split(":")
        sub = typer.Typer()
        getattr(importlib.import_module(module), func)(sub)
        built = typer.main.get_group(sub)
        for name, cmd in built.commands.items():
            self.commands.setdefault(name, cmd)


app = typer.Typer(
    name="armfusion",
    cls=LazyCommands,
    help="Absolute joint angles of a robot arm with relative encoders, from gravity: "
    "startup calibration, tracking, sensor calibration and model diagnosis.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def version_callback(value: bool) -> None:
    if value:
        console.print(f"armfusion {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[bool | None, typer.Option("--version", callback=version_callback,
                                                 is_eager=True, help="Print the version.")] = None,
) -> None:
    """armfusion: where are the joints of an arm whose encoders are only relative?"""


# --------------------------------------------------------------------------------------
PLOT_SUFFIXES = (".png", ".svg", ".pdf")
"""What ``info --plot`` draws to (matplotlib's formats that need nothing else)."""


@app.command()
def info(
    config: ConfigOpt = "wmra",
    json_out: JsonOpt = False,
    plot: Annotated[Path | None, typer.Option(help="Also draw the arm at its ready pose to this PNG.")] = None,
    urdf: Annotated[Path | None, typer.Option(help="Also write the arm's URDF (its joints and sensor frames, for robot_state_publisher: docs/ros2.md).")] = None,
) -> None:
    """Print the arm: its joints, its sensors, and which joints each sensor sees."""

    from armfusion.fusion.cli.describe import describe_arm

    if plot is not None:
        check_output_path(plot, "--plot", suffixes=PLOT_SUFFIXES, inputs=_config_inputs(config))
    if urdf is not None:
        check_output_path(urdf, "--urdf", suffixes=(".urdf",), inputs=_config_inputs(config))
    arm = load_arm_or_exit(config)
    d = describe_arm(arm)
    if plot is not None:
        from armfusion.fusion.cli.plots import plot_arm

        try:
            plot_arm(arm, arm.ready_pose_rad, plot)
        except OSError as e:
            fail(f"--plot {plot}: cannot write the drawing: {e.strerror or e}")
        d["plot"] = str(plot)
    if urdf is not None:
        from armfusion.fusion.ros2.urdf import urdf_from_arm

        try:
            urdf.write_text(urdf_from_arm(arm), encoding="utf-8")
        except OSError as e:
            fail(f"--urdf {urdf}: cannot write the URDF: {e.strerror or e}")
        d["urdf"] = str(urdf)
    if json_out:
        emit_json(d)
        return
    console.print(f"[bold]{arm.name}[/]  ({d['dh_convention']} DH, {arm.n_joints} joints)  "
                  f"from {arm.source}")
    t = _table("Joints", ("joint",), ("alpha [deg]", "a [mm]", "d [mm]", "offset [deg]", "limits [deg]",
                                     "ready [deg]", "counts/rev", "vertical at ready"))
    for j in d["joints"]:
        t.add_row(j["name"], _f(j.get("alpha_deg")), _f(j.get("a_mm")), _f(j.get("d_mm")),
                  _f(j.get("offset_deg")), f"{j['min_deg']:.0f} … {j['max_deg']:.0f}",
                  f"{j['ready_deg']:.0f}", f"{j['counts_per_rev']:.0f}",
                  "[red]yes: gravity-blind[/]" if j["vertical_at_ready"] else "no")
    console.print(t)
    t = _table("Sensors", ("sensor", "type", "link", "position [mm]", "bus", "sees joints", "unmodelled [g]"))
    for s in d["sensors"]:
        t.add_row(s["name"], s["type"], str(s["link"]),
                  ", ".join(f"{v:.1f}" for v in s["position_mm"]), s["bus"] or "-",
                  ", ".join(s["sees_joints"]) or "none (base)",
                  "-" if s["unmodelled_g"] is None else
                  f"{s['unmodelled_g']:g}" + (" (its class's)" if s["unmodelled_from"] == "class" else ""))
    console.print(t)
    b = d["base"]
    if b != "moving":
        tilt = ("level" if b["roll_deg"] is None else f"roll {b['roll_deg']:g}°, pitch {b['pitch_deg']:g}°")
        console.print(f"Base: fixed (bolted down), {tilt} ± {b['tilt_sigma_deg']:g}°")
    if d["effects"]:
        console.print("Effects in the model: " + ", ".join(
            f"{e['effect']}" + (f":{e['target']}" if e["target"] else "") for e in d["effects"]))
    if plot is not None:
        console.print(f"Drawing written to {plot}")
    if urdf is not None:
        console.print(f"URDF written to {urdf}")


def _table(title: str, left: tuple[str, ...], right: tuple[str, ...] = ()):
    """A rich table titled ``title``: the ``left`` columns, then the ``right``-justified ones
    (their names taken as text: "[deg]" is not markup)."""
    from rich.markup import escape
    from rich.table import Table

    t = Table(title=title, title_justify="left")
    for col in left:
        t.add_column(escape(col))
    for col in right:
        t.add_column(escape(col), justify="right")
    return t


def _f(v) -> str:
    return "-" if v is None else f"{v:g}"


def _config_inputs(config: str) -> tuple[Path | None, ...]:
    """The files a config is read from: its YAML and the URDF it names (``arm.urdf``), which no
    output may replace (``info --urdf`` had written over the config's own URDF)."""
    from armfusion.fusion.configfile import read_yaml

    path = config_file(config)
    try:
        named = read_yaml(path)["arm"]["urdf"] if path is not None else None
    except (ValueError, KeyError, TypeError):
        named = None
    return (path, (path.parent / named) if isinstance(named, str) else None)


# --------------------------------------------------------------------------------------
@app.command()
def inspect(
    recording: RecordingArg,
    json_out: JsonOpt = False,
    window_s: Annotated[float, typer.Option(help="Still-detection window [s].",
                                            callback=window_seconds("--window-s"))] = 1.0,
) -> None:
    """Summarise a recording: sensors, samples and rate each, duration, gaps, still segments."""

    from armfusion.fusion.cli.describe import describe_recording
    from armfusion.fusion.startup.static import StaticDetectionSettings

    rec = read_recording_or_exit(recording)
    window_holds_samples(rec, window_s)
    d = describe_recording(rec, StaticDetectionSettings(window_s=window_s))
    d["path"] = str(recording)
    if json_out:
        emit_json(d)
        return
    console.print(f"[bold]{recording}[/]: {d['duration_s']:.2f} s, "
                  f"t = {d['t_start_s']:.3f} … {d['t_end_s']:.3f} s")
    if d.get("read_report"):
        console.print(f"[yellow]{d['read_report']}[/]")
    t = _table("Streams", ("stream", "kind", "channels"),
               ("samples", "rate [Hz]", "gaps (missing)", "longest gap [s]"))
    for s in d["streams"]:
        t.add_row(s["name"], s["kind"], ", ".join(s["channels"]), str(s["samples"]),
                  f"{s['rate_hz']:.1f}",
                  f"{s['gaps']} ({s['missing_samples']})" if s["gaps"] else "0",
                  f"{s['longest_gap_s']:.3f}")
    console.print(t)
    segs = d["static_segments"]
    if segs:
        t = _table(f"Still segments ({len(segs)})", (), ("#", "start [s]", "end [s]", "duration [s]"))
        for i, s in enumerate(segs):
            t.add_row(str(i), f"{s['t_start_s']:.2f}", f"{s['t_end_s']:.2f}",
                      f"{s['duration_s']:.2f}")
        console.print(t)
    else:
        console.print("No still segment found.")


def run() -> None:  # pragma: no cover - console entry
    app()


if __name__ == "__main__":  # pragma: no cover
    app()
