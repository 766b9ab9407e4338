"""``armfusion simulate``: write a simulated recording and its truth file.

    armfusion simulate --config wmra --scenario daily-use --out rec.csv \\
        [--duration 600] [--rate 100] [--seed 0] [--effect mount_rotation:acc3=0.01,0.02,0 …]
        [--realistic] [--effects-file other.truth.json] [--no-noise] [--json]

Writes ``rec.csv`` (or ``.mcap``) and ``rec.truth.json``: every effect's true parameters
as config entries (``effects: [{effect, target, params, sigma, note}]``), the scenario's
events and the settings. ``--effects-file`` takes such a truth file (or an arm config's
``effects:`` list) and replays its effects, so several recordings come from the same
imperfect arm. ``--effect`` values are comma separated, in the units the effect documents
(``armfusion simulate --help`` lists them; docs/effects.md explains them).
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer
from armfusion.fusion.cli.common import (
    config_file,
    emit_json,
    fail,
    json_default,
    output_path_problem,
    progress_bar,
)
from armfusion.fusion.cli.options import (
    ConfigOpt,
    EffectOpt,
    EffectsFileOpt,
    JsonOpt,
    NoiseOpt,
    RealisticOpt,
    RecordingOutOpt,
    SeedOpt,
)
from armfusion.fusion.configfile import load_arm, read_yaml
from armfusion.models.arm import ArmModel
from armfusion.models.arm_config import ConfigError, ConfigProblem
from armfusion.models.effects import EFFECTS, Model, model_from_entries, parse_effect_option
from armfusion.models.simulator import SimulationOptions as SimulatorSettings
from armfusion.models.simulator import simulate as simulate_recording
from armfusion.models.trajectories import SCENARIOS
from armfusion.sensors.output_files import write_text_replacing
from armfusion.sensors.recording import write_recording

MEMORY_BYTES_PER_VALUE = 90
"""Peak memory per simulated value (one channel at one instant, truth columns included):
3000 s of the WMRA at 100 Hz (39 values an instant) peaked at 1.05 GB writing MCAP, 0.62 GB
writing CSV, 58 MB of it the program itself: 85 bytes a value, rounded up."""
MEMORY_SHARE = 0.5
"""A run may plan on at most this share of the memory available when it starts."""


def available_memory_bytes() -> int | None:
    """What the machine has available now (``MemAvailable``), or None where unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_run_size(arm: ArmModel, scenario: str, duration_s: float | None, rate_hz: float,
                   available_bytes: int | None = None) -> None:
    """Refuse, before anything is allocated, a duration or rate that is not a positive finite
    number, a run that holds no sample, a rate faster than any sensor delivers (the readers'
    bound), or a run that would need more than :data:`MEMORY_SHARE` of the available memory
    (``available_bytes``, default: the machine's now)."""
    import math

    from armfusion.sensors.sample_checks import FASTEST_SAMPLING_HZ

    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"--rate must be a positive number of Hz, not {rate_hz!r}")
    if duration_s is None:
        if scenario not in SCENARIOS:
            return  # the simulator names the scenarios it knows
        duration_s = SCENARIOS[scenario].default_duration_s
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"--duration must be a positive number of seconds, not {duration_s!r}")
    if duration_s * rate_hz < 1.0:  # (a recording of a header alone had been written, exit 0)
        raise ValueError(f"--duration {duration_s:g} s at {rate_hz:g} Hz holds no sample (one every "
                         f"{1.0 / rate_hz:g} s)")
    if rate_hz > FASTEST_SAMPLING_HZ:  # (every reader would refuse the recording)
        raise ValueError(f"--rate {rate_hz:g} Hz is faster than any sensor delivers "
                         f"({FASTEST_SAMPLING_HZ / 1e3:.0f} kHz at most)")
    values = (3 * len(arm.link_accelerometers) + (10 if arm.imu is not None else 0)
              + 2 * arm.n_joints + 3)  # + the truth columns
    need = duration_s * rate_hz * values * MEMORY_BYTES_PER_VALUE
    avail = available_memory_bytes() if available_bytes is None else available_bytes
    if avail is None:
        avail = 8 * 2**30
    cap = MEMORY_SHARE * avail
    if need > cap:
        most = cap / (rate_hz * values * MEMORY_BYTES_PER_VALUE)
        raise ValueError(
            f"--duration {duration_s:g} s at {rate_hz:g} Hz would need about {_bytes(need)} of memory "
            f"({values} values an instant, {MEMORY_BYTES_PER_VALUE} bytes each); the bound is half "
            f"the memory available now, {_bytes(cap)}: at most {most:,.0f} s at this rate")


def _bytes(n: float) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} PB"


def truth_path(out: str | Path) -> Path:
    """``REC.csv`` -> ``REC.truth.json``."""
    return Path(out).with_suffix(".truth.json")


