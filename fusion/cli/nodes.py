"""The service's ``armfusion`` subcommands: ``replay``, ``record``, ``serve``, ``recalibrate``,
``maneuver`` (and their shared options).

Every node takes the same Zenoh options: ``--zenoh-config`` (default config/zenoh.json5:
peer, listening on tcp/127.0.0.1:7447, no scouting), ``--listen`` and ``--connect``
(repeatable; loopback only; each replaces the file's endpoints) and ``--mode``. Without
``--zenoh-config``, a node given ``--connect`` but no ``--listen`` listens on an ephemeral
loopback port, so that it does not compete for 7447 with the node it connects to. See
docs/reference/service.md, "Zenoh configuration".
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer
import zenoh
from armfusion.fusion.cli.common import (
    beside_existing,
    check_output_path,
    choice_or_exit,
    config_file,
    console,
    emit_json,
    err_console,
    fail,
    load_arm_or_exit,
    prepare_output_path,
    read_recording_or_exit,
)
from armfusion.fusion.cli.options import (
    ADMITTED_WITHIN_S,
    AdmittedWithinOpt,
    BatchMsOpt,
    ConfigOpt,
    ConnectOpt,
    JsonOpt,
    ListenOpt,
    ModeOpt,
    RecordingArg,
    RobotOpt,
    StopAfterOpt,
    ZenohConfigOpt,
)
from armfusion.fusion.service.admitted import Admission, AdmissionWatch
from armfusion.fusion.service.node import stop_after, stop_on_signals
from armfusion.fusion.service.zenoh_config import ZenohConfigError, ZenohSettings, endpoints_line, load_config

DEFAULT_ROBOT = "chair1"
EPHEMERAL_LISTEN = "tcp/127.0.0.1:0"


def zenoh_settings(config: Path | None, listen: list[str] | None, connect: list[str] | None,
                   mode: str | None) -> ZenohSettings:
    """The node's settings from its options: ``--listen`` and ``--connect`` replace the
    file's endpoints; otherwise a ``--zenoh-config`` file's own are used as written. Without
    one (the default config listens on 7447), ``--connect`` alone gets an ephemeral listen
    port and a client listens nowhere."""
    listen_override = list(listen) if listen else None
    if listen_override is None and config is None:
        if mode == "client":
            listen_override = []
        elif connect:
            listen_override = [EPHEMERAL_LISTEN]
    return ZenohSettings(config_path=config, listen=listen_override,
                         connect=list(connect) if connect else None, mode=mode)


@contextlib.contextmanager
def session_or_exit(settings: ZenohSettings, *, say_endpoints: bool | None = None) -> Iterator[zenoh.Session]:
    """A session of ``settings``, or exit 2 saying why none opens. ``say_endpoints`` (by
    default: when a ``--zenoh-config`` file is given) prints where it listens and connects,
    and whether the file or the command line said so, on stderr."""
    try:
        config = load_config(settings)
        if say_endpoints if say_endpoints is not None else settings.config_path is not None:
            err_console.print(endpoints_line(config, settings), highlight=False, soft_wrap=True)
        session = zenoh.open(config)
    except ZenohConfigError as e:
        fail(str(e))
    except zenoh.ZError as e:
        fail(f"cannot open the Zenoh session: {e}")
    try:
        yield session
    finally:
        session.close()


@contextlib.contextmanager
def watching_admission(session: zenoh.Session, robot: str, timeout_s: float,
                       stop: threading.Event) -> Iterator[AdmissionWatch | None]:
    """A publisher's :class:`~armfusion.fusion.service.admitted.AdmissionWatch` (``None`` when
    ``timeout_s`` is 0: no check), the fusion node's first status awaited; ``stop`` is set
    as soon as the watch finds that nothing was admitted."""
    if timeout_s == 0:
        yield None
        return
    watch = AdmissionWatch(session, robot, timeout_s)
    watch.wait_for_node(stop)
    done = threading.Event()

    def guard() -> None:
        while not done.wait(0.1):
            verdict = watch.check()
            if verdict is not None:
                if verdict.state == "refused":
                    stop.set()
                return

    thread = threading.Thread(target=guard, name="admission watch", daemon=True)
    thread.start()
    try:
        yield watch
    finally:
        done.set()
        thread.join()
        watch.close()


def say_admission(admission: Admission | None) -> None:
    """One line on stderr when the fusion node's admission of what was sent is not known."""
    if admission is not None and admission.state == "unknown":
        err_console.print(f"[yellow]note:[/] {admission.message}", highlight=False)


