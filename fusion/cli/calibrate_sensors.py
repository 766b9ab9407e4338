"""``armfusion calibrate sensors``: the arm calibrates its own sensors from a recording.

    armfusion calibrate sensors --config wmra REC.csv [--mode separate|simultaneous]
        [--effects accel_bias,mount_rotation|all] [--window 25] [--json] [--write C2.yaml]
        [--base-tilt ROLL,PITCH] [--reference j7=0[:0.05][@T|@segK] ...]

Estimates every effect the config lists (or ``--effects`` names; with neither, the whole
library) plus the recording's encoder zeros and the base attitude; reports each parameter
with its σ, what was held and why (and the motion that would separate it), correlated
pairs, and the fit RMS per stream axis against the noise. ``--write`` saves a config with
the estimates and their σ and the unmodelled-error floor lowered to what the fit leaves.
A chair parked in several stances (``renk-ramp``) gets one base attitude per stance.
``--reference`` gives a joint's true angle once (a mechanical index, a pose the installer
confirms): it pins what gravity cannot (the last joint's zero against the last sensor's mount
about its axis; the first joint's against the IMU's mount), is checked against the rest of
the fit (a contradiction writes nothing) and is recorded in the written config.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
import yaml
from armfusion.fusion.cli.common import (
    arm_and_recording_or_exit,
    check_output_path,
    choice_or_exit,
    config_file,
    console,
    emit_json,
    err_console,
    fail,
    progress_bar,
    read_recording_or_exit,
    screen_or_exit,
)
from armfusion.fusion.cli.options import ConfigOpt, JsonOpt, WriteConfigOpt, count_at_least
from armfusion.fusion.configfile import resolve_config_path
from armfusion.fusion.identification.identify import (
    REFERENCE_SIGMA_RAD,
    IdentifySettings,
    config_with_estimates,
    data_from_recording,
    fit_streams,
    identify_recentred,
    identify_separately,
    joint_references,
    with_encoder_zeros,
)
from armfusion.models.effects import EFFECTS, Model, all_effects, model_from_arm
from armfusion.models.effects.library import MagHardIron, MagSoftIron
from armfusion.models.simulator import REALISTIC_EXCLUDE, drawn_by_default
from armfusion.sensors.output_files import write_text_replacing
from rich.table import Table


def parse_base_tilt(text: str, sigma_deg: float) -> tuple[np.ndarray, float]:
    """``"ROLL,PITCH"`` (degrees) and its σ (degrees) as the fit's base tilt reference (rad)."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 2 or not all(np.isfinite(vals)) or max(abs(v) for v in vals) >= 90:
        raise ValueError(f"--base-tilt: give ROLL,PITCH in degrees (within ±90), e.g. 0.4,-4.9; got {text!r}")
    if not (np.isfinite(sigma_deg) and sigma_deg > 0):
        raise ValueError(f"--base-tilt-sigma must be a positive number of degrees, got {sigma_deg!r}")
    return np.radians(vals), float(np.radians(sigma_deg))


def parse_reference(text: str) -> tuple[str, float, float, float | int | None]:
    """``JOINT=DEG[:SIGMA_DEG][@WHEN]`` as ``(joint, angle_rad, sigma_rad, when)``: WHEN a time
    in seconds on the recording's clock (``@12.5``) or its k-th still segment (``@seg2``);
    without it, the first still segment. σ defaults to 0.05° (a mechanical index)."""
    shown = text if len(text) <= 40 else text[:40] + "…"
    usage = (f"--reference: give JOINT=DEG[:SIGMA_DEG][@SECONDS|@segK], e.g. j7=0 or "
             f"j1=90:0.1@seg2; got {shown!r}")
    head, _, when_text = text.partition("@")
    joint, eq, value = head.partition("=")
    angle_text, _, sigma_text = value.partition(":")
    joint = joint.strip()
    if not eq or not joint or not angle_text.strip():
        raise ValueError(usage)
    try:
        angle = float(angle_text)
        sigma = float(sigma_text) if sigma_text.strip() else float(np.degrees(REFERENCE_SIGMA_RAD))
    except ValueError:
        raise ValueError(usage) from None
    if not (np.isfinite(angle) and np.isfinite(sigma)):
        raise ValueError(usage)
    when: float | int | None = None
    w = when_text.strip()
    if "@" in text:
        try:
            when = int(w[3:]) if w.lower().startswith("seg") else float(w)
        except ValueError:
            raise ValueError(usage) from None
        if isinstance(when, float) and not np.isfinite(when):
            raise ValueError(usage)
    return joint, float(np.radians(angle)), float(np.radians(sigma)), when


