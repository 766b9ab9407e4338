"""`armfusion import`: a foreign recording (CSV with a header, MATLAB .mat v5, HDF5) turned into
the arm's native recording by a column map (fusion/importing; docs/cli.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from armfusion.fusion.cli.common import (
    config_file,
    console,
    emit_json,
    err_console,
    fail,
    load_arm_or_exit,
    prepare_output_path,
)
from armfusion.fusion.cli.options import ConfigOpt, JsonOpt, RecordingOutOpt

OUT_SUFFIXES = (".csv", ".mcap")


def register(app: typer.Typer) -> None:
    """Add ``import`` to the ``armfusion`` app (once)."""
    if any(c.name == "import" for c in app.registered_commands):
        return
    app.command("import")(import_recording_cmd)


def import_recording_cmd(
    source: Annotated[Path, typer.Argument(help="The foreign recording: .csv (a header row of names), .mat (MATLAB v5), .h5/.hdf5, or a ROS bag (a rosbag2 directory, .mcap, .db3; ROS 1 .bag).")],
    column_map: Annotated[str, typer.Option("--map", "-m", help="Column map (YAML): a path, or a shipped one by name (imu-rig, broad, ros2-wmra).")],
    out: RecordingOutOpt,
    config: ConfigOpt = "wmra",
    json_out: JsonOpt = False,
) -> None:
    """Turn a foreign recording (CSV, MATLAB .mat, HDF5, a ROS bag) into the arm's native one: each stream
    from the columns the map names, in the unit the config declares; rows whose time does not increase dropped, NaN kept
    as gaps, every change said."""
    from armfusion.fusion.importing.bag import import_bag
    from armfusion.fusion.importing.column_map import ColumnMapError, load_column_map
    from armfusion.fusion.importing.run import import_recording
    from armfusion.models.arm_config import ConfigError
    from armfusion.sensors.foreign.rosbag import is_bag
    from armfusion.sensors.recording import write_recording

    out = prepare_output_path(out, "--out", OUT_SUFFIXES,
                              inputs=(source, config_file(config), Path(column_map)))
    if not source.exists():
        fail(f"recording not found: {source}")
    try:
        cmap = load_column_map(column_map)
    except (ColumnMapError, FileNotFoundError, ConfigError) as e:
        fail(str(e))
    arm = load_arm_or_exit(config)
    try:
        result = (import_bag if is_bag(source) else import_recording)(source, cmap, arm, config)
    except (ValueError, OSError) as e:
        said = str(e)  # (the import's messages name the file first: not twice)
        fail(f"cannot import {said}" if said.startswith(f"{source}: ") else f"cannot import {source}: {said}")
    try:
        write_recording(result.recording, out)
    except (ValueError, OSError) as e:
        fail(f"--out {out}: cannot write the recording: {e}")
    summary = {**result.summary, "out": str(out)}
    if json_out:
        emit_json(summary)
        _exit_if_lost(result.lost, out)
        return
    if "topics" in summary:  # a bag: each topic's messages, rate and gaps, as inspect says them
        console.print(f"[bold]{source}[/] -> {out}: t = {summary['time']['t_start_s']:.3f} … "
                      f"{summary['time']['t_end_s']:.3f} s", highlight=False, soft_wrap=True)
        for topic, r in summary["topics"].items():
            gaps = f"{r['gaps']} gaps ({r['missing_samples']} missing)" if r["gaps"] else "no gap"
            console.print(f"  {topic} ({r['type']}, frame {', '.join(r['frame_ids']) or '-'}): "
                          f"{r['messages']} messages, {r['rate_hz']:.1f} Hz by its {r['stamp']} stamp, "
                          f"{gaps}", highlight=False, soft_wrap=True)
    else:
        rows = summary["rows"]
        console.print(f"[bold]{source}[/] -> {out}: {rows['imported']} of {rows['in_file']} rows, "
                      f"t = {summary['time']['t_start_s']:.3f} … {summary['time']['t_end_s']:.3f} s",
                      highlight=False, soft_wrap=True)
    for name, s in summary["streams"].items():
        gaps = f", {s['nan_gaps'] + s['partly_nan']} gaps" if s["nan_gaps"] + s["partly_nan"] else ""
        console.print(f"  {name} ({s['kind']}): {s['samples']} samples, {', '.join(s['columns'])}: "
                      f"{s['conversion']}{gaps}", highlight=False, soft_wrap=True)
    for name, why in summary["absent"].items():
        console.print(f"  {name}: absent ({why})", highlight=False)
    if summary["not_mapped"]:
        console.print(f"  not in the file: {', '.join(summary['not_mapped'])}", highlight=False)
    if summary["changes"]:
        console.print("Changes to the source's data:")
        for c in summary["changes"]:
            console.print(f"  - {c}", highlight=False, soft_wrap=True)
    else:
        console.print("No change to the source's data (every row kept, no gap, nothing rounded).")
    _exit_if_lost(result.lost, out)


def _exit_if_lost(lost: int, out: Path) -> None:
    """Exit 1 where the import left out, for its time, a row that was not a copy of the one
    before (named in its changes): samples lost; what it wrote holds the rest, as ``replay``
    exits 1 having sent what it could read."""
    if lost:
        err_console.print(f"exit 1: {lost} row(s) left out for their time were not copies of the row "
                          f"before (named above): samples lost; {out} holds the rest",
                          highlight=False, soft_wrap=True)
        raise typer.Exit(1)
