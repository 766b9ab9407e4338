"""`armfusion calibrate joints`: the startup calibration from a recording."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from armfusion.fusion.cli.common import (
    arm_and_recording_or_exit,
    check_output_path,
    choice_or_exit,
    config_file,
    console,
    emit_json,
    err_console,
    fail,
)
from armfusion.fusion.cli.options import (
    ConfigOpt,
    JsonOpt,
    finite_between,
    window_holds_samples,
    window_seconds,
)
from armfusion.fusion.identification.identify import startup_correction
from armfusion.fusion.startup.pose_store import load_pose, save_pose
from armfusion.fusion.startup.solve import (
    StartupInputError,
    StartupPrior,
    StartupResult,
    StartupSettings,
    prior_after_move,
    readings_from_recording,
    solve_still,
)
from armfusion.fusion.startup.static import StaticDetectionSettings, find_static_segments
from armfusion.models.effects.library import TemperatureDrift
from armfusion.models.sensor_models import encoder_angles_at, mpu9150_temperature_c, stream_models
from rich.markup import escape
from rich.table import Table

calibrate_app = typer.Typer(help="Calibrate: joint angles from a still arm, or the sensors.",
                            no_args_is_help=True)


@calibrate_app.command("joints")
def calibrate_joints(
    recording: Annotated[Path, typer.Argument(help="Recording (.csv or .mcap) with a still arm.")],
    config: ConfigOpt = "wmra",
    segments: Annotated[bool, typer.Option("--segments", help="One solution per still segment.")] = False,
    method: Annotated[str, typer.Option(help="joint (all sensors at once) or sequential (the thesis).")] = "joint",
    json_out: JsonOpt = False,
    window_s: Annotated[float, typer.Option(help="Averaging window at the end of each still segment [s].",
                                            callback=window_seconds("--window-s"))] = 1.0,
    prior: Annotated[Path | None, typer.Option(help="Pose saved at the last clean shutdown (JSON): checked against the data, used to choose a branch only if it fits.")] = None,
    assume_parked: Annotated[bool, typer.Option("--assume-parked", help="Take the ready pose as evidence (the arm is known to be parked there): it picks among branches that fit, and the result says so.")] = False,
    independent: Annotated[bool, typer.Option("--independent", help="With --segments: solve every still window alone (by default each window's answer is carried to the next through the encoder counts).")] = False,
    save: Annotated[Path | None, typer.Option(help="Save the solved pose here (atomically) when every joint is ok.")] = None,
    gimbal_lock_deg: Annotated[float, typer.Option(help="Axis-to-vertical angle below which a joint is gravity-blind.", callback=finite_between("--gimbal-lock-deg", 0.0, 90.0, "an angle in degrees", hi_open=True))] = StartupSettings.gimbal_lock_deg,
    sigma_limit_deg: Annotated[float, typer.Option(help="Sigma above which a joint is ill_conditioned.", callback=finite_between("--sigma-limit-deg", 0.0, 180.0, "a sigma in degrees", lo_open=True))] = StartupSettings.sigma_limit_deg,
    start_at: Annotated[float | None, typer.Option("--start-at", metavar="SECONDS", help="Calibrate on the first still stretch from this many seconds after the recording's start.")] = None,
) -> None:
    """Every joint angle of a still arm, with sigma, flags, and a move that unlocks blind joints."""
    choice_or_exit(method, "--method", ("joint", "sequential"))
    if save is not None:
        check_output_path(save, "--save", inputs=(recording, config_file(config)))
    arm, rec, screen = arm_and_recording_or_exit(
        config, recording, lambda arm: [a.name for a in arm.link_accelerometers],
        "calibrate joints needs (every link accelerometer of {source})", json_out)
    window_holds_samples(rec, window_s)
    st = StartupSettings(gimbal_lock_deg=gimbal_lock_deg, sigma_limit_deg=sigma_limit_deg)
    notes: list[str] = []
    first_prior = _first_prior(prior, assume_parked, arm, notes)
    from armfusion.fusion.tracking.start import short_still_readings

    segs, short = _still_segments(arm, rec, recording, segments, window_s, start_at, notes)
    out = []
    temp = rec.get("imu_temp")
    corr, temperature_c = _correction_with_notes(arm, temp, notes)
    drifts = any(e.name == TemperatureDrift.name for e in corr.model.effects)
    by_temperature = {round(temperature_c, 1): corr}
    enc = rec.get("enc")
    carried: tuple[StartupResult, np.ndarray] | None = None  # last answer, encoder angles then
    for i_seg, seg in enumerate(segs):
        readings, checks = readings_from_recording(arm, rec, seg.t_start_s, seg.t_end_s, window_s)
        short_note = None
        if i_seg in short:
            readings, short_note = short_still_readings(arm, rec, seg, readings)
        enc_rad = _encoder_angles_at(arm, enc, seg.t_end_s)
        seg_prior = first_prior
        if carried is not None and not independent and enc_rad is not None:
            # within one power-on the encoders are continuous: what the last window found,
            # moved by what they counted since, is this window's (checked) prior
            seg_prior = prior_after_move(carried[0], enc_rad - carried[1], arm, st)
        seg_corr = _segment_correction(arm, seg, temp if drifts else None, corr, by_temperature)
        readings = seg_corr.readings(readings)
        seg_notes = [c.message for c in checks] + ([short_note] if short_note else [])
        try:
            geometric = solve_still(arm, readings, st, prior=seg_prior, method=method)
            res = seg_corr.controller_result(geometric)
        except StartupInputError as e:
            out.append({"t_start": seg.t_start_s, "t_end": seg.t_end_s, "error": str(e),
                        "notes": seg_notes})
            continue
        if enc_rad is not None:
            carried = (geometric, enc_rad)
        d = res.as_dict()
        d["t_start"], d["t_end"] = seg.t_start_s, seg.t_end_s
        d["notes"] = seg_notes + list(res.notes)
        out.append((d, res))
    docs = [o[0] if isinstance(o, tuple) else o for o in out]
    if save is not None:
        _save_last_pose(save, arm, [o[1] for o in out if isinstance(o, tuple)], notes)
    if json_out:
        emit_json({"config": arm.source, "recording": str(recording), "method": method,
                   "segments": docs, "notes": notes, "saturated_left_out": screen.as_dict()["saturated"]})
        return
    for n in notes:
        err_console.print(n)
    for d in docs:
        _print_segment(d)
    if all("error" in d for d in docs):
        raise typer.Exit(1)


def _first_prior(prior: Path | None, assume_parked: bool, arm, notes: list[str]):
    """The first still stretch's prior: ``--prior``'s saved pose (a note when it cannot be
    used), the ready pose with ``--assume-parked``, else none; exit 2 given both."""
    if prior is not None and assume_parked:
        fail("--prior and --assume-parked: give one (a saved pose is checked; --assume-parked asserts the ready pose)")
    if prior is not None:
        saved, why = load_pose(prior, arm)
        if saved is None:
            notes.append(why)
            return None
        return StartupPrior.saved_pose(saved.q_rad, source=f"the pose saved in {prior}")
    return StartupPrior.assume_parked(arm) if assume_parked else None


def _still_segments(arm, rec, recording: Path, segments: bool, window_s: float, start_at: float | None,
                    notes: list[str]) -> tuple[list, set[int]]:
    """The still stretches to calibrate on (every one with ``--segments``, else where a start
    would: the first near the start, a short one too) and which of them are short; exit 2
    when there is none."""
    from armfusion.fusion.tracking.start import NoStillWindowError, choose_start

    if start_at is not None and not (np.isfinite(start_at) and start_at >= 0.0):
        fail(f"--start-at must be a time of 0 s or more after the recording's start, not {start_at!r}")
    short = set()
    if segments:
        segs = find_static_segments(rec, StaticDetectionSettings(window_s=min(window_s, 1.0)),
                                    stream_models(arm))
    else:  # where a start would calibrate: the first still stretch near the start, a short one too
        try:
            choice = choose_start(arm, rec, window_s, None if start_at is None else rec.t_start_s + start_at)
        except NoStillWindowError as e:
            fail(f"{recording}: {e}")
        if choice.segment is None:
            fail(f"{recording}: no still stretch within 5 s of t = {start_at:g} s; the arm must be still "
                 "to calibrate (track --start-at starts on a moving arm)")
        segs = [choice.segment]
        if choice.short:
            short.add(0)
        if choice.note:
            notes.append(choice.note)
    if not segs:
        fail(f"{recording}: no still segment found (accelerometers, gyro and encoders all quiet "
             "for at least 1 s); the arm must be still to calibrate")
    return segs, short


def _correction_with_notes(arm, temp, notes: list[str]) -> tuple:
    """The config's correction of a still arm's readings at the IMU's mean temperature over
    the recording (``temp``, its stream; 25 °C without one), with notes on the effects it
    applies, the references the zeros rest on, and the effects it leaves out: ``(correction,
    temperature_c)``."""
    temperature_c = (float(mpu9150_temperature_c(np.mean(temp.values)))
                     if temp is not None and len(temp) else 25.0)
    try:
        corr = startup_correction(arm, temperature_c, include_joint_offsets=True)
    except (ValueError, KeyError) as e:
        fail(f"{arm.source}: effects: {e}")
    used = [e.block_name for e in corr.model.effects
            if e.stage in ("joints", "sensor") and (e.stage == "joints" or e.target in corr.maps
                                                   or e.target == getattr(arm.imu, "name", None))]
    if used:
        notes.append("applied from the config: " + ", ".join(used))
    for ref in arm.calibration.references:
        notes.append(f"{ref.joint}'s zero rests on the one-time reference of the sensors' "
                     f"calibration: {ref.joint} = {ref.angle_deg}° ± {ref.sigma_deg}° ({ref.where})")
    unused = [e.block_name for e in corr.model.effects if e.block_name not in used]
    if unused:
        notes.append("not applied to a still arm: " + ", ".join(unused))
    return corr, temperature_c


def _segment_correction(arm, seg, temp, corr, by_temperature: dict):
    """The correction at the still stretch's own temperature (``temp``: the IMU's temperature
    stream when the config's effects drift with it, else None: ``corr``), cached by 0.1 °C."""
    seg_temp = temp.between(seg.t_start_s, seg.t_end_s) if temp is not None else None
    if seg_temp is None or not len(seg_temp):
        return corr
    key = round(float(mpu9150_temperature_c(np.mean(seg_temp.values))), 1)
    if key not in by_temperature:
        by_temperature[key] = startup_correction(arm, key, include_joint_offsets=True)
    return by_temperature[key]


