"""``armfusion demo``: the whole service on one machine, no hardware, loopback only.

1. **The arm calibrates its sensors.** The WMRA is simulated with datasheet-typical sensor
   errors (``--realistic``: biases, scales, misaligned axes and mounts, link sag, time
   offsets…, drawn from ``--seed``) playing the planned self-calibration maneuver shipped
   with the code (``config/maneuvers/wmra-60s.yaml``, made once by ``armfusion
   plan-maneuver --config wmra --duration 60``; ``--maneuver`` plays another); the
   simulated installer gives j1's and j7's angle once, at the maneuver's still start
   (their true geometric angle plus N(0, 0.05°): :func:`armfusion.fusion.identification.truth.installer_reference`);
   the chair turns once on the spot (``compass-turn``); and ``armfusion calibrate sensors
   --reference … --compass-drive TURN --write`` identifies the errors (the compass's iron
   from the turn) and writes a calibrated config. Uncalibrated, the startup calibration honestly flags most
   joints ``ill_conditioned`` (the shipped config allows 45 mg of unmodelled error).
2. **The service runs, live.** Separate processes talk over Zenoh through a loopback
   router: the fake-device drivers (the same seed, so the same sensor errors; the chair in
   daily use, on the wall clock) → the fusion node (``serve`` with the calibrated config)
   → the recorder (``record`` to MCAP); this process watches the joint states as a
   consumer would.
3. **The summary**: startup and tracking accuracy against the simulator's truth, the flags
   seen, samples published / received / dropped, the sample→estimate latency (a sample's
   read time on the drivers' clock to the estimate's arrival here: one machine, one
   monotonic clock), and an HTML report (:mod:`armfusion.fusion.cli.demo_report`): the tracking
   plots and the workbench's verdict and error ladder on the calibration recording
   (``armfusion.fusion.workbench.diagnose``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
import yaml
from armfusion.fusion.cli.common import emit_json, err_console, fail
from armfusion.fusion.cli.demo_report import (
    heading_scores,
    joint_scores,
    latency_figures,
    sample_counts,
    say_summary,
    score_combinations,
    write_report,
)
from armfusion.fusion.cli.options import JsonOpt, ScenarioOpt, SeedOpt
from armfusion.fusion.cli.simulate import truth_path
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.processes import Children, cpu_seconds, free_loopback_port
from armfusion.fusion.tracking.tracker import truth_at
from armfusion.models.simulator import angle_truth
from armfusion.models.trajectories import SCENARIOS

ROBOT = "chair1"
SERVE_START_S = 600.0
"""How long the recorder and the fusion node may take to start: the fusion node compiles its
tracker kernels first (cached after the first run; a fresh copy's first demo on a 2-core
machine loaded by other work took more than 120 s)."""
MANEUVER = "maneuvers/wmra-60s.yaml"
"""The shipped planned self-calibration maneuver the demo's arm plays (a file of the shipped
configs' folder: ``armfusion.fusion.shipped.shipped_config``)."""
REFERENCE_JOINTS = ("j1", "j7")
"""The joints whose angle the demo's simulated installer gives once: what no parked maneuver
can pin (j1's zero against the IMU's mount about its axis, j7's against acc4's)."""
COMPASS_SCENARIO = "compass-turn"
"""The drive the compass's iron is learnt from (``calibrate sensors --compass-drive``): the
chair turns once on the spot, the arm parked (a parked maneuver cannot see the iron, and the
demo's 60 s of daily use turn the chair too little to learn it)."""
REFERENCE_SIGMA_DEG = 0.05
"""The installer's σ (``calibrate sensors --reference``'s default: a mechanical index)."""


class DemoError(RuntimeError):
    """A step of the demo failed; the message says which and why."""


@dataclass
class Watched:
    """What the demo's consumer receives: every joint state and heading with its arrival
    time (monotonic), and the nodes' last status."""

    joints: list[tuple[float, pl.JointState]] = field(default_factory=list)
    headings: list[tuple[float, pl.Heading]] = field(default_factory=list)
    status: dict[str, pl.Status] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample) -> None:
        arrived = time.monotonic()
        try:
            p = pl.decode(str(sample.key_expr), sample.payload.to_bytes())
        except pl.PayloadError:
            return
        with self.lock:
            if isinstance(p, pl.JointState):
                self.joints.append((arrived, p))
            elif isinstance(p, pl.Heading):
                self.headings.append((arrived, p))
            elif isinstance(p, pl.Status):
                self.status[p.node] = p


