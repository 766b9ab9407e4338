"""`armfusion track`: the tracker over a recording (startup calibration on its first still
stretch, then every sample), with an estimates file and a JSON summary (docs/track-recording.md, docs/reference/track-output.md)."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from armfusion.fusion.cli.common import (
    arm_and_recording_or_exit,
    check_output_path,
    config_file,
    console,
    emit_json,
    err_console,
    fail,
    progress_bar,
)
from armfusion.fusion.cli.options import ConfigOpt, JsonOpt, finite_between
from armfusion.sensors.samples import clipped_repr
from rich.table import Table

OUT_SUFFIXES = (".csv", ".mcap")


def register(app: typer.Typer) -> None:
    """Add ``track`` to the ``armfusion`` app (once)."""
    if any(c.name == "track" for c in app.registered_commands):
        return
    app.command("track")(track)


def _needed_streams(arm) -> list[str]:
    """What track reads: the encoders and every link accelerometer; an arm with no joints
    (an IMU alone) has neither, and its base IMU's accelerometer and gyroscope carry it."""
    if arm.n_joints == 0:
        return ["imu_acc", "imu_gyro"]
    return ["enc", *(a.name for a in arm.link_accelerometers)]


def track(
    recording: Annotated[Path, typer.Argument(help="Recording (.csv or .mcap) that starts with a still arm.")],
    config: ConfigOpt = "wmra",
    out: Annotated[Path | None, typer.Option("--out", help="Write every estimate to EST.csv, EST.mcap, or EST.ros2.mcap (ROS 2 messages: docs/ros2.md).")] = None,
    json_out: JsonOpt = False,
    prior: Annotated[Path | None, typer.Option(help="Pose saved at the last clean shutdown (JSON): picks startup branches.")] = None,
    after_s: Annotated[float, typer.Option(help="With truth columns: RMS errors count from this many seconds after the recording's start.", callback=finite_between("--after-s", 0.0, float("inf"), "a number of seconds", hi_open=True))] = 60.0,
    gate_significance: Annotated[float, typer.Option(help="Chi-square gate: probability that a good sample is rejected.")] = 1e-3,
    unmodelled_g: Annotated[float | None, typer.Option(help="Override the config's unmodelled accelerometer error (g, 1 sigma), for startup and tracking.")] = None,
    no_motion_compensation: Annotated[bool, typer.Option("--no-motion-compensation", help="Predict the accelerometers as if nothing moved (for comparison only).")] = False,
    moving_start: Annotated[bool, typer.Option("--moving-start", help="Start at the recording's start: with no still stretch in its first 5 s (an arm that never stops), on the least-moving instants there, the sigma widened by their motion.")] = False,
    start_at: Annotated[float | None, typer.Option("--start-at", metavar="SECONDS", help="Start the startup calibration at this many seconds after the recording's start: on a still stretch that begins within 5 s of it, else on the least-moving instants from it.")] = None,
    encoder_withheld: Annotated[str | None, typer.Option("--encoder-withheld", metavar="JOINT@SECONDS", help="The joint's encoder fails SECONDS after the recording's start: the gyroscopes on either side of it stand in, calibrated against the encoder before then, and tracking starts afresh there (its zero unknown).")] = None,
    sigma_relative: Annotated[bool, typer.Option("--sigma-relative", help="Report each sigma relative to a calibrated config's joint-zero conventions (the doubt of the angles against the calibration's own zeros), not the absolute one that also holds the zeros' own doubt.")] = False,
) -> None:
    """Track the joint angles and the heading through a recording: startup calibration on
    its first still stretch (or, with --moving-start, on its least-moving instants), then
    the unscented Kalman filter on every sample."""
    from dataclasses import replace

    from armfusion.fusion.tracking.tracker import TrackerSettings

    _check_options(start_at, gate_significance, out, recording, config, unmodelled_g)
    arm, rec, screen = arm_and_recording_or_exit(
        config, recording, _needed_streams,
        "track needs (the encoders and every link accelerometer of {source}; "
        "with no joints, its base IMU's accelerometer and gyroscope)", json_out)
    if unmodelled_g is not None:
        arm = replace(arm, calibration=arm.calibration.with_accel_floor(unmodelled_g))
    notes: list[str] = []
    rec, note = _scoring_truth(rec, recording, arm.joint_names)
    if note:
        notes.append(note)
    prior_q = _prior_pose(prior, arm, notes)
    settings = TrackerSettings(gate_significance=gate_significance,
                               motion_compensation=not no_motion_compensation)
    withheld = None
    if encoder_withheld is not None:
        rec, settings, withheld = _withhold_encoder(arm, rec, settings, encoder_withheld)
        notes.append(f"the encoder of {withheld['joint']} withheld from {withheld['from_s']:g} s: the "
                     f"gyros on either side of it stand in (scale {withheld['scale']:.4f}, bias "
                     f"{withheld['bias_deg_s']:+.4f} deg/s, drift {withheld['drift_deg_per_sqrt_s']:.3f} "
                     f"deg/sqrt(s) against the encoder before then); tracking starts afresh there")
    if sigma_relative:
        notes.append(_relative_sigma_note(arm))
    how = TrackStart(prior_q, moving_start, start_at, sigma_relative)
    tr, start, run = _start_and_run(arm, rec, recording, settings, how, notes, json_out)
    warnings = tr.sensor_warnings() if run.steps else []
    notes.extend(warnings)
    notes.extend(_floor_notes(arm))
    summary = _scored_summary(run, rec, after_s, notes)
    doc = {
        "config": arm.source,
        "recording": str(recording),
        "start": {"t_start_s": start.t_start_s, "t_end_s": start.t_end_s,
                  "summary": start.startup.summary,
                  "flags": {j.name: j.flag for j in start.startup.joints}},
        **summary,
        "final": tr.estimate.as_dict() if run.steps else None,
        "out": None if out is None else str(out),
        "gyro_scale_z": tr.gyro_scale() if run.steps else None,
        "model_alarms": [a.as_dict() for a in tr.alarm.raised],
        "sensor_warnings": warnings,
        "saturated_left_out": screen.as_dict()["saturated"],
        "encoder_withheld": withheld,
        "notes": notes,
    }
    if out is not None:
        try:
            write_estimates(run, out, arm.source)
        except (OSError, ValueError) as e:
            fail(f"cannot write {out}: {e}")
    if json_out:
        emit_json(doc)
        return
    for n in notes:
        err_console.print(n)
    _print(doc, run)