def build_model(arm, effects: str | None) -> Model:
    """The config's effects, or ``effects`` (comma separated names, or ``all``), plus the
    encoder zeros."""
    if effects:
        names = list(EFFECTS) if effects.strip() == "all" else [e.strip() for e in effects.split(",") if e.strip()]
        bad = [n for n in names if n not in EFFECTS]
        if bad:
            raise ValueError(f"--effects: unknown effect(s) {', '.join(bad)}; known: {', '.join(EFFECTS)}")
        model = Model(arm, [e for e in all_effects(arm, names) if drawn_by_default(e) or
                            (effects.strip() != "all" and e.block_name not in REALISTIC_EXCLUDE)])
    else:
        model = model_from_arm(arm)
        if not model.effects:
            model = Model(arm, [e for e in all_effects(arm) if drawn_by_default(e)])
    return with_encoder_zeros(model)


def calibrate_sensors(
    recording: Annotated[Path, typer.Argument(help="Recording (.csv or .mcap) of the arm moving "
                                              "through many orientations (e.g. renk-maneuver).")],
    config: ConfigOpt = "wmra",
    mode: Annotated[str, typer.Option(help="simultaneous (one gravity direction) or separate "
                                      "(each sensor alone, its own gravity direction).")] = "simultaneous",
    effects: Annotated[str | None, typer.Option(help="Effects to estimate, comma separated, or "
                                                "'all' (default: the config's, else all).")] = None,
    window: Annotated[int, typer.Option(help="Average this many samples per fit point.",
                                        callback=count_at_least("--window", 1, "samples per fit point"))] = 25,
    stances: Annotated[bool, typer.Option(help="Find where the chair stands parked (the IMU's gyro and "
                                          "accelerometer) and fit each stance's own base attitude, "
                                          "leaving out the moves between them (a maneuver on a "
                                          "ramp: renk-ramp); a chair that never moves is one "
                                          "stance.")] = True,
    base_tilt: Annotated[str | None, typer.Option(help="ROLL,PITCH in degrees: the arm base's tilt in "
                                                  "the first stance, read by an inclinometer on the "
                                                  "base (R = Rz Ry Rx). Pins the IMU's mount about "
                                                  "the first joint's axis, which no maneuver can.")] = None,
    base_tilt_sigma: Annotated[float, typer.Option(help="The inclinometer's σ, degrees.")] = 0.05,
    reference: Annotated[list[str] | None, typer.Option(
        "--reference", help="JOINT=DEG[:SIGMA_DEG][@SECONDS|@segK], repeatable: the joint's true "
        "geometric angle while the arm stands still (at a mechanical index, or a pose the installer "
        "confirms), default σ 0.05°, default the recording's first still segment. Pins what no "
        "maneuver can: j7's zero against the last sensor's mount about its axis, j1's against the "
        "IMU's mount (or use --base-tilt). Checked against the data; recorded in the written "
        "config.")] = None,
    compass_drive: Annotated[Path | None, typer.Option(
        "--compass-drive", help="A recording (.csv or .mcap) of the chair driving and turning (one "
        "turn on the spot will do): after the fit, the tracker learns the compass's hard and soft "
        "iron from its turns (which a parked maneuver cannot see), and the written config holds "
        "them with their σ.")] = None,
    json_out: JsonOpt = False,
    write: WriteConfigOpt = None,
) -> None:
    """Estimate the sensors' and the arm's effects (with σ, holds and correlations)."""
    choice_or_exit(mode, "--mode", ("separate", "simultaneous"))
    if write is not None:
        check_output_path(write, "--write", inputs=(recording, config_file(config), compass_drive))
    arm, rec, screen = arm_and_recording_or_exit(
        config, recording, fit_streams,
        "calibrate sensors fits (the encoders and every sensor stream of {source})", json_out,
        encoder_steps=True)
    # the drive read before the fit, not after a minute of it (/dev/zero, a FIFO, a damaged file)
    drive_rec = read_recording_or_exit(compass_drive, arm) if compass_drive is not None else None
    fit = FitOptions(mode, effects, window, stances, base_tilt, base_tilt_sigma, tuple(reference or ()))
    model, data = _model_and_data(arm, rec, fit)
    if not json_out:
        err_console.print(f"fitting {model.size} parameters on {data.n:,} points ({data.note})…")
    settings = IdentifySettings(encoder_scale=True)
    if mode == "separate":
        with progress_bar("fitting", json_out) as advance:
            groups = len(arm.link_accelerometers) + (arm.imu is not None)  # one fit each
            fits = identify_separately(model, data, settings, _jacobians(advance, groups))
        if json_out:
            emit_json({k: v.as_dict() for k, v in fits.items()})
            return
        _print_separate(fits)
        return
    with progress_bar("fitting", json_out) as advance:
        res, data = identify_recentred(model, data, None, settings, _jacobians(advance))
    bad = res.references_contradicted
    if bad:  # the installer's claim and the data disagree: nothing written, nothing to trust
        if json_out:
            d = res.as_dict()
            d["written"] = None
            emit_json(d)
        fail("; ".join(c.message() for c in bad)
             + (f". {write} not written" if write is not None else ""))
    compass_line = None
    src = resolve_config_path(config)
    out = config_with_estimates(yaml.safe_load(src.read_text(encoding="utf-8")), res)
    if compass_drive is not None:
        out, compass_line = _with_compass_from_drive(out, compass_drive, drive_rec, json_out)
    if write is not None:
        _write_config(write, res, out, f"# {res.summary()}\n# from {recording}, config {src.name}\n",
                      compass_line)
    if json_out:
        d = res.as_dict()
        d["written"] = str(write) if write else None
        d["compass_drive"] = compass_line
        d["saturated_left_out"] = {"samples": screen.as_dict()["saturated"],
                                   "windows": data.saturated_windows}
        emit_json(d)
        return
    _print(res, write)
    if compass_line:
        console.print(compass_line)