# --- the steps --------------------------------------------------------------------------------


def calibrate(workdir: Path, seed: int, duration_s: float | None, realistic: bool, ch: Children,
              say, maneuver: Path | None = None) -> tuple[Path, dict, Path, dict]:
    """Simulate the planned calibration maneuver (``maneuver``, default the shipped
    :data:`MANEUVER`; its first ``duration_s`` seconds of poses, or all of it), take the
    simulated installer's references of :data:`REFERENCE_JOINTS`, simulate the chair's turn
    on the spot (:data:`COMPASS_SCENARIO`) and identify the sensors' errors, the compass's
    iron from the turn: the calibrated config, the identification's JSON, the recording and
    what was played and referenced."""
    from armfusion.fusion.cli.simulate import SimulationOptions, simulate
    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.identification.planner import safe_maneuver
    from armfusion.fusion.identification.truth import installer_reference
    from armfusion.fusion.shipped import shipped_config
    from armfusion.sensors.recording import read_recording

    source = shipped_config(MANEUVER) if maneuver is None else Path(maneuver)
    arm = load_arm("wmra")
    try:
        plan = safe_maneuver(arm, source)
    except FileNotFoundError as e:
        raise DemoError(f"the calibration maneuver: {e}") from None
    except ValueError as e:  # its message begins with the file's name
        raise DemoError(f"the calibration maneuver {e}") from None
    if duration_s is not None:
        if duration_s > plan.duration_s + 1e-6:
            raise DemoError(f"--calibration-duration {duration_s:g}: the maneuver {source.name[:60]} "
                            f"lasts {plan.duration_s:.0f} s")
        plan = plan.until(duration_s)
    played = workdir / "maneuver.yaml"
    played.write_text(f"# the demo's calibration maneuver: {source.name}"
                      + ("" if duration_s is None else f", its poses within the first {duration_s:g} s")
                      + "\n" + yaml.safe_dump(plan.as_dict(), sort_keys=False, width=110), encoding="utf-8")
    rec = workdir / "calibration.mcap"
    say(f"simulating the planned calibration maneuver ({source.name}, {plan.duration_s:.1f} s, "
        f"{len(plan.poses_rad)} poses)")
    try:
        simulate("wmra", "planned", rec, SimulationOptions(seed=seed, realistic=realistic, maneuver=played))
    except ValueError as e:
        raise DemoError(f"the calibration maneuver {source.name[:60]}: {e}") from None
    drive = workdir / "compass-turn.mcap"
    say(f"simulating one turn of the chair on the spot ({COMPASS_SCENARIO}: the compass's iron)")
    simulate("wmra", COMPASS_SCENARIO, drive, SimulationOptions(seed=seed, realistic=realistic))
    refs = installer_reference(arm, read_recording(rec), REFERENCE_JOINTS, REFERENCE_SIGMA_DEG, seed,
                               None if realistic else [])
    given = [f"{j}={math.degrees(a):.9f}:{math.degrees(sg):g}" for j, a, sg, _ in refs]
    say("the installer gives " + ", ".join(f"{j} = {math.degrees(a):.3f}° ± {math.degrees(sg):g}°"
                                            for j, a, sg, _ in refs) + " once, at the maneuver's still start")
    cfg = workdir / "calibrated.yaml"
    say("identifying the sensors' errors (armfusion calibrate sensors)")
    child = ch.start("calibrate", ["calibrate", "sensors", str(rec), "--write", str(cfg), "--json",
                                   *[a for g in given for a in ("--reference", g)],
                                   "--compass-drive", str(drive)])
    while child.running:
        time.sleep(0.2)
    if child.proc.returncode != 0 or not cfg.exists():
        raise DemoError(f"the sensor identification failed: {child.stderr_tail()}")
    what = {"maneuver": str(source), "played": str(played), "maneuver_s": plan.duration_s,
            "poses": len(plan.poses_rad), "compass_drive": str(drive),
            "references": [{"joint": j, "angle_deg": round(math.degrees(a), 6),
                            "sigma_deg": REFERENCE_SIGMA_DEG} for j, a, _, _ in refs]}
    return cfg, json.loads(child.stdout_path.read_text()), rec, what


