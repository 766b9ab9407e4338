"""``armfusion drivers``: read the rig's sensors through the real drivers, and report.

    armfusion drivers --fake [--config wmra] [--scenario startup] [--duration 10]
        [--rate 100] [--seed 0] [--realistic] [--effect …] [--effects-file F]
        [--no-noise] [--fault SPEC …] [--out REC.csv|REC.mcap] [--realtime] [--json]
    armfusion drivers [--config wmra] [--duration 10] [--rate 100] [--out REC.csv] [--json]

Without ``--fake`` the devices of the config's ``bus:`` entries are opened on the real
buses (smbus2, spidev). A device that cannot be opened or does not answer gives one line
each, and the exit code is 2.

With ``--fake`` the same driver code runs against the register-level fakes
(:class:`~sensors.fakes.FakeRig`), whose physics come from the simulator
(:mod:`models.fake_rig`): the scenario, the effects and the seed mean what they mean for
``armfusion simulate``. The sampling loop runs on a :class:`~sensors.fakes.FakeClock`, as
fast as the host can (the buses' wire time still counts), or on the wall clock with
``--realtime``. The encoders come from a :class:`~sensors.encoders.SimulatedEncoderFeed`
of the simulator's counts. ``--fault`` injects bus and device faults on the fakes
(:func:`parse_fault`). Recording times are seconds since the rig powered up (the
scenario's t = 0); ``--out`` writes the recording and, with ``--fake``, its truth file.

The report: per device, the samples collected, read time, jitter, bus errors, retries and
the drivers' other counters (stale, overruns, offline, re-initialisations…). See
docs/drivers.md, "armfusion drivers".
"""

from __future__ import annotations

import contextlib
import errno as errno_mod
import json
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import typer

from fusion.cli.common import json_default, output_path_problem, progress_bar
from fusion.cli.simulate import effects_model, truth_json, truth_path
from fusion.configfile import load_arm
from fusion.service.commands import ConnectOpt, ListenOpt, ModeOpt, ZenohConfigOpt
from models.arm import ArmModel
from models.arm_config import ConfigError
from models.fake_rig import SimulatedRun, encoder_counts_at, physics_for, simulate_physics
from models.trajectories import SCENARIOS
from sensors.adxl345 import ADXL345, ADXL345Config, accel_stream
from sensors.bus import DeviceNotFoundError
from sensors.encoders import N_JOINTS, EncoderSample, SimulatedEncoderFeed, encoder_stream
from sensors.fakes import FakeClock, FakeRig
from sensors.fakes.faults import FaultInjector
from sensors.mpu9150 import MPU9150, imu_streams
from sensors.recording import SUFFIXES, write_recording
from sensors.samples import Recording, Stream
from sensors.sampling import Collector, LoopReport, SamplingLoop, Wiring, close_all, open_devices, readers_for

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


# --- faults on the fakes --------------------------------------------------------------------

FAULT_KINDS = {
    "nack": "the next K transactions fail with EIO (default K = 1), at T0",
    "random": "each transaction fails with probability P (EIO) from T0 to T1",
    "stuck": "every transaction times out (ETIMEDOUT) from T0 to T1",
    "unplug": "the device stops answering at T0 and is plugged back (power-cycled) at T1",
    "mag-overflow": "the IMU's AK8975 reports overflow (HOFL) from T0 to T1",
}
_FAULT_RE = re.compile(
    r"^(?P<target>[A-Za-z_][\w.]*):(?P<kind>[a-z-]+)(?:=(?P<value>[0-9.eE+-]+))?"
    r"(?:@(?P<t0>[0-9.]+)(?:-(?P<t1>[0-9.]+))?)?$")


@dataclass(frozen=True)
class FaultSpec:
    """``TARGET:KIND[=VALUE][@T0[-T1]]``: a device (``acc3``, ``imu``, ``imu.mag``) or a bus
    (``i2c1``, ``spi``), a kind of :data:`FAULT_KINDS`, times in seconds since power-up
    (default: from the first tick to the end)."""

    text: str
    target: str
    kind: str
    value: float | None = None
    t_start_s: float = 0.0
    t_end_s: float | None = None