@dataclass(frozen=True)
class FitOptions:
    """What ``calibrate sensors`` is told besides the recording: the fit's ``mode``
    (``simultaneous`` or ``separate``), the ``effects`` to fit (``--effects``; ``None``: the
    config's, else all), ``window`` samples averaged per fit point, the chair's ``stances``
    fitted each with its own base attitude; and the installer's one-time references: the
    base's tilt ``base_tilt`` (``"ROLL,PITCH"`` in degrees, ``None``: none) read by an
    inclinometer of σ ``base_tilt_sigma_deg``, and the joints' angles ``references``
    (``--reference`` specs)."""

    mode: str = "simultaneous"
    effects: str | None = None
    window: int = 25
    stances: bool = True
    base_tilt: str | None = None
    base_tilt_sigma_deg: float = 0.05
    references: tuple[str, ...] = ()


def _model_and_data(arm, rec, fit: FitOptions) -> tuple:
    """The model of the effects to fit and the fit's data (with the base tilt's and the joints'
    one-time references given), or exit 2 saying why there are none."""
    try:
        model = build_model(arm, fit.effects)
        data = data_from_recording(arm, rec, fit.window, nodes=2, stances=fit.stances)
        if fit.base_tilt is not None:
            data = replace(data, base_tilt_reference=parse_base_tilt(fit.base_tilt, fit.base_tilt_sigma_deg))
        if fit.references:
            if fit.mode == "separate":
                raise ValueError("--reference pins a joint's zero in the simultaneous fit; --mode "
                                 "separate compares each sensor's gravity direction and has no use "
                                 "for it")
            data = replace(data, joint_references=joint_references(
                arm, rec, [parse_reference(r) for r in fit.references]))
    except ValueError as e:
        fail(str(e))
    return model, data


def _print_separate(fits: dict) -> None:
    """The separate fits: each sensor's gravity direction in the base frame (the first stance)."""
    t = Table(title="Gravity direction in the base frame, per sensor (separate fits; the first "
                    "stance)", title_justify="left")
    for c in ("sensor", "roll [deg]", "pitch [deg]", "RMS / noise", "held"):
        t.add_column(c)
    for k, f in fits.items():
        ratio = np.mean([np.mean(s.rms / s.noise) for s in f.fits])
        a = np.degrees(f.attitude_rad)  # the first stance's
        i0 = len(f.names) - 3 * len(f.attitudes_rad)
        t.add_row(k, f"{a[0]:.3f} ± {np.degrees(f.sigma[i0]):.3f}",
                  f"{a[1]:.3f} ± {np.degrees(f.sigma[i0 + 1]):.3f}", f"{ratio:.2f}", str(int(f.held.sum())))
    console.print(t)