def _check_options(start_at: float | None, gate_significance: float, out: Path | None, recording: Path,
                   config: str, unmodelled_g: float | None) -> None:
    """Exit 2 before any work on an option out of its range or an output that cannot be written."""
    if start_at is not None and not (np.isfinite(start_at) and start_at >= 0.0):
        fail(f"--start-at must be a time of 0 s or more after the recording's start, not {start_at!r}")
    if not 0.0 < gate_significance < 1.0:
        fail(f"--gate-significance must be between 0 and 1, not {gate_significance!r}")
    if out is not None:
        check_output_path(out, "--out", OUT_SUFFIXES, inputs=(recording, config_file(config)))
    if unmodelled_g is not None and not 0.0 <= unmodelled_g <= 1.0:  # (the config's accel_unmodelled_g)
        fail(f"--unmodelled-g must be from 0 to 1 g (more than gravity itself would make the sensor "
             f"useless), not {unmodelled_g!r}")


def _prior_pose(prior: Path | None, arm, notes: list[str]):
    """The joint angles of ``--prior``'s saved pose, or None (with a note saying why, when one
    was given but cannot be used)."""
    from armfusion.fusion.startup.pose_store import load_pose

    if prior is None:
        return None
    saved, why = load_pose(prior, arm)
    if saved is None:
        notes.append(why)
        return None
    return saved.q_rad


@dataclass(frozen=True)
class TrackStart:
    """How ``track``'s startup calibration starts: with the saved pose's joint angles
    ``prior_q_rad`` (``--prior``; ``None``: none) to pick its branches; on the least-moving
    instants when the recording has no still stretch (``--moving-start``); at ``start_at_s``
    after the recording's start (``--start-at``; ``None``: its first still stretch); its σ
    relative to the calibration's joint-zero conventions (``--sigma-relative``)."""

    prior_q_rad: np.ndarray | None = None
    moving_start: bool = False
    start_at_s: float | None = None
    sigma_relative: bool = False