def load_effect_entries(path: str | Path) -> list[dict]:
    """The effect entries of a truth file (JSON) or an arm config (YAML ``effects:``)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"effects file not found: {p}")
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ConfigError([ConfigProblem(str(p), "(file)", p.name, f"not valid JSON: {e}")]) from e
    else:
        data = read_yaml(p)  # bounded: an alias bomb is refused
    entries = data.get("effects") if isinstance(data, dict) else data
    if not isinstance(entries, list):
        raise ConfigError([ConfigProblem(str(p), "effects", type(entries).__name__,
                                         "expected a list of effect entries under 'effects'")])
    return entries


def effects_model(arm: ArmModel, effect_options: list[str] | tuple[str, ...] = (),
                  effects_file: str | Path | None = None) -> Model | None:
    """The effects asked for: a file's (if any), then ``--effect`` options over them."""
    model = None
    if effects_file is not None:
        model = model_from_entries(arm, load_effect_entries(effects_file), str(effects_file))
    if effect_options:
        problems, entries = [], []
        for k, text in enumerate(effect_options):
            try:
                entries.append(parse_effect_option(text))
            except ValueError as e:
                problems.append(ConfigProblem("--effect", f"--effect[{k}]", text, str(e)))
        if problems:
            raise ConfigError(problems)
        given = model_from_entries(arm, entries, "--effect", "--effect")
        if model is None:
            model = given
        else:
            extra = [e for e in given.effects if e.block_name not in model.index]
            model = model.with_effects(extra).with_values(given.unpack())
    return model


@dataclass(frozen=True)
class SimulationOptions:
    """How ``armfusion simulate`` simulates (its options): ``duration_s`` (``None``: the
    scenario's) at ``rate_hz`` from ``seed``; ``effects`` (``--effect`` specs) over those of
    ``effects_file``, and with ``realistic`` drawn ones; ``noise``: the sensors' noise on;
    ``maneuver``: a planned maneuver's file (``plan-maneuver --out``) to play instead of a
    scenario, which sets its own length."""

    duration_s: float | None = None
    rate_hz: float = 100.0
    seed: int = 0
    effects: tuple[str, ...] = ()
    realistic: bool = False
    effects_file: str | Path | None = None
    noise: bool = True
    maneuver: str | Path | None = None


def simulate(config: str | Path, scenario: str, out: str | Path, options: SimulationOptions | None = None,
             progress=None) -> dict[str, Any]:
    """Simulate ``scenario`` on the arm of ``config`` as ``options`` say (``None``: the
    defaults) and write ``out`` and its truth file; a JSON-ready summary of what was done.

    ``progress(fraction_done, stage)`` follows the work: the simulation up to
    :data:`SIMULATED_SHARE` of it (by suffix), then the writing."""
    o = SimulationOptions() if options is None else options
    duration_s, rate_hz, seed, maneuver = o.duration_s, o.rate_hz, o.seed, o.maneuver
    effects_file, realistic, noise = o.effects_file, o.realistic, o.noise
    out = Path(out)
    if out.suffix.lower() not in (".csv", ".mcap"):
        raise ValueError(f"--out {out}: the recording must end in .csv or .mcap")
    for p in (out, truth_path(out)):
        why = output_path_problem(p, inputs=(config_file(str(config)), effects_file, maneuver))
        if why is not None:
            raise ValueError(f"--out {p}: {why}")
    arm = load_arm(config)
    if maneuver is not None:  # a planned maneuver (plan-maneuver --out): checked, then played
        from armfusion.fusion.identification.planner import safe_maneuver
        from armfusion.models.trajectories.planned import played_scenario

        plan = safe_maneuver(arm, maneuver)
        if duration_s is not None:
            raise ValueError("--duration: a maneuver file sets its own length; leave --duration out")
        duration_s = plan.duration_s
        check_run_size(arm, "planned", duration_s, rate_hz)
        scenario = played_scenario(arm, plan, seed)
    else:
        check_run_size(arm, scenario, duration_s, rate_hz)
    model = effects_model(arm, o.effects, effects_file)
    say = progress or (lambda _f, _m=None: None)
    share = SIMULATED_SHARE[out.suffix.lower()]
    t0 = time.perf_counter()
    settings = SimulatorSettings(noise=noise, progress=lambda f: say(share * f, "simulating"))
    rec, truth = simulate_recording(arm, scenario, duration_s, rate_hz, seed, model, realistic, settings)
    t_sim = time.perf_counter() - t0
    say(share, f"writing {out.name}")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_recording(rec, out)
    tp = truth_path(out)
    write_text_replacing(tp, truth_json(truth))
    t_all = time.perf_counter() - t0
    return {
        "out": str(out), "truth": str(tp), "config": arm.source, "arm": arm.name,
        "scenario": truth["scenario"], "duration_s": truth["duration_s"], "rate_hz": rate_hz,
        "seed": seed, "realistic": realistic, "noise": noise,
        "effects": [f"{e['target']}.{e['effect']}" for e in truth["effects"]],
        "streams": {k: v["samples"] for k, v in truth["streams"].items()},
        "simulate_s": round(t_sim, 3), "total_s": round(t_all, 3),
        "bytes": out.stat().st_size,
    }