def _wait_until_serving(record, serve) -> None:
    """Waits for the recorder and the fusion node to say they subscribe; a DemoError says why not."""
    for name, child, line in (("recorder", record, "recording"), ("fusion node", serve, "serving")):
        # (the fusion node compiles its kernels before it serves: on the first run after
        # an install that takes minutes on a busy 2-core machine)
        if child.wait_for_line(line, SERVE_START_S):
            continue
        if child is serve and child.proc.poll() is None:
            raise DemoError(
                f"the {name} did not start within {SERVE_START_S:.0f} s: it compiles its "
                "kernels on its first run after an install, which on a busy machine can take "
                "longer; what it compiled is cached, so running the demo again goes on from "
                f"there. {child.stderr_tail()}".rstrip())
        raise DemoError(f"the {name} did not start: {child.stderr_tail()}")


@dataclass(frozen=True)
class LiveDrive:
    """The demo's live run: the fake drivers play ``duration_s`` (wall clock) of ``scenario``
    from ``seed``, with ``realistic`` sensor errors or none, publishing a batch every
    ``batch_ms``; the fusion node and the recorder run with ``config``."""

    config: Path | str
    scenario: str
    duration_s: float
    seed: int
    realistic: bool
    batch_ms: float = 20.0


def run_live(workdir: Path, drive: LiveDrive, ch: Children, progress) -> dict[str, Any]:
    """Router, recorder, fusion node and drivers as processes (``ch``), the drivers as
    ``drive`` says, ``progress`` told what was received as it comes; returns what each
    reported and what the demo's consumer received."""
    import zenoh
    from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session

    router = f"tcp/127.0.0.1:{free_loopback_port()}"
    client = ["--mode", "client", "--connect", router]
    r = ch.start("router", ["router", "--listen", router], stdout=False)
    if not r.wait_for_line("listening", 60.0):
        raise DemoError(f"the router did not start: {r.stderr_tail()}")
    rec_path = workdir / "demo.mcap"
    config = str(drive.config)
    record = ch.start("record", ["record", str(rec_path), "--robot", ROBOT, "--config", config, "--json", *client])
    serve = ch.start("serve", ["serve", "--config", config, "--robot", ROBOT, "--json", *client])
    serve_t0 = time.monotonic()
    watched = Watched()
    truth_path = workdir / "drivers.mcap"
    with open_session(ZenohSettings(listen=[], connect=[router], mode="client")) as session:
        subs = [session.declare_subscriber(k, watched.on_sample)
                for k in (pl.joints_key(ROBOT), pl.heading_key(ROBOT), pl.status_key(ROBOT))]
        # the drivers once both subscribe: every sample published reaches both
        _wait_until_serving(record, serve)
        drivers = ch.start("drivers", [
            "drivers", "--fake", "--realtime", "--scenario", drive.scenario, "--seed", str(drive.seed),
            "--duration", str(drive.duration_s), "--robot", ROBOT, "--wait", "60", "--out", str(truth_path),
            "--batch-ms", str(drive.batch_ms),
            "--json", *(["--realistic"] if drive.realistic else []), *client])
        while drivers.running:
            progress(watched)
            time.sleep(0.25)
        if drivers.proc.returncode != 0:
            raise DemoError(f"the drivers failed: {drivers.stderr_tail()}")
        # the last batches reach the fusion node and the recorder
        n_before = -1
        while len(watched.joints) != n_before:
            n_before = len(watched.joints)
            time.sleep(1.0)
        machine = {"cpus": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2),
                   "serve_cpu_s": cpu_seconds(serve.proc.pid),
                   "serve_wall_s": round(time.monotonic() - serve_t0, 1)}
        ch.stop_all(children=[serve, record])
        for s in subs:
            s.undeclare()
    ch.stop_all(children=[r])
    for name, child in (("fusion node", serve), ("recorder", record)):
        if child.proc.returncode != 0:
            raise DemoError(f"the {name} failed: {child.stderr_tail()}")
    del zenoh
    return {"drivers": json.loads(drivers.stdout_path.read_text()),
            "serve": json.loads(serve.stdout_path.read_text()),
            "record": json.loads(record.stdout_path.read_text()),
            "watched": watched, "truth_path": truth_path, "recording": rec_path, "machine": machine}


