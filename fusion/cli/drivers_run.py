"""Reading the rig through the drivers: the real buses (:func:`run_real`) or the
register-level fakes fed by the simulator (:func:`run_fake`), for ``armfusion drivers``.

Both open the devices of the config's ``bus:`` entries (:func:`wiring_from_arm`), run one
:class:`~armfusion.sensors.sampling.SamplingLoop` over their readers (:func:`_sample`) and return a
:class:`DriversRun`: the loop's timing, every reader's results, the valid samples as a raw
recording (:func:`recording_from`) and each device's counters. With a :class:`LiveFeed` the
samples also go out as they are read (:class:`LiveSink`), which is how ``--robot``
publishes them; the fakes' simulated rig is a :class:`FakeRigOptions`. Recording times are seconds since the rig powered up (the scenario's
t = 0 with the fakes).
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from armfusion.fusion.cli.drivers_faults import FaultSchedule, FaultSpec, parse_fault
from armfusion.fusion.cli.simulate import check_run_size, effects_model
from armfusion.fusion.configfile import load_arm
from armfusion.models.arm import ArmModel
from armfusion.models.fake_rig import SimulatedRun, encoder_counts_at, physics_for, simulate_physics
from armfusion.models.trajectories import SCENARIOS
from armfusion.sensors.adxl345 import ADXL345, ADXL345Config, accel_stream
from armfusion.sensors.bus import DeviceNotFoundError
from armfusion.sensors.encoders import N_JOINTS, EncoderSample, SimulatedEncoderFeed, encoder_stream
from armfusion.sensors.fakes import FakeClock, FakeRig
from armfusion.sensors.mpu9150 import MPU9150, imu_streams
from armfusion.sensors.samples import Recording, Stream
from armfusion.sensors.sampling import (
    Collector,
    LoopReport,
    SamplingLoop,
    Wiring,
    close_all,
    open_devices,
    readers_for,
)

SIM_MARGIN_S = 2.0
"""Simulated beyond the run's duration: device initialisation (≈ 0.17 s: the MPU-9150's
reset and wake-up) comes before the first tick, and the scenario's t = 0 is power-up."""
ENCODER_READER = "enc"


# --- wiring -------------------------------------------------------------------------------


def wiring_from_arm(arm: ArmModel) -> tuple[tuple[Wiring, ...], list[str]]:
    """The devices of the config's ``bus:`` entries, and a note per sensor left out."""
    wiring: list[Wiring] = []
    notes: list[str] = []
    for s in arm.sensors:
        if not s.bus:
            notes.append(f"{s.name}: no bus entry in {arm.source}; not read")
            continue
        if s.type not in ("adxl345", "mpu9150"):
            notes.append(f"{s.name}: no driver for a {s.type}; not read")
            continue
        wiring.append(Wiring.from_bus(s.name, s.type, s.bus))
    if not wiring:
        raise ValueError(f"{arm.source}: no ADXL345 or MPU-9150 with a 'bus:' entry; nothing to read")
    return tuple(wiring), notes


@dataclass(frozen=True)
class DriversRun:
    """What one run read and how it went.

    ``samples[name]``: what each reader returned, flattened; ``recording`` the valid
    samples as raw streams (times in seconds since ``epoch_s``, the rig's power-up),
    plus the truth streams with ``--fake``; ``health`` each device's counters at the end
    (the IMU's magnetometer as ``<imu>.mag``).
    """

    mode: str  # "fake" or "real"
    arm: ArmModel
    wiring: tuple[Wiring, ...]
    rate_hz: float
    duration_s: float
    epoch_s: float
    loop: LoopReport
    samples: Mapping[str, list[Any]]
    recording: Recording
    health: Mapping[str, Any]
    encoder_stats: Any = None
    notes: list[str] = field(default_factory=list)
    faults: list[FaultSpec] = field(default_factory=list)
    faults_injected: int = 0
    sim: SimulatedRun | None = None
    rig: FakeRig | None = None
    settings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class FakeRigOptions:
    """The simulated rig behind the fakes (``armfusion drivers --fake``): the ``scenario``, the
    ``seed``, ``realistic`` and the ``effects`` (``--effect`` specs) and ``effects_file`` mean what
    they mean for ``armfusion simulate``; ``noise``: the sensors' noise on; ``faults``: bus and
    device faults to inject (``--fault`` specs or parsed,
    :mod:`armfusion.fusion.cli.drivers_faults`); ``realtime``: run on the wall clock instead of
    as fast as the host can."""

    scenario: str = "startup"
    seed: int = 0
    realistic: bool = False
    effects: tuple[str, ...] = ()
    effects_file: str | Path | None = None
    noise: bool = True
    faults: tuple[str | FaultSpec, ...] = ()
    realtime: bool = False