def _start_and_run(arm, rec, recording: Path, settings, how: TrackStart, notes: list[str],
                   json_out: bool) -> tuple:
    """The startup calibration as ``how`` says, then the tracker over the recording, with a
    progress bar: ``(tracker, start, run)``; exit 2 saying why the tracking cannot start."""
    from armfusion.fusion.startup.solve import StartupInputError
    from armfusion.fusion.tracking.tracker import NoStillWindowError, StartOptions, start_from_recording

    with progress_bar("startup calibration", json_out) as advance:
        try:
            tr, start = start_from_recording(arm, rec, settings, prior_q_rad=how.prior_q_rad, options=StartOptions(
                resolve_by_motion_s=20.0, moving_start=how.moving_start,
                start_at_s=None if how.start_at_s is None else rec.t_start_s + how.start_at_s,
                sigma_given_conventions=how.sigma_relative))
        except NoStillWindowError as e:
            fail(f"{recording}: {e}" + ("" if how.moving_start or how.start_at_s is not None else
                                        " (--moving-start starts on its least-moving instants)"))
        except (StartupInputError, ValueError) as e:
            fail(f"{recording}: cannot start tracking: {e}")
        notes.extend(start.notes)
        advance(0.0, "tracking")
        run = tr.run(rec, progress=advance)
    return tr, start, run


def _relative_sigma_note(arm) -> str:
    """What ``--sigma-relative`` makes of the σ, for the notes."""
    return ("sigma relative to the calibration's joint-zero conventions (--sigma-relative): the angles' "
            "doubt against the calibration's own zeros, without those zeros' own doubt (a board's turn "
            "about its joint, which no motion shows)"
            + ("" if arm.calibration.correction_covariance else
               "; this config holds no calibration's covariance, so it is the absolute sigma"))


def _floor_notes(arm) -> list[str]:
    """A note naming the unmodelled-error floors the config does not give (each sensor's
    class's default is used), or none."""
    floors = arm.calibration.floors_by_default
    if not floors:
        return []
    return ["unmodelled-error floors the config does not give, each sensor's class's: "
            + "; ".join(f"{k}: {v}" for k, v in floors.items())
            + " (docs/config.md, Unmodelled-error floors)"]


def _scored_summary(run, rec, after_s: float, notes: list[str]) -> dict:
    """The run's summary, its errors scored from ``after_s`` on (over the whole run, with a
    note, when the recording ends before), and the span they are scored over."""
    after = after_s
    if run.steps and run.t_s[-1] < rec.t_start_s + after_s:  # nothing to score after --after-s
        after = 0.0
        if rec.get("true_q") is not None:
            notes.append(f"the recording ends {run.t_s[-1] - rec.t_start_s:.1f} s after its start, "
                         f"before --after-s {after_s:g} s: the RMS errors are over the whole tracked run")
    summary = run.summary(after_s=after, t0_s=rec.t_start_s)
    scored = run.t_s[run.t_s >= rec.t_start_s + after] - rec.t_start_s if run.steps else run.t_s
    if "rms_error_deg" in summary:
        summary["rms_span_s"] = [float(scored[0]), float(scored[-1])] if len(scored) else None
    return summary


# --------------------------------------------------------------------------------------
def _withhold_encoder(arm, rec, settings, spec: str) -> tuple:
    """``--encoder-withheld JOINT@SECONDS``: the recording from then on with the joint's
    encoder made from the gyros (calibrated on what comes before), the settings with the
    gyros' drift as the joint's random walk, and what was done (for the JSON)."""
    from armfusion.fusion.tracking.gyro_encoder import (
        calibrate_gyro_encoder,
        settings_with_gyro_encoder,
        with_gyro_encoder,
    )

    joint, sep, when = spec.partition("@")
    if not sep or joint not in arm.joint_names:
        fail(f"--encoder-withheld takes JOINT@SECONDS with JOINT one of {', '.join(arm.joint_names)}, "
             f"not {clipped_repr(spec)}")
    try:
        from_s = float(when)
    except ValueError:
        from_s = float("nan")
    t0 = rec.t_start_s
    if not 0.0 < from_s < rec.duration_s:
        fail(f"--encoder-withheld {clipped_repr(spec)}: SECONDS must be a time inside the recording "
             f"(0 to {rec.duration_s:.1f} s after its start)")
    j = arm.joint_names.index(joint)
    try:
        cal = calibrate_gyro_encoder(arm, rec.between(t0, t0 + from_s), j)
        after = with_gyro_encoder(arm, rec.between(t0 + from_s, np.inf), j, cal)
    except ValueError as e:
        fail(f"--encoder-withheld {clipped_repr(spec)}: {e}")
    return after, settings_with_gyro_encoder(settings, cal), {**cal.as_dict(), "from_s": from_s}