# --- the figures of merit ---------------------------------------------------------------------


LATENCY_SETTLE_S = 10.0  # tracking time after which the latency is also given on its own


def evaluate(live: dict[str, Any]) -> dict[str, Any]:
    """Accuracy against the truth, flags, counts and latency, as one JSON-ready document."""
    from armfusion.sensors.recording import read_recording

    truth = read_recording(live["truth_path"]).truth()
    tq, tb = truth["true_q"], truth["true_base"]
    w: Watched = live["watched"]
    if not w.joints:
        raise DemoError("no joint state reached the consumer: "
                        + (live["serve"].get("message") or "the fusion node said nothing"))
    arrived = np.array([a for a, _ in w.joints])
    js = [j for _, j in w.joints]
    names = list(js[0].joint_names)
    sidecar = truth_path(live["truth_path"])
    if sidecar.exists():  # score against the angle gravity can find: true angle + DH zero offset
        tq = angle_truth(tq, json.loads(sidecar.read_text(encoding="utf-8")), names)
    t = np.array([j.t_s for j in js])
    q = np.array([j.q_rad for j in js])
    sig = np.array([j.sigma_rad for j in js])
    flags = np.array([j.flags for j in js])
    # the truth interpolated to each estimate's instant: the fake drivers read each device at
    # an instant of its own, between the simulator's 100 Hz grid points
    err_deg = np.degrees(q - truth_at(tq, t))
    joints = joint_scores(names, t, err_deg, sig, flags)
    heading_rms, heading_within, heading_status = heading_scores(w.headings, tb)
    tilt_true = truth_at(tb, t, angles=True)[:, :2] if tb is not None else np.full((len(t), 2), np.nan)
    combos = score_combinations([j.combinations for j in js], t, truth_at(tq, t), tilt_true, names)
    drv, srv, rec = live["drivers"], live["serve"], live["record"]
    latency = latency_figures(arrived, t, drv.get("epoch_monotonic_s"), LATENCY_SETTLE_S)
    return {
        "joint_names": names,
        "startup": {"t_s": float(srv.get("startup_t_s") or t[0]), "message": srv.get("message", ""),
                    "joints": joints["startup"]},
        "tracking": {"t_start_s": float(t[0]), "t_end_s": float(t[-1]), "estimates": int(len(t)),
                     "rms_error_deg": joints["rms"], "max_error_deg": joints["worst"],
                     "within_3_sigma": joints["within"], "from_first_ok": joints["once_ok"],
                     "heading_rms_deg": heading_rms, "heading_within_3_sigma": heading_within,
                     "heading_status": heading_status, "combinations": combos},
        "flags_seen": joints["seen"],
        "samples": sample_counts(drv, srv, rec, len(t)),
        "latency": latency,
        "machine": live.get("machine"),
        "_series": {"t": t, "q": q, "sigma": sig, "flags": flags, "truth_q": tq, "truth_base": tb,
                    "headings": [(h.t_s, h.heading_rad, h.heading_sigma_rad) for _, h in w.headings]},
    }


# --- the workbench and the report -------------------------------------------------------------