@dataclass(frozen=True)
class LiveFeed:
    """Where the samples go as they are read: ``on_batch(streams)`` receives the samples read
    in each ``batch_s`` of the rig's clock (:class:`LiveSink`); ``stop``, when set, ends the
    run (Ctrl-C sets it too)."""

    on_batch: Callable[[list[Stream]], None] | None = None
    batch_s: float = 0.02
    stop: threading.Event | None = None


@dataclass(frozen=True)
class LoopClock:
    """The sampling loop's clock: ``now()`` in seconds, ``wait(s)`` to sleep on it (``None``:
    the loop's own), and ``epoch_s``, the rig's power-up on it (recording times count from
    there)."""

    now: Callable[[], float]
    wait: Callable[[float], Any] | None
    epoch_s: float


class _WallClock:
    """The FakeRig's clock for ``--realtime``: the host's monotonic clock (transfers on
    the fake buses then take no time)."""

    monotonic = staticmethod(time.monotonic)
    sleep = staticmethod(time.sleep)


def _adxl_config(rate_hz: float) -> ADXL345Config:
    try:
        # stream-mode FIFO: nothing is lost while the loop reads once per 32 samples
        return ADXL345Config(rate_hz=rate_hz, fifo=True)
    except ValueError as e:
        raise ValueError(f"--rate {rate_hz:g}: the ADXL345s run at the loop rate, and {e}") from None


def _shifted(s: Stream, epoch_s: float) -> Stream:
    return Stream(s.name, s.kind, s.t_s - epoch_s, s.values, s.channels)


def recording_from(samples: Mapping[str, list[Any]], devices: Mapping[str, ADXL345 | MPU9150],
                   epoch_s: float, meta: dict | None = None,
                   truth: Mapping[str, Stream] | None = None) -> Recording:
    """The valid samples as a raw recording (times relative to ``epoch_s``)."""
    streams: dict[str, Stream] = {}
    for name, dev in devices.items():
        got = samples.get(name, [])
        if isinstance(dev, MPU9150):
            for s in imu_streams(got).values():
                streams[s.name] = _shifted(s, epoch_s)
        else:
            streams[name] = _shifted(accel_stream(name, got), epoch_s)
    enc: list[EncoderSample] = samples.get(ENCODER_READER, [])
    if enc:
        streams["enc"] = _shifted(encoder_stream(enc), epoch_s)
    streams.update(truth or {})
    return Recording(streams, dict(meta or {}))


@dataclass
class LiveSink:
    """The sampling loop's sink when publishing: keeps every result (as a
    :class:`~armfusion.sensors.sampling.Collector`) and, every ``batch_s`` of the loop's clock, hands
    the samples read since the last batch to ``on_batch`` as raw streams (times relative to
    ``epoch_s``; a sensor with no valid sample in the batch is left out)."""

    devices: Mapping[str, ADXL345 | MPU9150]
    epoch_s: float
    clock: Callable[[], float]
    batch_s: float
    on_batch: Callable[[list[Stream]], None]
    last_reader: str
    collector: Collector = field(default_factory=Collector, init=False)
    _pending: Collector = field(default_factory=Collector, init=False)
    _next_s: float = field(init=False)

    def __post_init__(self) -> None:
        self._next_s = self.clock() + self.batch_s

    @property
    def results(self) -> dict[str, list[Any]]:
        return self.collector.results

    def __call__(self, name: str, result: Any) -> None:
        self.collector(name, result)
        self._pending(name, result)
        if name == self.last_reader and self.clock() >= self._next_s:
            self.flush()

    def flush(self) -> None:
        """Hand on what is pending (also called once after the loop ends)."""
        self._next_s = self.clock() + self.batch_s
        pending, self._pending = self._pending.results, Collector()
        if any(pending.values()):
            rec = recording_from(pending, self.devices, self.epoch_s)
            self.on_batch([s for s in rec.streams.values() if len(s)])


