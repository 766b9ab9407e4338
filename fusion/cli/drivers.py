"""``armfusion drivers``: read the rig's sensors through the real drivers, and report.

    armfusion drivers --fake [--config wmra] [--scenario startup] [--duration 10]
        [--rate 100] [--seed 0] [--realistic] [--effect …] [--effects-file F]
        [--no-noise] [--fault SPEC …] [--out REC.csv|REC.mcap] [--realtime] [--json]
    armfusion drivers [--config wmra] [--duration 10] [--rate 100] [--out REC.csv] [--json]

Without ``--fake`` the devices of the config's ``bus:`` entries are opened on the real
buses (smbus2, spidev). A device that cannot be opened or does not answer gives one line
each, and the exit code is 2.

With ``--fake`` the same driver code runs against the register-level fakes
(:class:`~armfusion.sensors.fakes.FakeRig`), whose physics come from the simulator
(:mod:`armfusion.models.fake_rig`): the scenario, the effects and the seed mean what they mean for
``armfusion simulate``. The sampling loop runs on a :class:`~armfusion.sensors.fakes.FakeClock`, as
fast as the host can (the buses' wire time still counts), or on the wall clock with
``--realtime``. The encoders come from a :class:`~armfusion.sensors.encoders.SimulatedEncoderFeed`
of the simulator's counts. ``--fault`` injects bus and device faults on the fakes
(:mod:`armfusion.fusion.cli.drivers_faults`). Recording times are seconds since the rig powered up
(the scenario's t = 0); ``--out`` writes the recording and, with ``--fake``, its truth file.
``--scenario``, ``--seed``, ``--realistic``, ``--effect``, ``--effects-file``, ``--no-noise``,
``--fault`` and ``--realtime`` apply with ``--fake`` only (given without it: exit 2).

This module is the command; the runs are :mod:`armfusion.fusion.cli.drivers_run` (``run_fake``,
``run_real``), the report :mod:`armfusion.fusion.cli.drivers_report`.

The report: per device, the samples collected, read time, jitter, bus errors, retries and
the drivers' other counters (stale, overruns, offline, re-initialisations…). See
docs/drivers.md, "armfusion drivers".
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer
from armfusion.fusion.cli.common import check_output_path, config_file, emit_json, fail, progress_bar
from armfusion.fusion.cli.drivers_faults import FAULT_KINDS
from armfusion.fusion.cli.drivers_report import print_report, summary
from armfusion.fusion.cli.drivers_run import DriversRun, FakeRigOptions, LiveFeed, run_fake, run_real
from armfusion.fusion.cli.options import (
    ADMITTED_WITHIN_S,
    AdmittedWithinOpt,
    BatchMsOpt,
    ConfigOpt,
    ConnectOpt,
    EffectOpt,
    EffectsFileOpt,
    JsonOpt,
    ListenOpt,
    ModeOpt,
    NoiseOpt,
    RealisticOpt,
    RecordingOutOpt,
    ScenarioOpt,
    SeedOpt,
    ZenohConfigOpt,
    check_robot,
)
from armfusion.fusion.cli.simulate import truth_json, truth_path
from armfusion.models.arm_config import ConfigError
from armfusion.sensors.bus import DeviceNotFoundError
from armfusion.sensors.output_files import write_text_replacing
from armfusion.sensors.recording import SUFFIXES, write_recording


@dataclass(frozen=True)
class DriverOptions:
    """What ``armfusion drivers`` reads: the ``config``'s devices for ``duration_s`` at
    ``rate_hz``, on the fakes of the simulated ``rig`` (``fake``) or the real buses (where
    the rig's options, given, are an error)."""

    fake: bool
    config: str | Path
    duration_s: float
    rate_hz: float
    rig: FakeRigOptions


@dataclass
class _Live:
    publisher: Any
    stop: threading.Event
    batch_s: float
    watch: Any = None
    admission: Any = None
    """The fusion node's admission of what was published (armfusion.fusion.service.admitted), at the end."""

    def on_batch(self, streams) -> None:
        if self.watch is not None and not self.watch.started:
            self.watch.start()
        self.publisher.publish(streams)


@contextlib.contextmanager
def _publishing(robot: str, batch_ms: float, wait_s: float, admitted_within_s: float,
                zenoh_config: Path | None, listen: list[str] | None, connect: list[str] | None,
                mode: str | None) -> Iterator[_Live]:
    """A Zenoh session and a :class:`~armfusion.fusion.service.raw_publisher.RawPublisher` for
    ``--robot``; SIGINT and SIGTERM stop the run, and so does the fusion node's admitting
    none of the samples within ``admitted_within_s`` (the verdict: ``_Live.admission``);
    the last status says ``done``."""
    from armfusion.fusion.cli.nodes import session_or_exit, watching_admission, zenoh_settings
    from armfusion.fusion.service.node import stop_on_signals
    from armfusion.fusion.service.raw_publisher import RawPublisher

    if wait_s < 0:
        fail(f"--wait {wait_s!r}: expected >= 0")
    stop = threading.Event()
    with session_or_exit(zenoh_settings(zenoh_config, listen, connect, mode)) as session, \
            stop_on_signals(stop), watching_admission(session, robot, admitted_within_s, stop) as watch:
        publisher = RawPublisher(session, robot, message="publishing raw samples")
        if wait_s:
            publisher.wait_for_subscriber("imu_acc", wait_s, stop)
        publisher.status("running", "publishing raw samples")
        live = _Live(publisher, stop, batch_ms / 1000.0, watch)
        try:
            yield live
        finally:
            if watch is not None:
                live.admission = watch.finish(stop)
            n = sum(publisher.samples.values())
            publisher.close(("stopped: " if stop.is_set() else "") + f"published {n} samples")


def drivers_command(
    fake: Annotated[bool, typer.Option("--fake", help="Read register-level fake devices fed by "
                                       "the simulator instead of the real buses.")] = False,
    config: ConfigOpt = "wmra",
    scenario: ScenarioOpt = "startup",
    duration: Annotated[float, typer.Option("--duration", help="Seconds to read.")] = 10.0,
    rate: Annotated[float, typer.Option("--rate", help="Loop rate [Hz] (also the ADXL345s' "
                                        "output data rate: 12.5 … 3200).")] = 100.0,
    seed: SeedOpt = 0,
    realistic: RealisticOpt = False,
    effect: EffectOpt = None,
    effects_file: EffectsFileOpt = None,
    noise: NoiseOpt = True,
    fault: Annotated[list[str] | None, typer.Option("--fault", help="With --fake: TARGET:KIND"
                                                    "[=VALUE][@T0[-T1]], repeatable. Kinds: " + "; ".join(
                                                        f"{k}: {v}" for k, v in FAULT_KINDS.items()))] = None,
    out: RecordingOutOpt = None,
    realtime: Annotated[bool, typer.Option("--realtime", help="With --fake: run on the wall "
                                           "clock instead of as fast as possible.")] = False,
    json_out: JsonOpt = False,
    robot: Annotated[str | None, typer.Option("--robot", callback=check_robot, help=(
        "Publish the raw samples over Zenoh on armfusion/<robot>/raw/<sensor> as they are "
        "read."))] = None,
    batch_ms: BatchMsOpt = 20.0,
    wait_s: Annotated[float, typer.Option("--wait", help="With --robot: first wait up to this long "
                                          "for a subscriber to the raw samples, in s.")] = 0.0,
    admitted_within_s: AdmittedWithinOpt = ADMITTED_WITHIN_S,
    zenoh_config: ZenohConfigOpt = None,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
) -> None:
    """Read the sensors through the drivers (or, with --fake, the simulator-fed fakes) and
    report read time, jitter, errors and samples per device; with --robot, publish the raw
    samples over Zenoh as they are read.

    The options of the simulated rig (--scenario … --fault, --realtime) apply with --fake
    only."""
    if out is not None:
        check_output_path(out, "--out", SUFFIXES, inputs=(config_file(config),))
        if fake:
            check_output_path(truth_path(out), "--out", inputs=(config_file(config),))
    if robot is None:
        given = [o for o, v in (("--listen", listen), ("--connect", connect), ("--mode", mode),
                                ("--zenoh-config", zenoh_config), ("--wait", wait_s)) if v]
        if given:
            fail(f"{', '.join(given)}: only with --robot (which publishes over Zenoh)")
        publishing = contextlib.nullcontext(None)
    else:
        publishing = _publishing(robot, batch_ms, wait_s, admitted_within_s, zenoh_config, listen,
                                 connect, mode)
    rig = FakeRigOptions(scenario, seed, realistic, tuple(effect or ()), effects_file, noise,
                         tuple(fault or ()), realtime)
    with publishing as live, progress_bar("reading the fakes", json_out or not fake) as advance:
        run = _run(DriverOptions(fake, config, duration, rate, rig), live, advance)
    doc = summary(run)
    if live is not None:
        admission = live.admission
        doc["published"] = {"robot": robot, "samples": live.publisher.samples,
                            "batches": live.publisher.batches,
                            "admission": None if admission is None else admission.as_dict()}
    _finish(doc, run, out, json_out)
    if live is not None:
        from armfusion.fusion.cli.nodes import say_admission

        if not json_out:
            say_admission(live.admission)
        if live.admission is not None and live.admission.state == "refused":
            fail(live.admission.message, code=1)

def _run(options: DriverOptions, live: _Live | None, advance) -> DriversRun:
    """The run ``options`` asks for, its samples handed to ``live`` (``None``: not published)
    as they are read and, on the fakes, its progress to ``advance``; a bad option or a device
    that cannot be opened exits 2 with its message."""
    feed = LiveFeed() if live is None else LiveFeed(live.on_batch, live.batch_s, live.stop)
    rig = options.rig
    try:
        if options.fake:
            return run_fake(options.config, rig, options.duration_s, options.rate_hz, live=feed,
                            progress=advance)
        else:
            ignored = [o for o, v in (("--scenario", rig.scenario != "startup"), ("--seed", rig.seed != 0),
                                      ("--realistic", rig.realistic), ("--effect", bool(rig.effects)),
                                      ("--effects-file", rig.effects_file is not None),
                                      ("--fault", bool(rig.faults)), ("--realtime", rig.realtime)) if v]
            if ignored:
                fail(f"{', '.join(ignored)} only appl{'y' if len(ignored) > 1 else 'ies'} "
                     "with --fake")
            return run_real(options.config, options.duration_s, options.rate_hz, live=feed)
    except (DeviceNotFoundError, ConfigError, FileNotFoundError, ValueError) as e:
        fail(str(e))
    raise AssertionError("unreachable")  # fail() exits


def _finish(doc: dict[str, Any], run: DriversRun, out: Path | None, json_out: bool) -> None:
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_recording(run.recording, out)
        doc["out"] = str(out)
        if run.sim is not None:
            tp = truth_path(out)
            truth = {**run.sim.truth, "duration_s": run.recording.t_end_s,
                     "simulated_s": run.sim.truth["duration_s"], "streams": doc["streams"]}
            write_text_replacing(tp, truth_json(truth))
            doc["truth"] = str(tp)
    if json_out:
        emit_json(doc)
        return
    print_report(doc)


COMMAND_TABLE = (
    ("drivers", drivers_command),
)
"""The drivers' command: each command's name and its function."""


def register(app: typer.Typer) -> None:
    """Add the commands of :data:`COMMAND_TABLE` to ``app``."""
    for name, command in COMMAND_TABLE:
        app.command(name)(command)