def _scoring_truth(rec, recording: Path, joint_names) -> tuple:
    """With a simulator's ``REC.truth.json`` beside the recording, the joint truth the
    errors are scored against is the true angle plus each joint's true DH zero offset (the
    angle gravity can find; :func:`armfusion.models.simulator.angle_truth`). Returns the recording
    (its ``true_q`` replaced when it applies) and a note, or ``None``."""
    import json

    from armfusion.fusion.cli.simulate import truth_path
    from armfusion.models.simulator import angle_truth, true_zero_offsets_rad
    from armfusion.sensors.samples import Recording

    tq = rec.get("true_q")
    sidecar = truth_path(recording)
    if tq is None or not sidecar.exists():
        return rec, None
    try:
        truth = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        return rec, f"{sidecar}: not read ({e}); errors against the recording's true_q as it is"
    if not np.any(true_zero_offsets_rad(truth, joint_names)):
        return rec, None
    streams = {**rec.streams, "true_q": angle_truth(tq, truth, joint_names)}
    return Recording(streams, rec.meta), (
        f"errors against the true angle plus each joint's true zero offset ({sidecar.name}): "
        "a relative encoder's zero is what the startup makes it")


def estimate_columns(run) -> list[str]:
    from armfusion.fusion.tracking.run import combination_column

    j = run.joint_names
    return (["t"] + [f"q_{n}" for n in j] + [f"sigma_{n}" for n in j] + [f"flag_{n}" for n in j]
            + ["roll", "pitch", "yaw", "sigma_roll", "sigma_pitch", "sigma_yaw",
               "gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "magnetic_disturbance", "magnetic_recovery",
               "heading_status"]
            + [f"status_{s}" for s in run.sensor_names]
            + [c for name in (getattr(run, "combinations", None) or {}) for c in (combination_column(name),
                                                               "sigma_" + combination_column(name))])


def write_estimates(run, path: Path, arm_config: str = "") -> None:
    """Every fused instant's estimate: CSV (one row each, angles in rad), MCAP (JSON
    messages on ``estimates/joints`` and ``estimates/heading``: the records of
    :mod:`armfusion.fusion.tracking.estimate`), or, for a name ending ``.ros2.mcap``, a rosbag2 MCAP
    file of ROS 2 messages (:mod:`armfusion.fusion.ros2.estimates_bag`); under a temporary name renamed
    when complete."""
    from armfusion.sensors.output_files import replaced_when_done

    path = Path(path)
    kind = ".ros2.mcap" if path.name.lower().endswith(".ros2.mcap") else path.suffix.lower()
    with replaced_when_done(path) as tmp:  # a failure halfway leaves no half file
        _write_estimates(run, tmp, kind, arm_config)