def _write_config(write: Path, res, out: dict, header: str, compass_line: str | None) -> None:
    """Write the calibrated config ``out``: ``header``, the references it rests on and the
    compass's line as comments, then the YAML."""
    write.parent.mkdir(parents=True, exist_ok=True)
    refs = "".join(f"# rests on the one-time reference {c.reference.joint} = "
                   f"{np.degrees(c.reference.angle_rad):.3f}° ± {np.degrees(c.reference.sigma_rad):.3g}° "
                   f"({c.reference.where}): calibration.identified.references\n"
                   for c in res.reference_checks)
    compass = f"# {compass_line}\n" if compass_line else ""
    write_text_replacing(write, header + refs + compass + yaml.safe_dump(out, sort_keys=False, width=110))


def _with_compass_from_drive(cfg: dict, drive: Path, rec, json_out: bool) -> tuple[dict, str]:
    """``cfg`` (the fitted config, as written) with the compass's iron learnt from the turns
    in ``drive`` (read as ``rec``) in place of the parked fit's; the line that says what the
    drive gave."""
    import tempfile

    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.tracking.compass_drive import calibrate_compass_on_drive

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "fitted.yaml"
        path.write_text(yaml.safe_dump(cfg, sort_keys=False), encoding="utf-8")
        arm = load_arm(str(path))
    screen_or_exit(arm, rec, drive, (), "", True)  # (the same door as the recording's; saturation unsaid)
    try:
        entries, line = calibrate_compass_on_drive(arm, rec, drive.name)
    except ValueError as e:
        fail(f"--compass-drive {drive}: {e}")
    if entries is None:
        return cfg, line
    kept = [e for e in cfg.get("effects", []) if e.get("effect") not in (MagHardIron.name, MagSoftIron.name)]
    return {**cfg, "effects": kept + entries}, line


EXPECTED_JACOBIANS = 50
"""Jacobians a calibration fit takes, for the bar's time left: 44 measured on 300 s of the
realistic WMRA's renk-maneuver (34 of them on the coarse subset), 55 on 60 s
(``docs/benchmarks.md``, the identification speed); past it the bar expects one more at a time."""


def _jacobians(advance, fits: int = 1):
    """``progress(k, cost)`` of ``fits`` fits as a bar: every Jacobian (of any pass) counts
    one of :data:`EXPECTED_JACOBIANS` per fit."""
    done = 0

    def progress(k: int, cost: float) -> None:
        nonlocal done
        done += 1
        advance(done / max(fits * EXPECTED_JACOBIANS, done + 1), f"fitting: Jacobian {k}, cost {cost:.4g}")
    return progress


def _print(res, write) -> None:
    from rich.markup import escape
    console.print(f"[bold]{res.summary()}[/]")
    t = Table(title="Estimates", title_justify="left")
    for c in ("parameter", "estimate", "σ", "prior σ", ""):
        t.add_column(c, justify="right" if c != "parameter" else "left")
    for i, n in enumerate(res.names):
        t.add_row(escape(n), f"{res.x[i]:.5g}", f"{res.sigma[i]:.2g}", f"{res.prior_sigma[i]:.2g}",
                  "held" if res.held[i] else "")
    console.print(t)
    if res.holds:
        console.print("[bold]Not separable by this recording[/] (held at their priors):")
        for h in res.holds:
            console.print(escape(f"  • {h.message}.\n    To separate: {h.suggestion}."), highlight=False)
    pairs = res.correlated_pairs()
    if pairs:
        console.print("[bold]Strongly correlated estimates[/] (|ρ| > 0.9):")
        for a, b, r in pairs[:15]:
            console.print(escape(f"  {a} ~ {b}: ρ = {r:+.3f}"), highlight=False)
    t = Table(title="Fit RMS per axis against the noise (window means)", title_justify="left")
    for c in ("stream", "unit", "RMS", "noise"):
        t.add_column(c)
    for f in res.fits:
        t.add_row(f.stream, f.unit, ", ".join(f"{v:.3g}" for v in f.rms), ", ".join(f"{v:.3g}" for v in f.noise))
    console.print(t)
    for n in res.notes:
        console.print(f"note: {n}", highlight=False)
    if write:
        console.print(f"Wrote {write}")