def parse_fault(text: str) -> FaultSpec:
    m = _FAULT_RE.match(text.strip())
    if m is None:
        raise ValueError(f"--fault {text!r}: expected TARGET:KIND[=VALUE][@T0[-T1]], e.g. "
                         "acc3:unplug@2-3, i2c1:random=0.02, imu:nack=2@1")
    kind = m["kind"]
    if kind not in FAULT_KINDS:
        raise ValueError(f"--fault {text!r}: unknown kind {kind!r}; kinds: {', '.join(FAULT_KINDS)}")
    value = float(m["value"]) if m["value"] is not None else None
    if kind == "random" and (value is None or not 0.0 < value <= 1.0):
        raise ValueError(f"--fault {text!r}: random needs a probability in (0, 1], e.g. random=0.02")
    if kind == "nack" and value is not None and (value < 1 or value != int(value)):
        raise ValueError(f"--fault {text!r}: nack takes a whole number of transactions")
    t0 = float(m["t0"]) if m["t0"] is not None else 0.0
    t1 = float(m["t1"]) if m["t1"] is not None else None
    if t1 is not None and t1 <= t0:
        raise ValueError(f"--fault {text!r}: the end time must come after the start")
    return FaultSpec(text, m["target"], kind, value, t0, t1)


class FaultSchedule:
    """Applies fault specs to a rig as simulated time passes (:meth:`step` before each tick)."""

    def __init__(self, rig: FakeRig, specs: Sequence[FaultSpec]):
        self.rig = rig
        self._pending: list[tuple[float, Callable[[], None]]] = []
        self.injectors: dict[str, FaultInjector] = {}
        for spec in specs:
            start, stop = self._actions(spec)
            self._pending.append((spec.t_start_s, start))
            if spec.t_end_s is not None and stop is not None:
                self._pending.append((spec.t_end_s, stop))
        self._pending.sort(key=lambda p: p[0])

    def _injector(self, spec: FaultSpec) -> FaultInjector:
        rig, target = self.rig, spec.target
        if target == "spi":
            inj = rig.spi.faults
        elif re.fullmatch(r"i2c\d+", target):
            n = int(target[3:])
            if n not in rig.i2c:
                raise ValueError(f"--fault {spec.text!r}: no I2C bus {n} on the rig")
            inj = rig.i2c[n].faults
        elif target.endswith(".mag") and target[:-4] in rig.devices and \
                hasattr(rig.devices[target[:-4]], "ak8975"):
            inj = rig.devices[target[:-4]].ak8975.faults  # type: ignore[attr-defined]
        elif target in rig.devices:
            inj = rig.devices[target].faults
        else:
            raise ValueError(f"--fault {spec.text!r}: no device or bus {target!r}; targets: "
                             f"{', '.join([*rig.devices, 'imu.mag', *(f'i2c{n}' for n in rig.i2c), 'spi'])}")
        self.injectors[target] = inj
        return inj

    def _actions(self, spec: FaultSpec) -> tuple[Callable[[], None], Callable[[], None] | None]:
        if spec.kind == "unplug":
            dev = self.rig.devices.get(spec.target)
            if dev is None:
                raise ValueError(f"--fault {spec.text!r}: unplug takes a device "
                                 f"({', '.join(self.rig.devices)})")
            self.injectors.setdefault(spec.target, dev.faults)
            return dev.disappear, dev.reappear
        if spec.kind == "mag-overflow":
            dev = self.rig.devices.get(spec.target.removesuffix(".mag"))
            ak = getattr(dev, "ak8975", None)
            if ak is None:
                raise ValueError(f"--fault {spec.text!r}: mag-overflow takes the IMU")

            def on() -> None:
                ak.force_overflow = True

            def off() -> None:
                ak.force_overflow = False

            return on, off
        inj = self._injector(spec)
        if spec.kind == "nack":
            k = int(spec.value or 1)
            return (lambda: inj.fail_next(k, errno_mod.EIO)), None
        if spec.kind == "random":
            p = float(spec.value or 0.0)
            return (lambda: inj.fail_randomly(p, errno_mod.EIO)), inj.clear
        return (lambda: inj.stick(errno_mod.ETIMEDOUT)), inj.clear  # stuck

    def step(self, t_s: float) -> None:
        """Apply every action due at or before ``t_s`` (seconds since power-up)."""
        while self._pending and self._pending[0][0] <= t_s:
            _, action = self._pending.pop(0)
            action()

    def injected(self) -> int:
        """Failed transactions caused so far (unplugged devices NACK on their own)."""
        return sum(inj.injected for inj in self.injectors.values())