def _save_last_pose(save: Path, arm, results: list, notes: list[str]) -> None:
    """Save the last still stretch's pose to ``save`` when every joint of it is ok; a note
    either way."""
    last = results[-1] if results else None
    if last is not None and last.all_ok:
        save_pose(save, arm, last.q_rad)
        notes.append(f"pose saved to {save}")
    else:
        notes.append(f"pose not saved to {save}: not every joint is ok")


def _encoder_angles_at(arm, enc, t_s: float) -> np.ndarray | None:
    """The encoders' relative joint angles (rad) at the last sample at or before ``t_s``."""
    if enc is None or not len(enc) or enc.values.shape[1] != arm.n_joints:
        return None
    return encoder_angles_at(arm, enc, t_s)[1]


def _print_segment(d: dict) -> None:
    console.print(f"\n[bold]still segment t = {d['t_start']:.2f} … {d['t_end']:.2f} s[/]")
    for n in d.get("notes", []):
        console.print(f"[yellow]{n}[/]")
    if "error" in d:
        console.print(f"[red]refused:[/] {d['error']}")
        return
    b = d["base"]
    console.print(f"base roll {np.degrees(b['roll_rad']):+.3f}° ± {np.degrees(b['roll_sigma_rad']):.3f}, "
                  f"pitch {np.degrees(b['pitch_rad']):+.3f}° ± {np.degrees(b['pitch_sigma_rad']):.3f}; "
                  f"residual {d['residual_rms_g'] * 1000:.2f} mg rms ({d['branches']} feasible branch"
                  f"{'es' if d['branches'] != 1 else ''})")
    t = Table(show_header=True)
    for col in ("joint", "angle [deg]", "sigma [deg]", "flag", "axis to vertical [deg]", "thesis detector"):
        t.add_column(escape(col), justify="right" if "deg" in col else "left")
    colours = {"ok": "green", "ill_conditioned": "yellow", "gimbal_lock": "red", "ambiguous": "magenta",
               "out_of_limits": "red"}
    for j in d["joints"]:
        ang = "-" if j["angle_rad"] is None else f"{np.degrees(j['angle_rad']):.3f}"
        if j["alternatives_rad"]:
            ang = " or ".join(f"{np.degrees(a):.2f}" for a in j["alternatives_rad"])
        elif len(j.get("turns_rad", ())) > 1:  # gravity reads it modulo a turn
            ang = " or ".join(f"{np.degrees(a):.2f}" for a in j["turns_rad"]) + " (a turn apart)"
        elif j["angle_rad"] is None and j.get("range_rad"):
            lo, hi = np.degrees(j["range_rad"])
            ang = f"unseen: {lo:.0f} … {hi:.0f}"
        sig = "-" if j["sigma_rad"] is None else f"{np.degrees(j['sigma_rad']):.3f}"
        th = {None: "n/a", True: "locked", False: "clear"}[j["thesis_detector_locked"]]
        t.add_row(j["name"], ang, sig, f"[{colours[j['flag']]}]{j['flag']}[/]",
                  f"{j['axis_to_vertical_deg']:.1f}", th)
    console.print(t)
    console.print(d["summary"])