SIMULATED_SHARE = {".csv": 0.45, ".mcap": 0.15}
"""The simulation's share of a run's time (the rest is writing), measured on 3000 s of the
WMRA: 5.7 of 12.8 s to CSV; 600 s: 1.7 of 11.7 s to MCAP."""


def truth_json(truth: dict) -> str:
    """The truth dict as JSON, indented, with short lists of numbers kept on one line."""
    text = json.dumps(truth, indent=1, default=json_default)
    num = r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?"
    flat = re.compile(r"\[\s*(" + num + r"(?:,\s*" + num + r")*)\s*\]")
    inner = re.compile(r"\[\s*(\[[^\[\]]*\](?:,\s*\[[^\[\]]*\])*)\s*\]")
    text = flat.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    text = inner.sub(lambda m: "[" + re.sub(r",\s*", ", ", m.group(1)) + "]", text)
    return text + "\n"




def _listing_help() -> str:
    """The scenarios and the effects, for ``simulate --help`` (the shared --scenario and
    --effect options point there)."""
    scenarios = "; ".join(f"{k} ({v.description}, {v.default_duration_s:g} s)" for k, v in SCENARIOS.items())
    effects = "; ".join(f"{name} ({cls.target_kind}; {', '.join(cls.labels)} in {cls.units})"
                        for name, cls in EFFECTS.items())
    return f"Scenarios: {scenarios}.\n\nEffects: {effects}."


def register(app: typer.Typer) -> None:
    """Add the ``simulate`` command to ``app``."""
    from rich.console import Console
    from rich.table import Table

    @app.command("simulate")
    def simulate_command(
        out: RecordingOutOpt,
        scenario: Annotated[str | None, typer.Option(
            "--scenario", "-s", help="The simulated motion: a scenario of armfusion.models.trajectories (listed "
            "below); or give --maneuver.")] = None,
        maneuver: Annotated[Path | None, typer.Option(
            "--maneuver", help="Play a planned maneuver (armfusion plan-maneuver --out M.yaml) instead "
            "of a scenario; refused if it is not safe on the config's arm.")] = None,
        config: ConfigOpt = "wmra",
        duration: Annotated[float | None, typer.Option("--duration", help="Seconds (default: the "
                                                       "scenario's).")] = None,
        rate: Annotated[float, typer.Option("--rate", help="Sample rate of every device [Hz].")] = 100.0,
        seed: SeedOpt = 0,
        effect: EffectOpt = None,
        realistic: RealisticOpt = False,
        effects_file: EffectsFileOpt = None,
        noise: NoiseOpt = True,
        json_out: JsonOpt = False,
    ) -> None:
        """Simulate a recording of the arm's sensors (raw counts, truth columns, truth file)."""
        if (scenario is None) == (maneuver is None):
            fail("give one of --scenario NAME or --maneuver M.yaml")
        if scenario is not None and not scenario.strip():
            fail(f"--scenario {scenario!r}: give a scenario's name (`armfusion simulate --help` lists them)")
        try:
            with progress_bar("simulating", json_out) as advance:
                options = SimulationOptions(duration, rate, seed, tuple(effect or ()), realistic, effects_file,
                                            noise, maneuver)
                summary = simulate(config, scenario or "planned", out, options, progress=advance)
        except (ConfigError, FileNotFoundError, ValueError) as e:
            fail(str(e))
        if json_out:
            emit_json(summary)
            return
        con = Console()
        con.print(f"[bold]{summary['scenario']}[/] on {summary['arm']}: {summary['duration_s']:.1f} s at "
                  f"{summary['rate_hz']:g} Hz, seed {summary['seed']}"
                  + (", realistic effects" if summary["realistic"] else "")
                  + ("" if summary["noise"] else ", no noise"))
        t = Table(title="Streams written", title_justify="left")
        t.add_column("stream")
        t.add_column("samples", justify="right")
        for k, v in summary["streams"].items():
            t.add_row(k, str(v))
        con.print(t)
        n = len(summary["effects"])
        con.print(f"Effects: {n}" + (f" ({', '.join(summary['effects'][:6])}{', …' if n > 6 else ''})"
                                     if n else " (ideal sensors)"))
        con.print(f"Wrote {summary['out']} ({summary['bytes'] / 1e6:.1f} MB) and {summary['truth']} "
                  f"in {summary['total_s']:.1f} s (simulation {summary['simulate_s']:.1f} s)")

    simulate_command.__doc__ = f"{simulate_command.__doc__}\n\n{_listing_help()}"