def workbench(calibration_rec: Path, identification: dict, window: int = 25):
    """The workbench on the calibration recording: the shipped model's diagnosis (verdict,
    ranked missing effects) and the error ladder (shipped model → + the identified effects)."""
    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.identification.identify import data_from_recording
    from armfusion.fusion.workbench.diagnose import diagnose
    from armfusion.models.effects import model_from_arm
    from armfusion.sensors.recording import read_recording

    arm = load_arm("wmra")
    data = data_from_recording(arm, read_recording(calibration_rec), window=window)
    before = diagnose(model_from_arm(arm), data)
    free = sum(1 for p in identification["parameters"] if not p["held"])
    n_res = int(identification["n_residuals"])
    # the identification's fit on the same points, as diagnose's rms_ratio: sqrt(chi2 / residuals)
    ratio = math.sqrt(float(identification["chi2_red"]) * max(n_res - free, 1) / max(n_res, 1))
    ladder = [{"label": "wmra as shipped", "rms_ratio": round(before.rms_ratio, 5), "effects": []},
              {"label": "+ identified effects (calibrated.yaml)", "rms_ratio": round(ratio, 5),
               "effects": sorted({p["name"].split("[")[0] for p in identification["parameters"]})}]
    return before, ladder


# --- the command ------------------------------------------------------------------------------