def _write_estimates(run, path: Path, suffix: str, arm_config: str) -> None:
    from armfusion.fusion.tracking.estimate import HEADING_STATUS
    from armfusion.fusion.tracking.tracker import JOINT_FLAGS, SENSOR_STATUS

    if suffix == ".ros2.mcap":
        from armfusion.fusion.ros2.estimates_bag import write_estimates_bag

        write_estimates_bag(run, path, Path(arm_config).stem)
        return
    if suffix == ".csv":
        with open(path, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(estimate_columns(run))
            flags = np.array(JOINT_FLAGS, dtype=object)[run.flags]
            status = np.array(SENSOR_STATUS, dtype=object)[run.sensor_status]
            mag = run.magnetic
            heading_status = np.array(HEADING_STATUS, dtype=object)[run.heading_status]
            combos = [a for _, v, sg in (run.combinations or {}).values() for a in (v, sg)]
            for i in range(run.steps):
                w.writerow([f"{run.t_s[i]:.6f}", *(f"{v:.9f}" for v in run.q_rad[i]),
                            *(f"{v:.3e}" for v in run.sigma_rad[i]), *flags[i],
                            *(f"{v:.9f}" for v in run.rpy_rad[i]), *(f"{v:.3e}" for v in run.rpy_sigma_rad[i]),
                            *(f"{v:.4e}" for v in run.gyro_bias_rad_s[i]),
                            int(mag[i] & 1 > 0), int(mag[i] & 2 > 0), heading_status[i], *status[i],
                            *("" if not np.isfinite(a[i]) else f"{a[i]:.9f}" for a in combos)])
        return
    from armfusion.fusion.tracking import estimate as wire
    from armfusion.sensors.recording_mcap import McapRecorder

    t0 = float(run.t_s[0]) if run.steps else 0.0
    combos = (run.combinations or {}).items()
    with McapRecorder(path, arm_config=arm_config, t_offset_s=max(0.0, -t0)) as mc:
        for i in range(run.steps):
            t = float(run.t_s[i])
            sensors = zip(run.sensor_names, (SENSOR_STATUS[c] for c in run.sensor_status[i]), strict=True)
            known = [{"name": nm, "coefficients": dict(coef), "angle_rad": v[i], "sigma_rad": sg[i]}
                     for nm, (coef, v, sg) in combos if np.isfinite(v[i])]
            wire.write_mcap_record(mc, "joints", wire.joints_record(
                t, run.joint_names, run.q_rad[i], run.sigma_rad[i], [JOINT_FLAGS[f] for f in run.flags[i]],
                sensors, combinations=known))
            wire.write_mcap_record(mc, "heading", wire.heading_record(
                t, run.rpy_rad[i], run.rpy_sigma_rad[i], run.gyro_bias_rad_s[i],
                run.magnetic[i] & 1, run.magnetic[i] & 2, wire.HEADING_STATUS[run.heading_status[i]],
                run.true_north))


def _print(doc: dict, run) -> None:
    from armfusion.fusion.tracking.alarm import Alarm
    from rich.markup import escape

    console.print(f"[bold]{doc['recording']}[/]: startup on t = {doc['start']['t_start_s']:.2f} … "
                  f"{doc['start']['t_end_s']:.2f} s: {doc['start']['summary']}")
    console.print(f"{doc['steps']} steps over {doc['duration_s']:.1f} s in {doc['elapsed_s']:.2f} s "
                  f"({doc['steps_per_s']:.0f} steps/s)")
    t = Table(title="Joints", title_justify="left")
    cols = ["joint", "final [deg]", "sigma [deg]", "flag"]
    truth = "rms_error_deg" in doc
    if truth:
        span = doc.get("rms_span_s")
        cols += ["RMS error, no instant scored" if span is None else
                 f"RMS error {span[0]:.1f}…{span[1]:.1f} s [deg]", "max [deg]"]
    cols.append("flags seen")
    for c in cols:  # escaped: "[deg]" is not a style
        t.add_column(escape(c), justify="left" if c in ("joint", "flag", "flags seen") else "right")
    last = doc["final"] or {}
    final = {nm: {"q_rad": q, "sigma_rad": s, "flag": f} for nm, q, s, f in zip(
        last.get("joint_names", []), last.get("q_rad", []), last.get("sigma_rad", []), last.get("flags", []),
        strict=True)}
    for nm in run.joint_names:
        f = final.get(nm, {})
        row = [nm, _deg(f.get("q_rad")), _deg(f.get("sigma_rad"), 4), f.get("flag", "-")]
        if truth:
            row += [_num(doc["rms_error_deg"][nm], 4), _num(doc["max_error_deg"][nm], 3)]
        seen = doc["flags_seen"]["joints"][nm]
        row.append(", ".join(f"{k} {v}" for k, v in seen.items()))
        t.add_row(*row)
    console.print(t)
    if "heading_rms_deg" in doc and doc["heading_rms_deg"] is not None:
        console.print(f"heading RMS error {doc['heading_rms_deg']:.3f}°")
    if "nees" in doc:
        n = doc["nees"]
        console.print(f"NEES mean {n['mean']:.2f} ({n['dof']} states; 95 % bounds for one instant "
                      f"{n['bounds_95_single'][0]:.1f} … {n['bounds_95_single'][1]:.1f})")
    for a in doc["model_alarms"]:
        line = Alarm.of_dict(a).line()
        console.print(f"[bold red]model changed[/]: {escape(line)} (raised at {a['raised_s']:.1f} s)")
    for c in doc.get("combinations", []):
        if c["last_angle_rad"] is None:
            continue
        line = (f"gravity reads together {c['name']}: {np.degrees(c['last_angle_rad']):.3f}° ± "
                f"{np.degrees(c['last_sigma_rad']):.3f}° at the end (reported at "
                f"{100 * c['reported_share']:.0f} % of instants; column {c['column']})")
        if "rms_error_deg" in c:
            line += f", RMS error {c['rms_error_deg']:.3f}°, within 3σ {100 * c['within_3_sigma']:.1f} %"
        console.print(escape(line))
    rej = {s: v for s, v in doc["rejections"].items() if v}
    console.print("rejections: " + (", ".join(f"{s} {v}" for s, v in rej.items()) or "none"))
    for s, d in doc["nis"].items():
        console.print(f"  NIS {s}: mean {d['mean']:.2f} ({d['dof']} dof)")
    if doc["out"]:
        console.print(f"estimates written to {doc['out']}")


def _deg(v, digits: int = 3) -> str:
    return "-" if v is None else f"{np.degrees(v):.{digits}f}"


def _num(v, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"