@contextlib.contextmanager
def _stop_on_sigint(stop: threading.Event) -> Iterator[None]:
    """Ctrl-C sets ``stop`` (the loop ends within one wait) instead of raising."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _health(devices: Mapping[str, ADXL345 | MPU9150]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, dev in devices.items():
        out[name] = dev.health()
        if isinstance(dev, MPU9150) and dev.config.magnetometer:
            out[f"{name}.mag"] = dev.mag_health()
    return out


def _sample(devices: Mapping[str, ADXL345 | MPU9150], readers: dict[str, Callable[[], Any]],
            rate_hz: float, duration_s: float | None, clock: LoopClock, live: LiveFeed,
            ) -> tuple[LoopReport, dict[str, list[Any]], dict[str, Any]]:
    """Run the sampling loop over ``readers`` on ``clock`` until ``live.stop`` (or Ctrl-C) or
    ``duration_s``, handing the samples to ``live.on_batch`` as they come; the loop's report,
    every reader's results and each device's counters at the end."""
    sink: Collector | LiveSink = Collector() if live.on_batch is None else \
        LiveSink(devices, clock.epoch_s, clock.now, live.batch_s, live.on_batch, last_reader=list(readers)[-1])
    loop = SamplingLoop(readers, rate_hz, sink=sink, clock=clock.now, wait=clock.wait)
    stop = live.stop or threading.Event()
    with _stop_on_sigint(stop):
        report = loop.run(stop, duration_s=duration_s)
    if isinstance(sink, LiveSink):
        sink.flush()
    return report, sink.results, _health(devices)


def _with_faults_and_progress(read: Callable[[], Any], clock: LoopClock, schedule: FaultSchedule,
                              duration_s: float, progress: Callable[[float], None] | None,
                              ) -> Callable[[], Any]:
    """The loop's first reader ``read``, preceded by the fault ``schedule`` stepped to the rig's
    time and, every 1 % of ``duration_s``, ``progress`` told the fraction done."""
    shown = [-1]

    def first_with_faults() -> Any:
        t = clock.now() - clock.epoch_s
        schedule.step(t)
        if progress is not None and int(100 * t / duration_s) > shown[0]:
            shown[0] = int(100 * t / duration_s)
            progress(min(t / duration_s, 1.0))
        return read()

    return first_with_faults


def _simulated(arm: ArmModel, rig: FakeRigOptions, duration_s: float, rate_hz: float) -> SimulatedRun:
    """The simulator's run behind the fakes: ``duration_s`` plus :data:`SIM_MARGIN_S` of
    ``rig``'s scenario, effects and seed, sampled at ``rate_hz``."""
    model = effects_model(arm, tuple(rig.effects), rig.effects_file)
    return simulate_physics(arm, rig.scenario, duration_s + SIM_MARGIN_S, seed=rig.seed, effects=model,
                            realistic=rig.realistic, sample_rate_hz=rate_hz)