def parse_speed(text: str) -> float | None:
    if text.strip().lower() == "max":
        return None
    try:
        speed = float(text)
    except ValueError:
        speed = -1.0
    if not speed > 0:
        fail(f"--speed {text!r}: expected a factor > 0 (1 = real time) or 'max'")
    return speed


def _write_ros2(recording: Path, out: Path, arm_name: str) -> dict:
    """The estimates recorded in ``recording`` as the ROS 2 bag ``out`` (written under a
    temporary name, renamed when complete); exits 1 naming why when there are none."""
    from armfusion.fusion.ros2.from_records import RecordsError, write_ros2_from_records
    from armfusion.sensors.output_files import replaced_when_done

    try:
        with replaced_when_done(out) as tmp:
            run, left_out, counts = write_ros2_from_records(recording, tmp, Path(arm_name).stem)
    except RecordsError as e:
        fail(f"--ros2-out: {e}", code=1)
    return {"path": str(out), "instants": run.steps, "left_out": left_out, "messages": counts}


def replay_command(
    recording: RecordingArg,
    speed: Annotated[str, typer.Option(help="Time factor (1 = real time, 2 = twice as fast) "
                                            "or 'max' (as fast as the subscribers take).")] = "1",
    robot: RobotOpt = DEFAULT_ROBOT,
    batch_ms: BatchMsOpt = 20.0,
    wait_s: Annotated[float, typer.Option(
        "--wait", help="First wait up to this long for a subscriber on every sensor, in s; "
                       "if no sensor has one by then, publish nothing and exit 1.")] = 5.0,
    admitted_within_s: AdmittedWithinOpt = ADMITTED_WITHIN_S,
    zenoh_config: ZenohConfigOpt = None,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Publish a recording's raw samples on armfusion/<robot>/raw/<sensor>, with their timing.

    Exits 1 when an MCAP file ends early or is damaged, or holds a sample topic the reader
    cannot take (what could be read is replayed)."""
    from armfusion.fusion.service.replay import NoSubscriberError, ReplayPacing, replay

    factor = parse_speed(speed)
    if not (math.isfinite(wait_s) and wait_s >= 0):
        fail(f"--wait {wait_s!r}: expected a number of seconds >= 0")
    rec = read_recording_or_exit(recording)
    stop = threading.Event()
    with session_or_exit(zenoh_settings(zenoh_config, listen, connect, mode)) as session, \
            stop_on_signals(stop), watching_admission(session, robot, admitted_within_s, stop) as watch:
        try:
            pacing = ReplayPacing(speed=factor, batch_s=batch_ms / 1000.0, wait_for_subscribers_s=wait_s,
                                  require_subscriber=True)
            report = replay(session, rec, robot, pacing, stop=stop,
                            on_start=None if watch is None else watch.start)
        except NoSubscriberError as e:
            fail(str(e), code=1)
        except ValueError as e:
            fail(f"{recording}: {e}")
        admission = None if watch is None else watch.finish(stop)
    doc = {"recording": str(recording), **report.as_dict(),
           "admission": None if admission is None else admission.as_dict()}
    if json_out:
        emit_json(doc)
    else:
        console.print(f"replayed {sum(report.samples.values())} samples of {len(report.samples)} "
                      f"sensors as {robot} in {report.wall_s:.2f} s ({report.batches} batches)"
                      + (" [yellow]stopped early[/]" if report.stopped else ""))
        if report.unmatched:
            err_console.print(f"[yellow]warning:[/] no subscriber for {', '.join(report.unmatched)} "
                              f"after {wait_s:g} s")
        say_admission(admission)
    if admission is not None and admission.state == "refused":
        fail(admission.message, code=1)
    read = rec.meta.get("read_report")
    if read is not None and not read.complete:  # the samples after the damage are lost
        fail(f"replayed only what could be read: {read.message}", code=1)
    if read is not None and read.left_out:  # a sample topic the reader cannot take was not sent
        fail(f"replayed only what could be read: {recording}: left out {read.left_out_words()}", code=1)
    if report.unheard:
        total = sum(report.samples.values())
        fail(f"{sum(report.unheard.values())} of {total} samples went out while nothing subscribed "
             f"to their key ({', '.join(f'{k} {n}' for k, n in report.unheard.items())}): the "
             "subscriber left or never came", code=1)

def _check_state_file(path: Path, inputs) -> None:
    """Exit 2 unless ``serve --state-file`` may be written over: a place where a file can be
    made (:func:`check_output_path`), not one of the node's inputs, and either no file yet or a
    saved fusion state (of any version: it is read, or said stale, and replaced). A device such
    as /dev/zero, a FIFO, or a file that is no fusion state (a recording; the node writes its
    state whole, so a power cut leaves none half written) is never replaced."""
    import json

    from armfusion.fusion.configfile import read_bounded
    from armfusion.fusion.service.state_file import STATE_FORMAT

    check_output_path(path, "--state-file", inputs=inputs)
    if not path.exists():
        return
    if not path.is_file():
        fail(f"--state-file {path}: not a regular file (a device, a FIFO); the node would replace it")
    try:
        doc = json.loads(read_bounded(path, 64 << 20, "a saved state"))
    except (OSError, ValueError):
        doc = None
    if not (isinstance(doc, dict) and str(doc.get("format", "")).startswith(STATE_FORMAT.split("/")[0])):
        fail(f"--state-file {path}: holds something other than a saved fusion state; the node would "
             "replace it: give another path, or remove the file")


def record_command(
    out: Annotated[Path, typer.Argument(help="Output recording (.mcap).")],
    robot: RobotOpt = DEFAULT_ROBOT,
    duration_s: StopAfterOpt = None,
    arm_config: Annotated[str, typer.Option("--config", "-c", help="Arm config name stored "
                                            "in the file's metadata.")] = "",
    ros2_out: Annotated[Path | None, typer.Option(
        "--ros2-out", help="When the recording stops, also write its estimates to EST.ros2.mcap: a "
                           "rosbag2 of ROS 2 messages (joint states, heading as sensor_msgs/Imu, "
                           "diagnostics; docs/ros2.md).")] = None,
    zenoh_config: ZenohConfigOpt = None,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Record a robot's raw samples and estimates from Zenoh to MCAP until stopped."""
    from armfusion.fusion.service.record import Recorder

    if out.suffix.lower() != ".mcap":
        fail(f"{out}: the recording must end in .mcap")
    out = beside_existing(out, "OUT")
    prepare_output_path(out, "OUT")
    if ros2_out is not None:
        if not ros2_out.name.lower().endswith(".ros2.mcap"):
            fail(f"--ros2-out {ros2_out}: a ROS 2 bag's name ends in .ros2.mcap")
        ros2_out = beside_existing(ros2_out, "--ros2-out")
        if ros2_out.resolve() == out.resolve():
            fail(f"--ros2-out {ros2_out}: the same file as the recording")
        prepare_output_path(ros2_out, "--ros2-out")
    stop = threading.Event()
    with session_or_exit(zenoh_settings(zenoh_config, listen, connect, mode)) as session, \
            stop_on_signals(stop), stop_after(duration_s, stop):
        recorder = Recorder(session, out, robot, arm_config=arm_config)
        threading.Thread(target=_say_ready, args=(recorder, robot, out), daemon=True).start()
        report = recorder.run(stop)
    ros2 = None if ros2_out is None else _write_ros2(out, ros2_out, arm_config or robot)
    if json_out:
        emit_json({**report.as_dict(), **({} if ros2 is None else {"ros2": ros2})})
        return
    console.print(f"recorded {sum(report.samples.values())} samples of {len(report.samples)} "
                  f"sensors and {sum(report.estimates.values())} estimates to {out} "
                  f"in {report.wall_s:.1f} s; dropped: "
                  + (", ".join(f"{k} {v}" for k, v in report.dropped.items()) or "none"))
    if ros2 is not None:
        console.print(f"wrote {ros2['instants']} estimates to {ros2['path']} as a ROS 2 bag "
                      f"({', '.join(f'{k} {v}' for k, v in ros2['messages'].items())})"
                      + (f"; {ros2['left_out']} heading(s) without their joints left out"
                         if ros2["left_out"] else ""))

def serve_command(
    config: ConfigOpt = "wmra",
    robot: RobotOpt = DEFAULT_ROBOT,
    publish_hz: Annotated[float, typer.Option(help="Most estimates published per second "
                                                   "of sample time.")] = 50.0,
    duration_s: StopAfterOpt = None,
    state_file: Annotated[Path | None, typer.Option(
        "--state-file", help="Save the tracker's state here (every --save-every s and at stop) "
                             "and resume from it at start when the encoders kept counting.")] = None,
    save_every_s: Annotated[float, typer.Option(
        "--save-every", help="Seconds (wall time) between saves of --state-file.")] = 1.0,
    state_max_age_s: Annotated[float, typer.Option(
        "--state-max-age", help="A saved state older than this (s) is stale: calibrate "
                                "on a still arm instead.")] = 60.0,
    assume_parked: Annotated[bool, typer.Option(
        "--assume-parked", help="Take the ready pose as evidence at the startup (the arm is "
                                "known to power up parked there): it picks the branches the "
                                "still data cannot tell apart, and the status says so.")] = False,
    maneuver: Annotated[Path | None, typer.Option(
        "--maneuver", help="A planned calibration maneuver (plan-maneuver --out) to publish on "
                           "armfusion/<robot>/maneuver for the arm's controller; the node keeps "
                           "the samples between its start and done requests and runs calibrate "
                           "sensors on them (it never moves the arm, and tracks with the "
                           "config it writes only when asked: armfusion maneuver apply).")] = None,
    maneuver_dir: Annotated[Path, typer.Option(
        "--maneuver-dir", help="Where the maneuver's recording and calibrated config are "
                               "written.")] = Path("maneuver-runs"),
    maneuver_effects: Annotated[str | None, typer.Option(
        "--maneuver-effects", help="calibrate sensors --effects for the maneuver's fit (default: "
                                   "the config's, else all).")] = None,
    maneuver_reference: Annotated[list[str] | None, typer.Option(
        "--maneuver-reference", help="calibrate sensors --reference for the maneuver's fit "
                                     "(JOINT=DEG[:SIGMA_DEG][@SECONDS|@segK], repeatable): the "
                                     "installer's one-time angles.")] = None,
    zenoh_config: ZenohConfigOpt = None,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """The fusion node: startup calibration on the first still window (or resume from
    --state-file), then the tracker; publishes armfusion/<robot>/state/joints,
    state/heading and status; answers armfusion/<robot>/calibrate (and, with --maneuver,
    serves a planned calibration maneuver on armfusion/<robot>/maneuver)."""
    from armfusion.fusion.service.serve import FusionNode
    from armfusion.fusion.service.serve_settings import NodeSettings

    if not publish_hz > 0:
        fail(f"--publish-hz {publish_hz!r}: expected > 0")
    if not save_every_s > 0 or not state_max_age_s > 0:
        fail(f"--save-every {save_every_s!r} and --state-max-age {state_max_age_s!r}: expected > 0")
    if state_file is not None:
        _check_state_file(state_file, (config_file(config), maneuver))
    settings = NodeSettings(publish_hz=publish_hz, state_path=state_file, save_period_s=save_every_s,
                            max_state_age_s=state_max_age_s, assume_parked=assume_parked)
    arm = load_arm_or_exit(config)
    served = None
    if maneuver is not None:
        served = _served_maneuver(arm, robot, config, maneuver, maneuver_dir, maneuver_effects,
                                  tuple(maneuver_reference or ()))
    stop = threading.Event()
    with session_or_exit(zenoh_settings(zenoh_config, listen, connect, mode)) as session, \
            stop_on_signals(stop), stop_after(duration_s, stop):
        node = FusionNode(session, arm, robot, settings, maneuver=served)
        threading.Thread(target=_say_serving, args=(node, robot, arm.name), daemon=True).start()
        report = node.run(stop)
    if json_out:
        emit_json(report.as_dict())
        return
    if report.resume_message:
        console.print(f"{robot}: {report.resume_message}")
    console.print(f"{robot}: {report.message}; {report.samples} samples in, {report.estimates} "
                  f"estimates out, {report.out_of_order} late samples dropped; dropped payloads: "
                  + (", ".join(f"{k} {v}" for k, v in report.dropped.items()) or "none"))


def recalibrate_command(
    robot: RobotOpt = DEFAULT_ROBOT,
    timeout_s: Annotated[float, typer.Option(
        "--timeout", help="Wait this long for the reply, in s.")] = 10.0,
    zenoh_config: ZenohConfigOpt = None,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Ask the fusion node (armfusion serve) to re-run the startup calibration now, on the
    latest still stretch; it refuses, saying why, while the arm moves. Exits 1 when refused."""
    from armfusion.fusion.service.requests import request_calibration

    reply = _node_reply(zenoh_settings(zenoh_config, listen, connect, mode), timeout_s,
                        lambda session: request_calibration(session, robot, timeout_s))
    if json_out:
        emit_json(reply.to_json())
    elif reply.ok:
        console.print(f"{robot}: calibrated on {reply.t_start_s:.2f}-{reply.t_end_s:.2f} s")
        for name, q, sig, flag in zip(reply.joint_names, reply.q_rad, reply.sigma_rad, reply.flags,
                                      strict=True):
            angle = "    —   " if q is None else f"{math.degrees(q):8.3f}°"
            sigma = "" if sig is None else f" ± {math.degrees(sig):.3f}°"
            console.print(f"  {name:>4} {angle}{sigma}  {flag}", highlight=False)
    else:
        err_console.print(f"{robot}: calibration refused: {reply.message}", highlight=False)
    if not reply.ok:
        raise typer.Exit(1)


def maneuver_command(
    request: Annotated[str, typer.Argument(help="show (the plan and its run), start (about to play "
                                                "it: keep the samples), done (played: fit them), "
                                                "abort, or apply (track with the config the fit "
                                                "wrote, once reviewed).")] = "show",
    robot: RobotOpt = DEFAULT_ROBOT,
    timeout_s: Annotated[float, typer.Option(
        "--timeout", help="Wait this long for the reply, in s.")] = 10.0,
    zenoh_config: ZenohConfigOpt = None,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """The planned calibration maneuver the fusion node serves (serve --maneuver), as the arm's
    controller sees it: show it, or say the controller starts it, is done with it (the node
    then fits the sensors on it) or aborts it; apply the fit's config. Exits 1 when the node
    refuses."""
    from armfusion.fusion.service.payloads import MANEUVER_ACTIONS
    from armfusion.fusion.service.requests import request_maneuver

    choice_or_exit(request, "REQUEST", ("show", *MANEUVER_ACTIONS))
    action = None if request == "show" else request
    reply = _node_reply(zenoh_settings(zenoh_config, listen, connect, mode), timeout_s,
                        lambda session: request_maneuver(session, robot, action, timeout_s))
    if json_out:
        emit_json(reply.to_json())
    else:
        plan = reply.plan
        console.print(f"{robot}: maneuver {reply.state}: {reply.message}", highlight=False)
        if request == "show":
            for k, ((_, t0, t1), q) in enumerate(zip(plan.schedule(), plan.poses_rad, strict=True)):
                console.print(f"  pose {k:>2} at {t0:6.2f}-{t1:6.2f} s: "
                              + " ".join(f"{math.degrees(v):8.3f}" for v in q), highlight=False)
    if not reply.accepted:
        raise typer.Exit(1)


COMMAND_TABLE = (
    ("replay", replay_command),
    ("record", record_command),
    ("serve", serve_command),
    ("recalibrate", recalibrate_command),
    ("maneuver", maneuver_command),
)
"""The service's node commands: each command's name and its function."""


def register(app: typer.Typer) -> None:
    """Add the commands of :data:`COMMAND_TABLE` to ``app``."""
    for name, command in COMMAND_TABLE:
        app.command(name)(command)


def _node_reply(settings: ZenohSettings, timeout_s: float, ask):
    """``ask(session)``'s reply from the fusion node, or exit 2 saying why there is none."""
    from armfusion.fusion.service.payloads import PayloadError
    from armfusion.fusion.service.requests import NoReplyError

    if not timeout_s > 0:
        fail(f"--timeout {timeout_s!r}: expected > 0")
    with session_or_exit(settings) as session:
        try:
            return ask(session)
        except (NoReplyError, PayloadError) as e:
            fail(str(e))


def _served_maneuver(arm, robot: str, config: str, maneuver: Path, out_dir: Path, effects: str | None,
                     references: tuple[str, ...]):
    """``serve --maneuver``'s plan, checked safe for ``arm``, ready to serve (or exit 2, saying why)."""
    from armfusion.fusion.configfile import resolve_config_path
    from armfusion.fusion.identification.planner import safe_maneuver
    from armfusion.fusion.service.maneuver import ManeuverSettings, ServedManeuver

    try:
        plan = safe_maneuver(arm, maneuver)
        config_path = resolve_config_path(config)
    except (FileNotFoundError, ValueError) as e:
        fail(f"--maneuver: {e}")
    return ServedManeuver(arm, robot, plan, config_path, ManeuverSettings(out_dir, effects, references))


def _say_serving(node, robot: str, arm_name: str) -> None:
    # (however long the kernels take to be ready: a busy machine's first run takes minutes)
    if node.ready.wait():
        err_console.print(f"serving {arm_name} as {robot}: armfusion/{robot}/raw/* in, state/joints, "
                          "state/heading and status out; Ctrl-C (SIGINT) or SIGTERM stops", highlight=False)


def _say_ready(recorder, robot: str, out: Path) -> None:
    if recorder.ready.wait(30.0):
        err_console.print(f"recording armfusion/{robot}/raw/* and state/* to {out}; "
                          "Ctrl-C (SIGINT) or SIGTERM stops", highlight=False)