def demo_command(
    duration_s: Annotated[float, typer.Option(
        "--duration", help="Seconds of the live run (wall clock).")] = 60.0,
    seed: SeedOpt = 0,
    realistic: Annotated[bool, typer.Option(
        "--realistic/--ideal", help="Datasheet-typical sensor errors (default) or none.")] = True,
    calibrate_sensors: Annotated[bool, typer.Option(
        "--calibrate/--no-calibrate", help="First identify the sensors' errors on the calibration "
        "maneuver and serve with the calibrated config (default); else the shipped config.")] = True,
    calibration_s: Annotated[float | None, typer.Option(
        "--calibration-duration", help="Play only the calibration maneuver's poses within its first "
        "SECONDS (default: all of it, 60 s).")] = None,
    maneuver: Annotated[Path | None, typer.Option(
        "--maneuver", help="The calibration maneuver to play (armfusion plan-maneuver --config wmra "
        "--out M.yaml); default the shipped config/maneuvers/wmra-60s.yaml.")] = None,
    scenario: ScenarioOpt = "daily-use",
    run_workbench: Annotated[bool, typer.Option(
        "--workbench/--no-workbench", help="Diagnose the calibration recording for the report.")] = True,
    out: Annotated[Path, typer.Option(
        "--out", "-o", help="Directory for the recordings, the configs, the nodes' outputs and "
        "the report.")] = Path("armfusion-demo"),
    batch_ms: Annotated[float, typer.Option(
        "--batch-ms", help="The drivers' read time per published batch, ms (keep it well under "
        "the fusion node's 0.1 s reorder window, or samples arrive too late to fuse).")] = 20.0,
    json_out: JsonOpt = False,
) -> None:
    """The whole service on this machine, no hardware, loopback only: the simulated WMRA
    calibrates its sensors, then fake drivers → fusion node → recorder run as processes
    over Zenoh; a summary against the truth and an HTML report."""
    _check_options(duration_s, calibrate_sensors, calibration_s, batch_ms, scenario, out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    timings: dict[str, float] = {}
    show = not json_out

    def say(msg: str) -> None:
        if show:
            err_console.print(f"[bold]demo:[/] {msg}", highlight=False)

    # without --calibrate-sensors: the shipped config, nothing identified or played
    identification, calibration_rec, played, config = None, None, {}, "wmra"
    try:
        with Children(out / "nodes") as ch:
            if calibrate_sensors:
                with err_console.status("calibrating the sensors…", spinner="dots") if show \
                        else contextlib.nullcontext():
                    config, identification, calibration_rec, played = calibrate(
                        out, seed, calibration_s, realistic, ch, say, maneuver)
                timings["calibration_s"] = time.monotonic() - t0
                say(f"calibrated config: {config} (reduced chi-square "
                    f"{identification['chi2_red']:.2f}, {identification['seconds']:.0f} s fit)")
                if identification.get("compass_drive"):
                    say(identification["compass_drive"])
            say(f"live: router, recorder, fusion node and drivers over Zenoh on 127.0.0.1 "
                f"({duration_s:g} s of {scenario})")
            t1 = time.monotonic()
            with _live_bar(duration_s, show) as progress:
                live = run_live(out, LiveDrive(config, scenario, duration_s, seed, realistic, batch_ms), ch,
                                progress)
            timings["live_s"] = time.monotonic() - t1
    except DemoError as e:
        fail(str(e))
    t2 = time.monotonic()
    try:
        ev = evaluate(live)
    except DemoError as e:
        fail(str(e))
    diag = ladder = None
    if run_workbench and calibration_rec is not None:
        with err_console.status("the workbench: diagnosing the calibration recording…") if show \
                else contextlib.nullcontext():
            diag, ladder = workbench(calibration_rec, identification)
    doc = {"seed": seed, "realistic": realistic, "scenario": scenario, "duration_s": duration_s,
           "config": str(config), "out": str(out), "recording": str(live["recording"]),
           "calibration": _calibration_doc(identification, calibration_rec, config, played),
           **{k: v for k, v in ev.items() if not k.startswith("_")}}
    if diag is not None:
        doc["workbench"] = {"verdict": diag.verdict, "rms_ratio": diag.rms_ratio, "ladder": ladder}
    report = write_report(out / "report.html", doc, ev, diag, ladder)
    timings["report_s"] = time.monotonic() - t2
    timings["total_s"] = time.monotonic() - t0
    doc["report"] = str(report)
    doc["timings_s"] = {k: round(v, 1) for k, v in timings.items()}
    (out / "summary.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    if json_out:
        emit_json(doc)
        return
    say_summary(doc, ev, diag, ladder, f"report: {report}  (recording: {live['recording']}; "
                f"{timings['total_s']:.0f} s in all)")


def _check_options(duration_s: float, calibrate_sensors: bool, calibration_s: float | None,
                   batch_ms: float, scenario: str, out: Path) -> None:
    """Exit 2 before any work on an option out of its range."""
    if not duration_s >= 5:
        fail(f"--duration {duration_s!r}: expected at least 5 s (the arm is still for the first seconds)")
    if calibrate_sensors and calibration_s is not None and not calibration_s >= 15:
        fail(f"--calibration-duration {calibration_s!r}: expected at least 15 s")
    if not 1.0 <= batch_ms <= 1000.0:
        fail(f"--batch-ms {batch_ms!r}: expected 1 to 1000")
    if scenario not in SCENARIOS:
        fail(f"--scenario {scenario!r}: expected one of {', '.join(SCENARIOS)}")
    if out.exists() and not out.is_dir():
        fail(f"--out {out}: exists and is not a directory")


@contextlib.contextmanager
def _live_bar(duration_s: float, show: bool):
    """A progress bar of the live run (hidden unless ``show``): the ``progress(watched)``
    callback that updates it, and the bar completed at the end."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("{task.description}"), BarColumn(),
                  TextColumn("{task.fields[info]}"), TimeElapsedColumn(),
                  console=err_console, disable=not show, transient=False) as bar:
        task = bar.add_task("live", total=duration_s, info="starting the nodes")

        def progress(w: Watched) -> None:
            with w.lock:
                last = w.joints[-1][1] if w.joints else None
                n = len(w.joints)
                serve = w.status.get("serve")
                drv = w.status.get("drivers")
            published = 0 if drv is None else \
                sum(v for k, v in drv.counters if k.startswith("samples."))
            state = "" if serve is None else serve.state
            flags = "" if last is None else " ".join(
                f"{k} {v}" for k, v in Counter(last.flags).most_common())
            bar.update(task, completed=0.0 if last is None else min(last.t_s, duration_s),
                       info=f"{state} · {published} samples out · {n} estimates in · {flags}")

        yield progress
        bar.update(task, completed=duration_s)


def _calibration_doc(identification: dict | None, calibration_rec, config, played: dict) -> dict | None:
    """The summary's ``calibration``: what was played and identified (None: not calibrated)."""
    if identification is None:
        return None
    return {"recording": str(calibration_rec), "config": str(config), **played,
            "chi2_red": identification["chi2_red"],
            "compass": identification.get("compass_drive"),
            "unmodelled_g": identification.get("unmodelled_g")}


COMMAND_TABLE = (
    ("demo", demo_command),
)
"""The demo's command: each command's name and its function."""


def register(app: typer.Typer) -> None:
    """Add the commands of :data:`COMMAND_TABLE` to ``app``."""
    for name, command in COMMAND_TABLE:
        app.command(name)(command)