def run_fake(
    config: str | Path | ArmModel = "wmra",
    rig: FakeRigOptions | None = None,
    duration_s: float = 10.0,
    rate_hz: float = 100.0,
    *,
    live: LiveFeed | None = None,
    prepare: Callable[[FakeRig], None] | None = None,
    progress: Callable[[float], None] | None = None,
) -> DriversRun:
    """Run the real drivers against the fakes of the simulated ``rig`` (``None``: its defaults)
    for ``duration_s`` seconds.

    ``prepare(rig)`` runs after the devices are opened and before the first tick (a
    test's hook for fault injection beyond ``rig.faults``). ``live``: where the samples go as
    they are read, and what stops the run (:class:`LiveFeed`).
    ``progress(fraction_done)`` follows the rig's clock (every 1 % of ``duration_s``).
    """
    rig = FakeRigOptions() if rig is None else rig
    if not duration_s > 0:
        raise ValueError(f"--duration must be positive, got {duration_s!r} s")
    if rig.scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {rig.scenario!r}; known: {', '.join(SCENARIOS)}")
    arm = config if isinstance(config, ArmModel) else load_arm(config)
    wiring, notes = wiring_from_arm(arm)
    adxl_config = _adxl_config(rate_hz)
    check_run_size(arm, rig.scenario, duration_s + SIM_MARGIN_S, rate_hz)  # (1e9 s: 7 TiB, a traceback)
    specs = [f if isinstance(f, FaultSpec) else parse_fault(f) for f in rig.faults]
    sim = _simulated(arm, rig, duration_s, rate_hz)
    host: Any = _WallClock() if rig.realtime else FakeClock()
    clock = LoopClock(host.monotonic, None if rig.realtime else host.sleep, host.monotonic())  # power-up: t = 0
    physics = physics_for(sim, [w.name for w in wiring], clock.epoch_s, noise=rig.noise, seed=rig.seed)
    fake_rig = FakeRig(host, physics, wiring=wiring, seed=rig.seed)
    schedule = FaultSchedule(fake_rig, specs)
    devices = open_devices(wiring, smbus_factory=fake_rig.smbus, spi_factory=fake_rig.spi.SpiDev,
                           adxl_config=adxl_config, clock=host.monotonic, sleep=host.sleep)
    try:
        if prepare is not None:
            prepare(fake_rig)
        readers = readers_for(devices)
        feed = None
        if arm.n_joints == N_JOINTS:
            feed = SimulatedEncoderFeed(encoder_counts_at(sim, clock.epoch_s), rate_hz, clock=host.monotonic)
            readers[ENCODER_READER] = feed.poll
        else:
            notes.append(f"encoders: the feed carries {N_JOINTS} joints, {arm.name} has "
                         f"{arm.n_joints}; not read")
        first = next(iter(readers))
        readers[first] = _with_faults_and_progress(readers[first], clock, schedule, duration_s, progress)
        report, results, health = _sample(devices, readers, rate_hz, duration_s, clock, live or LiveFeed())
    finally:
        close_all(devices)
    meta = {"generator": "armfusion drivers --fake", "arm": arm.name, "arm_config": arm.source,
            "scenario": rig.scenario, "seed": int(rig.seed), "rate_hz": float(rate_hz),
            "realistic": bool(rig.realistic), "noise": bool(rig.noise), "realtime": bool(rig.realtime)}
    if rig.realtime:
        meta["epoch_monotonic_s"] = float(clock.epoch_s)
    rec = recording_from(results, devices, clock.epoch_s, meta)
    rec = Recording({**rec.streams, **sim.truth_streams(rate_hz, rec.t_end_s)}, rec.meta)
    return DriversRun("fake", arm, wiring, float(rate_hz), float(duration_s), clock.epoch_s, report,
                      results, rec, health, feed.stats() if feed else None, notes, specs,
                      schedule.injected(), sim, fake_rig, meta)


def run_real(
    config: str | Path | ArmModel = "wmra",
    duration_s: float | None = 10.0,
    rate_hz: float = 100.0,
    *,
    live: LiveFeed | None = None,
) -> DriversRun:
    """Open the config's devices on the real buses and read them (until ``live.stop`` or
    ``duration_s``); ``live`` as for :func:`run_fake`. Raises
    :class:`DeviceNotFoundError` with one line per device that cannot be opened or does
    not answer."""
    arm = config if isinstance(config, ArmModel) else load_arm(config)
    wiring, notes = wiring_from_arm(arm)
    adxl_config = _adxl_config(rate_hz)
    order = {w.name: i for i, w in enumerate(wiring)}
    try:
        devices = open_devices(wiring, adxl_config=adxl_config)
    except DeviceNotFoundError as e:  # one line per device, in the config's order
        lines = sorted(str(e).splitlines(), key=lambda ln: order.get(ln.split(":", 1)[0], 99))
        raise DeviceNotFoundError("\n".join(lines)) from None
    except ImportError as e:
        raise DeviceNotFoundError(f"cannot reach the buses: {e} (pip install smbus2 spidev)") from None
    epoch = time.monotonic()
    try:
        report, results, health = _sample(devices, readers_for(devices), rate_hz, duration_s,
                                          LoopClock(time.monotonic, None, epoch), live or LiveFeed())
    finally:
        close_all(devices)
    meta = {"generator": "armfusion drivers", "arm": arm.name, "arm_config": arm.source,
            "rate_hz": float(rate_hz), "epoch_monotonic_s": float(epoch)}
    notes.append("encoders: not read (the UDP feed from the motor controller is the "
                 "service's job)")
    rec = recording_from(results, devices, epoch, meta)
    return DriversRun("real", arm, wiring, float(rate_hz), float(report.duration_s), epoch, report,
                      results, rec, health, None, notes, settings=meta)