# --- the run -------------------------------------------------------------------------------


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


class LiveSink:
    """The sampling loop's sink when publishing: keeps every result (as a
    :class:`~sensors.sampling.Collector`) and, every ``batch_s`` of the loop's clock, hands
    the samples read since the last batch to ``on_batch`` as raw streams (times relative to
    ``epoch_s``; a sensor with no valid sample in the batch is left out)."""

    def __init__(self, devices: Mapping[str, ADXL345 | MPU9150], epoch_s: float,
                 clock: Callable[[], float], batch_s: float,
                 on_batch: Callable[[list[Stream]], None], last_reader: str):
        self.collector = Collector()
        self.results = self.collector.results
        self._devices = devices
        self._epoch_s = epoch_s
        self._clock = clock
        self._batch_s = batch_s
        self._on_batch = on_batch
        self._last_reader = last_reader
        self._pending: dict[str, list[Any]] = {}
        self._next_s = clock() + batch_s

    def __call__(self, name: str, result: Any) -> None:
        self.collector(name, result)
        bucket = self._pending.setdefault(name, [])
        if isinstance(result, list):
            bucket.extend(result)
        else:
            bucket.append(result)
        if name == self._last_reader and self._clock() >= self._next_s:
            self.flush()

    def flush(self) -> None:
        """Hand on what is pending (also called once after the loop ends)."""
        self._next_s = self._clock() + self._batch_s
        pending, self._pending = self._pending, {}
        if any(pending.values()):
            rec = recording_from(pending, self._devices, self._epoch_s)
            self._on_batch([s for s in rec.streams.values() if len(s)])


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


def run_fake(
    config: str | Path | ArmModel = "wmra",
    scenario: str = "startup",
    duration_s: float = 10.0,
    rate_hz: float = 100.0,
    *,
    seed: int = 0,
    realistic: bool = False,
    effect: Sequence[str] = (),
    effects_file: str | Path | None = None,
    noise: bool = True,
    faults: Sequence[str | FaultSpec] = (),
    realtime: bool = False,
    stop: threading.Event | None = None,
    prepare: Callable[[FakeRig], None] | None = None,
    on_batch: Callable[[list[Stream]], None] | None = None,
    batch_s: float = 0.02,
    progress: Callable[[float], None] | None = None,
) -> DriversRun:
    """Run the real drivers against the simulator-fed fakes for ``duration_s`` seconds.

    ``prepare(rig)`` runs after the devices are opened and before the first tick (a
    test's hook for fault injection beyond ``faults``). ``on_batch(streams)`` receives the
    samples read in each ``batch_s`` of the rig's clock as they come (:class:`LiveSink`).
    ``progress(fraction_done)`` follows the rig's clock (every 1 % of ``duration_s``).
    """
    if not duration_s > 0:
        raise ValueError(f"--duration must be positive, got {duration_s!r} s")
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
    arm = config if isinstance(config, ArmModel) else load_arm(config)
    wiring, notes = wiring_from_arm(arm)
    adxl_config = _adxl_config(rate_hz)
    specs = [f if isinstance(f, FaultSpec) else parse_fault(f) for f in faults]
    model = effects_model(arm, tuple(effect), effects_file)
    sim = simulate_physics(arm, scenario, duration_s + SIM_MARGIN_S, seed=seed, effects=model,
                           realistic=realistic, sample_rate_hz=rate_hz)
    clock: Any = _WallClock() if realtime else FakeClock()
    now: Callable[[], float] = clock.monotonic
    sleep: Callable[[float], None] = clock.sleep
    epoch = now()  # power-up: the scenario's t = 0
    physics = physics_for(sim, [w.name for w in wiring], epoch, noise=noise, seed=seed)
    rig = FakeRig(clock, physics, wiring=wiring, seed=seed)
    schedule = FaultSchedule(rig, specs)
    devices = open_devices(wiring, smbus_factory=rig.smbus, spi_factory=rig.spi.SpiDev,
                           adxl_config=adxl_config, clock=now, sleep=sleep)
    try:
        if prepare is not None:
            prepare(rig)
        readers = readers_for(devices)
        feed = None
        if arm.n_joints == N_JOINTS:
            feed = SimulatedEncoderFeed(encoder_counts_at(sim, epoch), rate_hz, clock=now)
            readers[ENCODER_READER] = feed.poll
        else:
            notes.append(f"encoders: the feed carries {N_JOINTS} joints, {arm.name} has "
                         f"{arm.n_joints}; not read")
        first = next(iter(readers))
        read_first = readers[first]

        shown = [-1]

        def first_with_faults() -> Any:
            t = now() - epoch
            schedule.step(t)
            if progress is not None and int(100 * t / duration_s) > shown[0]:
                shown[0] = int(100 * t / duration_s)
                progress(min(t / duration_s, 1.0))
            return read_first()

        readers[first] = first_with_faults
        sink: Collector | LiveSink = Collector() if on_batch is None else \
            LiveSink(devices, epoch, now, batch_s, on_batch, last_reader=list(readers)[-1])
        loop = SamplingLoop(readers, rate_hz, sink=sink, clock=now,
                            wait=None if realtime else sleep)
        stop = stop or threading.Event()
        with _stop_on_sigint(stop):
            report = loop.run(stop, duration_s=duration_s)
        if isinstance(sink, LiveSink):
            sink.flush()
        health = _health(devices)
    finally:
        close_all(devices)
    meta = {"generator": "armfusion drivers --fake", "arm": arm.name, "arm_config": arm.source,
            "scenario": scenario, "seed": int(seed), "rate_hz": float(rate_hz),
            "realistic": bool(realistic), "noise": bool(noise), "realtime": bool(realtime)}
    if realtime:
        meta["epoch_monotonic_s"] = float(epoch)
    rec = recording_from(sink.results, devices, epoch, meta)
    rec = Recording({**rec.streams, **sim.truth_streams(rate_hz, rec.t_end_s)}, rec.meta)
    return DriversRun("fake", arm, wiring, float(rate_hz), float(duration_s), epoch, report,
                      sink.results, rec, health, feed.stats() if feed else None, notes, specs,
                      schedule.injected(), sim, rig, meta)


