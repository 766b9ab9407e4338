"""``armfusion plan-maneuver``: the self-calibration maneuver that makes the identification's
parameters best known in the time given, and the σ they (and each joint's startup) will have.

    armfusion plan-maneuver --config wmra [--duration 60] [--out M.yaml] [--effects all]
        [--criterion D|E|startup] [--focus all|startup] [--seed 0] [--dwells 1,1.5,2,3] [--json]

Writes ``M.yaml``: the poses (degrees), each one's move time and dwell, the settings the plan
kept to (joint limits, the unlock move's largest move, peak joint rate, tool speed), and the
prediction: every element's σ after the maneuver (held ones named), each joint's startup σ.
``armfusion simulate --maneuver M.yaml`` plays it; on a real chair the arm's controller does
(armfusion never moves the arm), and ``calibrate sensors`` fits the recording.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
import yaml
from armfusion.fusion.cli.common import check_output_path, config_file, console, emit_json, fail, progress_bar
from armfusion.fusion.cli.options import ConfigOpt, JsonOpt
from armfusion.fusion.configfile import load_arm, read_yaml, resolve_config_path
from armfusion.fusion.identification.planner import (
    CRITERIA,
    FOCUS,
    PlanSettings,
    maneuver_problems,
    plan_maneuver,
    predict_maneuver,
)
from armfusion.models.arm_config import ConfigError
from armfusion.sensors.output_files import write_text_replacing


def run_plan(config: str | Path, settings: PlanSettings | None = None, effects: str | None = "all",
             startup_poses: int = 64, progress=None) -> dict[str, Any]:
    """Plan, check, predict: the maneuver file's content (``maneuver`` is the plan itself).

    ``settings``: the planner's (length, criterion, focus, seed, candidates, dwells; ``None``:
    its defaults); ``effects``: the effects to calibrate, as ``calibrate sensors --effects``;
    ``startup_poses``: the random still poses the startup's predicted σ is the median over;
    ``progress(fraction_done, stage)`` follows the work."""
    from armfusion.fusion.cli.calibrate_sensors import build_model

    arm = load_arm(config)
    st = PlanSettings() if settings is None else settings
    st.check()
    model = build_model(arm, effects)
    say = progress or (lambda _f, _m=None: None)
    plan = plan_maneuver(model, st, progress=lambda f: say(0.7 * f, "planning"))
    problems = maneuver_problems(arm, plan.maneuver, st)
    if problems:  # the planner keeps to the checks by construction: this would be a bug
        raise RuntimeError("the plan fails its own checks: " + "; ".join(problems))
    say(0.7, "predicting")
    cfg = read_yaml(resolve_config_path(config))
    pred = predict_maneuver(model, plan.maneuver, cfg, poses=startup_poses)
    say(1.0, "done")
    ident = pred.identification
    held = [n for n, h in zip(ident.names, ident.held, strict=True) if h]
    return {
        **plan.maneuver.as_dict(),
        "config": arm.source, "arm": arm.name, "duration_s": round(plan.maneuver.duration_s, 3),
        "plan": {"criterion": f"{st.criterion}-optimal", "focus": st.focus, "seed": st.seed,
                 "candidates_scored": plan.candidates_scored,
                 "gauges_left_out": list(plan.gauges),
                 "checks": {"joint_limits": "every pose inside [min_deg, max_deg]",
                            "max_move_deg": st.max_move_deg, "peak_rate_deg_s": st.peak_rate_deg_s,
                            "max_tool_speed_mps": st.max_tool_speed_mps, "chair": "parked"},
                 "dwell_choices_s": list(st.dwell_choices_s) or [st.dwell_s]},
        "predicted": {
            "note": "the fit's sigma at the priors (identifiability analysis and consider covariance as "
                    "calibrate sensors computes them; a stream fitted worse than its noise would scale "
                    "its elements' sigma); the startup's: median sigma of its ok answers at "
                    f"{startup_poses} random still poses on the config that fit would write, at 25 C, the "
                    "chair tilted N(0, 3 deg), a saved pose 10 deg off as the prior",
            "elements": [{"name": n, "sigma": float(f"{s:.4g}"), "prior_sigma": float(f"{p:.4g}"),
                          "held": bool(h)}
                         for n, s, p, h in zip(ident.names, ident.sigma, ident.prior_sigma, ident.held,
                                               strict=True)],
            "held": held,
            "startup": [{"joint": j, "sigma_deg": None if not np.isfinite(s) else round(float(np.degrees(s)), 4),
                         "ok_share": round(float(o), 3)}
                        for j, s, o in zip(arm.joint_names, pred.joint_sigma_rad, pred.joint_ok_share,
                                           strict=True)],
        },
    }


def plan_command(
    config: ConfigOpt = "wmra",
    duration: Annotated[float, typer.Option("--duration", help="The maneuver's length [s].")] = 60.0,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write the maneuver file (YAML).")] = None,
    effects: Annotated[str, typer.Option("--effects", help="The effects to calibrate, as calibrate "
                                         "sensors --effects (default all).")] = "all",
    criterion: Annotated[str, typer.Option("--criterion", help="D (log det of the information), "
                                           "E (its smallest eigenvalue) or startup (the joints' "
                                           "linearised startup variances).")] = "D",
    focus: Annotated[str, typer.Option("--focus", help="all: every element but the gauges; startup: "
                                       "those the startup uses.")] = "all",
    seed: Annotated[int, typer.Option("--seed", help="The candidates' seed.")] = 0,
    dwells: Annotated[str, typer.Option("--dwells", help="The dwells each pose may be held [s], "
                                        "e.g. 1,1.5,2,3 (default: every pose 2 s).")] = "",
    json_out: JsonOpt = False,
) -> None:
    """Plan the self-calibration maneuver: poses, dwells and safe moves that make the fit's
    parameters best known in the time given; the sigma each parameter and each joint's
    startup will have after it."""
    if out is not None:
        check_output_path(out, "--out", (".yaml", ".yml"), inputs=(config_file(config),))
    if criterion not in CRITERIA:
        fail(f"--criterion must be one of {', '.join(CRITERIA)}, not {criterion[:20]!r}")
    if focus not in FOCUS:
        fail(f"--focus must be one of {', '.join(FOCUS)}, not {focus[:20]!r}")
    try:
        dwells_s = tuple(float(v) for v in dwells.split(",") if v.strip())
        PlanSettings(dwell_choices_s=dwells_s).check()
    except ValueError as e:
        fail(f"--dwells: expected seconds separated by commas, got {dwells[:30]!r} ({str(e)[:80]})")
    try:
        with progress_bar("planning", json_out) as advance:
            settings = PlanSettings(duration_s=duration, criterion=criterion, focus=focus, seed=seed,
                                    dwell_choices_s=dwells_s)
            doc = run_plan(config, settings, effects, progress=advance)
    except (ConfigError, FileNotFoundError, ValueError) as e:
        fail(str(e))
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_text_replacing(out, "# armfusion plan-maneuver: play with `armfusion simulate --maneuver "
                       f"{out.name}` or on the arm's controller\n"
                       + yaml.safe_dump(doc, sort_keys=False, width=110))
    if json_out:
        emit_json({**doc, "out": None if out is None else str(out)})
        return
    _print_plan(doc, focus, out)


COMMAND_TABLE = (
    ("plan-maneuver", plan_command),
)
"""The planner's command: each command's name and its function."""


def register(app: typer.Typer) -> None:
    """Add the commands of :data:`COMMAND_TABLE` to ``app``."""
    for name, command in COMMAND_TABLE:
        app.command(name)(command)


def _print_plan(doc: dict, focus: str, out: Path | None) -> None:
    """The plan as a table of poses, the predicted sigmas, and where it was written."""
    from rich.table import Table

    t = Table(title=f"{len(doc['poses'])} poses, {doc['duration_s']:.1f} s ({doc['plan']['criterion']}, "
              f"focus {focus})", title_justify="left")
    t.add_column("pose")
    t.add_column("move [s]", justify="right")
    t.add_column("dwell [s]", justify="right")
    t.add_column("joints [deg]")
    for k, p in enumerate(doc["poses"]):
        t.add_row(str(k), f"{p['move_s']:.1f}", f"{p['dwell_s']:.1f}", " ".join(f"{v:7.1f}" for v in p["pose_deg"]))
    console.print(t)
    pr = doc["predicted"]
    n_free = sum(not e["held"] for e in pr["elements"])
    console.print(f"Predicted: {n_free} elements estimated, {len(pr['held'])} held at their priors "
                  f"({', '.join(pr['held'][:5])}{', …' if len(pr['held']) > 5 else ''}).")
    console.print("Startup sigma after it (median over ok poses): " + ", ".join(
        f"{s['joint']} {'flagged' if s['sigma_deg'] is None else format(s['sigma_deg'], '.3f') + '°'}"
        for s in pr["startup"]))
    if out is not None:
        console.print(f"Wrote {out}")
