"""The ``armfusion`` command line.

Every command that computes something takes ``--json`` and then prints exactly one JSON
document on stdout (see docs/cli.md). Errors go to stderr as one clear message, exit 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from fusion import __version__
from fusion.cli_common import (  # noqa: F401  (re-exported for the command modules)
    ConfigOpt,
    JsonOpt,
    console,
    emit_json,
    err_console,
    fail,
    json_default,
    load_arm_or_exit,
    read_recording_or_exit,
)

app = typer.Typer(
    name="armfusion",
    help="Absolute joint angles of a robot arm with relative encoders, from gravity: "
    "startup calibration, tracking, sensor calibration and model diagnosis.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
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
@app.command()
def info(
    config: ConfigOpt = "wmra",
    json_out: JsonOpt = False,
    plot: Annotated[Path | None, typer.Option(help="Also draw the arm at its ready pose to this PNG.")] = None,
) -> None:
    """Print the arm: its joints, its sensors, and which joints each sensor sees."""
    from fusion.describe import describe_arm

    arm = load_arm_or_exit(config)
    d = describe_arm(arm)
    if plot is not None:
        from fusion.plots import plot_arm

        plot_arm(arm, arm.ready_pose_rad, plot)
        d["plot"] = str(plot)
    if json_out:
        emit_json(d)
        return
    console.print(f"[bold]{arm.name}[/]  ({d['dh_convention']} DH, {arm.n_joints} joints)  "
                  f"from {arm.source}")
    t = Table(title="Joints", title_justify="left")
    for col in ("joint", "alpha [deg]", "a [mm]", "d [mm]", "offset [deg]", "limits [deg]",
                "ready [deg]", "counts/rev", "vertical at ready"):
        t.add_column(col, justify="right" if col != "joint" else "left")
    for j in d["joints"]:
        t.add_row(j["name"], _f(j.get("alpha_deg")), _f(j.get("a_mm")), _f(j.get("d_mm")),
                  _f(j.get("offset_deg")), f"{j['min_deg']:.0f} … {j['max_deg']:.0f}",
                  f"{j['ready_deg']:.0f}", f"{j['counts_per_rev']:.0f}",
                  "[red]yes: gravity-blind[/]" if j["vertical_at_ready"] else "no")
    console.print(t)
    t = Table(title="Sensors", title_justify="left")
    for col in ("sensor", "type", "link", "position [mm]", "bus", "sees joints"):
        t.add_column(col)
    for s in d["sensors"]:
        t.add_row(s["name"], s["type"], str(s["link"]),
                  ", ".join(f"{v:.1f}" for v in s["position_mm"]), s["bus"] or "-",
                  ", ".join(s["sees_joints"]) or "none (base)")
    console.print(t)
    if d["effects"]:
        console.print("Effects in the model: " + ", ".join(
            f"{e['effect']}" + (f":{e['target']}" if e["target"] else "") for e in d["effects"]))
    if plot is not None:
        console.print(f"Drawing written to {plot}")


def _f(v) -> str:
    return "-" if v is None else f"{v:g}"


# --------------------------------------------------------------------------------------
@app.command()
def inspect(
    recording: Annotated[Path, typer.Argument(help="Recording: .csv (shared spec) or .mcap.")],
    json_out: JsonOpt = False,
    window_s: Annotated[float, typer.Option(help="Still-detection window [s].")] = 1.0,
) -> None:
    """Summarise a recording: sensors, samples and rate each, duration, gaps, still segments."""
    from fusion.describe import describe_recording
    from fusion.static import StaticDetectionSettings

    rec = read_recording_or_exit(recording)
    d = describe_recording(rec, StaticDetectionSettings(window_s=window_s))
    d["path"] = str(recording)
    if json_out:
        emit_json(d)
        return
    console.print(f"[bold]{recording}[/]: {d['duration_s']:.2f} s, "
                  f"t = {d['t_start_s']:.3f} … {d['t_end_s']:.3f} s")
    if d.get("read_report"):
        console.print(f"[yellow]{d['read_report']}[/]")
    t = Table(title="Streams", title_justify="left")
    for col in ("stream", "kind", "channels", "samples", "rate [Hz]", "gaps (missing)",
                "longest gap [s]"):
        t.add_column(col, justify="right" if col in ("samples", "rate [Hz]", "gaps (missing)",
                                                     "longest gap [s]") else "left")
    for s in d["streams"]:
        t.add_row(s["name"], s["kind"], ", ".join(s["channels"]), str(s["samples"]),
                  f"{s['rate_hz']:.1f}",
                  f"{s['gaps']} ({s['missing_samples']})" if s["gaps"] else "0",
                  f"{s['longest_gap_s']:.3f}")
    console.print(t)
    segs = d["static_segments"]
    if segs:
        t = Table(title=f"Still segments ({len(segs)})", title_justify="left")
        for col in ("#", "start [s]", "end [s]", "duration [s]"):
            t.add_column(col, justify="right")
        for i, s in enumerate(segs):
            t.add_row(str(i), f"{s['t_start_s']:.2f}", f"{s['t_end_s']:.2f}",
                      f"{s['duration_s']:.2f}")
        console.print(t)
    else:
        console.print("No still segment found.")


def _register_subcommands() -> None:
    from fusion import (
        identify_cmd,  # noqa: F401 - registers `calibrate sensors`
        simulate_cmd,
    )
    from fusion.calibrate_cmd import calibrate_app
    from fusion.drivers_cmd import register as register_drivers

    simulate_cmd.register(app)
    register_drivers(app)
    from fusion.service.commands import register as register_service; register_service(app)  # noqa: E702, I001
    from fusion.diagnose_cmd import register as register_diagnose; register_diagnose(app)  # noqa: E702, I001
    from fusion.track_cmd import register as register_track; register_track(app)  # noqa: E702, I001
    app.add_typer(calibrate_app, name="calibrate")


if __name__ != "__main__":  # `python -m fusion.cli` registers through the real module below
    _register_subcommands()


def run() -> None:  # pragma: no cover - console entry
    app()


if __name__ == "__main__":  # pragma: no cover
    from fusion.cli import app as registered_app

    registered_app()