def run_real(
    config: str | Path | ArmModel = "wmra",
    duration_s: float | None = 10.0,
    rate_hz: float = 100.0,
    *,
    stop: threading.Event | None = None,
    on_batch: Callable[[list[Stream]], None] | None = None,
    batch_s: float = 0.02,
) -> DriversRun:
    """Open the config's devices on the real buses and read them (until ``stop`` or
    ``duration_s``); ``on_batch`` as for :func:`run_fake`. Raises
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
        readers = readers_for(devices)
        sink: Collector | LiveSink = Collector() if on_batch is None else \
            LiveSink(devices, epoch, time.monotonic, batch_s, on_batch, last_reader=list(readers)[-1])
        loop = SamplingLoop(readers, rate_hz, sink=sink)
        stop = stop or threading.Event()
        with _stop_on_sigint(stop):
            report = loop.run(stop, duration_s=duration_s)
        if isinstance(sink, LiveSink):
            sink.flush()
        health = _health(devices)
    finally:
        close_all(devices)
    meta = {"generator": "armfusion drivers", "arm": arm.name, "arm_config": arm.source,
            "rate_hz": float(rate_hz), "epoch_monotonic_s": float(epoch)}
    notes.append("encoders: not read (the UDP feed from the motor controller is the "
                 "service's job)")
    rec = recording_from(sink.results, devices, epoch, meta)
    return DriversRun("real", arm, wiring, float(rate_hz), float(report.duration_s), epoch, report,
                      sink.results, rec, health, None, notes, settings=meta)


# --- the report ----------------------------------------------------------------------------


def _valid_count(name: str, results: list[Any]) -> int:
    if name == ENCODER_READER:
        return len(results)
    n = 0
    for s in results:
        n += bool(getattr(s, "valid", False))
    return n


def _ms(seconds: float) -> float:
    return round(1e3 * seconds, 4)


def _bus(w: Wiring) -> str:
    return f"spi{w.bus_number}.{w.address}" if w.bus == "spi" else f"i2c{w.bus_number} 0x{w.address:02X}"


def summary(run: DriversRun) -> dict[str, Any]:
    """The run as one JSON-ready document (documented in docs/drivers.md)."""
    rep = run.loop
    bus = {w.name: _bus(w) for w in run.wiring}
    devices: dict[str, Any] = {}
    for name, timing in rep.readers.items():
        results = run.samples.get(name, [])
        d: dict[str, Any] = {
            "bus": bus.get(name, "simulated feed" if run.mode == "fake" else "-"),
            "samples": _valid_count(name, results),
            "read_time_ms": {"mean": _ms(timing.read_time_mean_s), "std": _ms(timing.read_time_std_s),
                             "max": _ms(timing.read_time_max_s)},
            "jitter_ms": {"std": _ms(timing.jitter_std_s), "max_abs": _ms(timing.jitter_max_abs_s)},
            "loop_errors": timing.errors,
        }
        h = run.health.get(name)
        if h is not None:
            d.update({"where": h.where, "online": h.online, "counters": dict(h.counters),
                      "errors": h["bus_errors"], "retries": h["retries"], "last_error": h.last_error})
        elif name == ENCODER_READER and run.encoder_stats is not None:
            st = run.encoder_stats
            d.update({"where": "simulated encoder feed", "online": True,
                      "counters": dict(st.__dict__), "errors": st.malformed, "retries": 0,
                      "last_error": ""})
        devices[name] = d
        mag = run.health.get(f"{name}.mag")
        if mag is not None:
            w = next(w for w in run.wiring if w.name == name)
            devices[f"{name}.mag"] = {
                "bus": f"i2c{w.bus_number} 0x0C",
                "samples": sum(1 for s in results if getattr(s, "mag_valid", False)),
                "where": mag.where, "online": mag.online, "counters": dict(mag.counters),
                "errors": mag["bus_errors"], "retries": mag["retries"], "last_error": mag.last_error,
            }
    return {
        "mode": run.mode,
        "config": run.arm.source,
        "arm": run.arm.name,
        **({k: run.settings[k] for k in ("scenario", "seed", "realistic", "noise", "realtime",
                                         "epoch_monotonic_s") if k in run.settings}),
        "rate_hz": run.rate_hz,
        "duration_s": round(rep.duration_s, 6),
        "ticks": rep.ticks,
        "missed_ticks": rep.missed_ticks,
        "lateness_ms": {"mean": _ms(rep.lateness_mean_s), "max": _ms(rep.lateness_max_s)},
        "devices": devices,
        "streams": {k: len(s) for k, s in run.recording.streams.items()},
        "faults": [{"spec": f.text, "target": f.target, "kind": f.kind} for f in run.faults],
        "faults_injected": run.faults_injected,
        "notes": list(run.notes),
    }


_QUIET = frozenset({"reads", "ok", "bus_errors", "retries", "received", "accepted"})


def _events(counters: Mapping[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counters.items()) if v and k not in _QUIET) or "-"


def print_report(doc: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    con = Console()
    head = f"[bold]{doc['arm']}[/] ({doc['mode']}"
    if doc["mode"] == "fake":
        head += f": {doc['scenario']}, seed {doc['seed']}" + (", realistic" if doc["realistic"] else "")
        head += ", wall clock" if doc["realtime"] else ", simulated clock"
    con.print(head + f"): {doc['ticks']} ticks at {doc['rate_hz']:g} Hz over {doc['duration_s']:.2f} s, "
              f"{doc['missed_ticks']} missed; tick lateness {doc['lateness_ms']['mean']:.3f} ms mean / "
              f"{doc['lateness_ms']['max']:.3f} ms max", highlight=False)
    t = Table(title="Devices", title_justify="left")
    for col in ("device", "bus", "samples", "read (ms) mean/max", "jitter (ms) std/max",
                "errors", "retries", "other events"):
        t.add_column(col, justify="right" if col in ("samples", "errors", "retries") else "left")
    for name, d in doc["devices"].items():
        timing = "-"
        jitter = "-"
        if "read_time_ms" in d:
            timing = f"{d['read_time_ms']['mean']:.2f}/{d['read_time_ms']['max']:.2f}"
            jitter = f"{d['jitter_ms']['std']:.2f}/{d['jitter_ms']['max_abs']:.2f}"
        errors = d.get("errors", 0) + d.get("loop_errors", 0)
        events = _events(d.get("counters", {}))
        if not d.get("online", True):
            events = "[red]OFFLINE[/]" + ("" if events == "-" else f", {events}")
        t.add_row(name, d["bus"], str(d["samples"]), timing, jitter,
                  f"[red]{errors}[/]" if errors else "0", str(d.get("retries", 0)), events)
    con.print(t)
    for f in doc["faults"]:
        con.print(f"fault injected: {escape(f['spec'])}", highlight=False)
    if doc["faults"]:
        con.print(f"{doc['faults_injected']} transactions failed by injection", highlight=False)
    for name, d in doc["devices"].items():
        if d.get("last_error"):
            con.print(f"[yellow]{name}[/] last error: {escape(d['last_error'])}", highlight=False)
    for n in doc["notes"]:
        con.print(f"note: {escape(n)}", highlight=False)
    if doc.get("out"):
        con.print(f"Wrote {doc['out']}" + (f" and {doc['truth']}" if doc.get("truth") else ""),
                  highlight=False)




@dataclass
class _Live:
    publisher: Any
    stop: threading.Event
    batch_s: float


@contextlib.contextmanager
def _publishing(robot: str, batch_ms: float, wait_s: float, zenoh_config: Path | None,
                listen: list[str] | None, connect: list[str] | None, mode: str | None,
                fail: Callable[[str], None]) -> Iterator[_Live]:
    """A Zenoh session and a :class:`~fusion.service.raw_publisher.RawPublisher` for
    ``--robot``; SIGINT and SIGTERM stop the run; the last status says ``done``."""
    from fusion.service.commands import session_or_exit, zenoh_settings
    from fusion.service.node import stop_on_signals
    from fusion.service.payloads import check_name
    from fusion.service.raw_publisher import RawPublisher

    try:
        check_name(robot, "--robot")
    except ValueError as e:
        fail(str(e))
    if not batch_ms > 0:
        fail(f"--batch-ms {batch_ms!r}: expected > 0")
    if wait_s < 0:
        fail(f"--wait {wait_s!r}: expected >= 0")
    stop = threading.Event()
    with session_or_exit(zenoh_settings(zenoh_config, listen, connect, mode)) as session, \
            stop_on_signals(stop):
        publisher = RawPublisher(session, robot, message="publishing raw samples")
        if wait_s:
            publisher.wait_for_subscriber("imu_acc", wait_s, stop)
        publisher.status("running", "publishing raw samples")
        try:
            yield _Live(publisher, stop, batch_ms / 1000.0)
        finally:
            n = sum(publisher.samples.values())
            publisher.close(("stopped: " if stop.is_set() else "") + f"published {n} samples")


def register(app: typer.Typer) -> None:
    """Add the ``drivers`` command to ``app``."""
    from rich.console import Console
    from rich.markup import escape

    @app.command("drivers")
    def drivers_command(
        fake: Annotated[bool, typer.Option("--fake", help="Read register-level fake devices fed by "
                                           "the simulator instead of the real buses.")] = False,
        config: Annotated[str, typer.Option("--config", "-c", help="Arm config: a shipped name "
                                            "(wmra) or a YAML path; its sensors' bus: entries "
                                            "say where each device is.")] = "wmra",
        scenario: Annotated[str, typer.Option("--scenario", "-s", help="With --fake: the simulated "
                                              "motion: " + ", ".join(SCENARIOS))] = "startup",
        duration: Annotated[float, typer.Option("--duration", help="Seconds to read.")] = 10.0,
        rate: Annotated[float, typer.Option("--rate", help="Loop rate [Hz] (also the ADXL345s' "
                                            "output data rate: 12.5 … 3200).")] = 100.0,
        seed: Annotated[int, typer.Option("--seed", help="With --fake: as for simulate.")] = 0,
        realistic: Annotated[bool, typer.Option("--realistic", help="With --fake: every effect at "
                                                "datasheet-typical magnitudes.")] = False,
        effect: Annotated[list[str] | None, typer.Option("--effect", help="With --fake: as for "
                                                         "simulate; repeatable.")] = None,
        effects_file: Annotated[Path | None, typer.Option("--effects-file", help="With --fake: replay "
                                                          "the effects of a REC.truth.json.")] = None,
        noise: Annotated[bool, typer.Option("--noise/--no-noise", help="With --fake: sensor "
                                            "noise.")] = True,
        fault: Annotated[list[str] | None, typer.Option("--fault", help="With --fake: TARGET:KIND"
                                                        "[=VALUE][@T0[-T1]], repeatable. Kinds: " + "; ".join(
                                                            f"{k}: {v}" for k, v in FAULT_KINDS.items()))] = None,
        out: Annotated[Path | None, typer.Option("--out", "-o", help="Write the recording: REC.csv "
                                                 "or REC.mcap (with --fake also REC.truth.json).")] = None,
        realtime: Annotated[bool, typer.Option("--realtime", help="With --fake: run on the wall "
                                               "clock instead of as fast as possible.")] = False,
        json_out: Annotated[bool, typer.Option("--json", help="Print one machine-readable JSON "
                                               "document.")] = False,
        robot: Annotated[str | None, typer.Option("--robot", help="Publish the raw samples over Zenoh "
                                                  "on armfusion/<robot>/raw/<sensor> as they are "
                                                  "read.")] = None,
        batch_ms: Annotated[float, typer.Option("--batch-ms", help="With --robot: read time per "
                                                "published batch, in ms.")] = 20.0,
        wait_s: Annotated[float, typer.Option("--wait", help="With --robot: first wait up to this long "
                                              "for a subscriber to the raw samples, in s.")] = 0.0,
        zenoh_config: ZenohConfigOpt = None,
        listen: ListenOpt = None,
        connect: ConnectOpt = None,
        mode: ModeOpt = None,
    ) -> None:
        """Read the sensors through the drivers (or, with --fake, the simulator-fed fakes) and
        report read time, jitter, errors and samples per device; with --robot, publish the raw
        samples over Zenoh as they are read."""
        err = Console(stderr=True)

        def fail(message: str) -> None:
            for line in message.splitlines() or [""]:
                err.print(f"[bold red]error:[/] {escape(line)}", highlight=False, soft_wrap=True)
            raise typer.Exit(2)

        if out is not None:
            for path in (out, truth_path(out) if fake else None):
                why = None if path is None else output_path_problem(path, SUFFIXES if path == out else None)
                if why is not None:
                    fail(f"--out {path}: {why}")
        if robot is None:
            given = [o for o, v in (("--listen", listen), ("--connect", connect), ("--mode", mode),
                                    ("--zenoh-config", zenoh_config), ("--wait", wait_s)) if v]
            if given:
                fail(f"{', '.join(given)}: only with --robot (which publishes over Zenoh)")
            publishing = contextlib.nullcontext(None)
        else:
            publishing = _publishing(robot, batch_ms, wait_s, zenoh_config, listen, connect, mode, fail)
        with publishing as live, progress_bar("reading the fakes", json_out or not fake) as advance:
            run = _run(fake, config, scenario, duration, rate, seed, realistic, effect, effects_file,
                       noise, fault, realtime, live, fail, advance)
        doc = summary(run)
        if live is not None:
            doc["published"] = {"robot": robot, "samples": live.publisher.samples,
                                "batches": live.publisher.batches}
        _finish(doc, run, out, json_out)

    def _run(fake, config, scenario, duration, rate, seed, realistic, effect, effects_file, noise,
             fault, realtime, live, fail, advance) -> DriversRun:
        on_batch = None if live is None else live.publisher.publish
        batch_s = 0.02 if live is None else live.batch_s
        stop = threading.Event() if live is None else live.stop
        try:
            if fake:
                return run_fake(config, scenario, duration, rate, seed=seed, realistic=realistic,
                                effect=effect or (), effects_file=effects_file, noise=noise,
                                faults=fault or (), realtime=realtime, stop=stop, on_batch=on_batch,
                                batch_s=batch_s, progress=advance)
            else:
                ignored = [o for o, v in (("--scenario", scenario != "startup"), ("--seed", seed != 0),
                                          ("--realistic", realistic), ("--effect", bool(effect)),
                                          ("--effects-file", effects_file is not None),
                                          ("--fault", bool(fault)), ("--realtime", realtime)) if v]
                if ignored:
                    fail(f"{', '.join(ignored)} only appl{'y' if len(ignored) > 1 else 'ies'} "
                         "with --fake")
                return run_real(config, duration, rate, stop=stop, on_batch=on_batch, batch_s=batch_s)
        except DeviceNotFoundError as e:
            fail(str(e))
        except (ConfigError, FileNotFoundError, ValueError) as e:
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
                tp.write_text(truth_json(truth), encoding="utf-8")
                doc["truth"] = str(tp)
        if json_out:
            typer.echo(json.dumps(doc, indent=2, default=json_default))
            return
        print_report(doc)
