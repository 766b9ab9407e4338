"""The workbench's false alarms measured: clean recordings through `diagnose`, `--discover`
and the residual analysis.

A **clean** recording is simulated with exactly the effects its config states, so anything
other than "fits to noise" is a false alarm:

- **the shipped arm**: ``config/wmra.yaml`` (no effects) and a simulation with none;
- **the realistic arm**: the simulator's realistic arm of seed S (every effect of the
  library at datasheet-typical magnitudes), calibrated on its own ``renk-maneuver`` of
  ``--calibration-s`` seconds (seed S) by ``calibrate sensors --effects all``
  (``tools/bench_calibrated.py``'s :func:`calibrate`, the command's functions) and written
  as a config (:func:`calibrated_config`); then *new* recordings of the same arm (the same
  drawn effects, other seeds: other motion and noise) diagnosed against that config. The
  config then states every effect the arm has, with the calibration's estimates and σ as
  its priors: the truth differs from the config by the calibration's error, which its σ
  state (the honest doubt). Its model holds every library effect, so no candidate is left
  to test: the score test and discovery cannot raise anything there, and what can fail is
  the RMS against the noise and the residual analysis.

Scenarios: those a parked ``diagnose`` takes (the chair parked: ``renk-maneuver``,
``static-poses`` and a maneuver ``plan-maneuver`` plans, played as ``simulate --maneuver``
plays it); ``renk-ramp`` is not among them: it drives the chair between its stances and the
command sends it to the innovations' analysis (any recording the command would send there
is counted here as "not parked" and not diagnosed). Each recording is diagnosed as the command does
(window means of ``--window`` samples, the config's model), through :func:`discover` (whose
first rung *is* ``diagnose``): counted are (1) the diagnosis's verdict other than "fits to
noise", (2) discovery adding anything, (3) the residual analysis flagging an input
correlation or a non-white axis (``ResidualAnalysis.white``). Each rate with its Wilson 95 %
interval. Discovery adds an effect exactly when its first rung has a significant candidate;
``--rungs`` (1) bounds the ladder's cost on a recording where it does (the count does not
depend on it).

Besides the counts, how well each test's own statistics hold: the share of individual score
tests (each candidate, uncorrected) below p 0.05 and 0.01, and the residual analysis's
largest |correlation| over its flag band, per recording.

The default 200 recordings took 4.7 min of CPU (one core; the two calibrations and the
plan 37 s more), 0.3-2 s a recording of the shipped arm, 6-21 s of the realistic one.

Writes its markdown section to ``--out FILE`` (docs/benchmarks.md is written by whoever
merges) and prints it.

    nice python tools/bench_null.py [--seeds 40] [--planned-seeds 10] [--realistic-arms 2]
        [--realistic-seeds 6] [--jobs 2] [--out FILE] [--quick]
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from scipy.stats import chi2 as chi2_dist  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.identification.data import data_from_recording  # noqa: E402
from armfusion.fusion.workbench.diagnose import chair_moves  # noqa: E402
from armfusion.fusion.workbench.discover import DiscoverSettings, discover  # noqa: E402
from armfusion.models.effects import model_from_arm  # noqa: E402
from armfusion.models.simulator import simulate  # noqa: E402

from tools.bench_calibrated import calibrate, calibrated_config  # noqa: E402
from tools.benchdoc import machine_line, publish, wilson  # noqa: E402

WINDOW = 10
"""Window means of 10 samples, as ``armfusion diagnose`` by default (``--window``)."""
TARGET = 0.05
SHIPPED_PLAN = (("renk-maneuver", 30.0, 1.75), ("renk-maneuver", 60.0, 1.0), ("renk-maneuver", 120.0, 0.6),
                ("renk-maneuver", 300.0, 0.25), ("static-poses", 60.0, 0.6), ("static-poses", 120.0, 0.25))
"""(scenario, duration, recordings per ``--seeds``): the shorter the more (the CPU bound)."""
REALISTIC_PLAN = (("renk-maneuver", 60.0),)
PLANNED = "planned-maneuver"
"""A maneuver ``plan-maneuver`` plans for the shipped config (``--effects all``, D-optimal,
``PLANNED_S`` long), planned once, played with each seed's chair tilt and noise."""
PLANNED_S = 60.0
KINDS = ("diagnose", "discover", "residuals")


@dataclass(frozen=True)
class Case:
    arm: str
    """``shipped`` or ``realistic S`` (S: the realistic arm's seed)."""
    scenario: str
    duration_s: float
    seed: int

    @property
    def group(self) -> tuple[str, str, float]:
        return (self.arm.split()[0], self.scenario, self.duration_s)


@dataclass
class Outcome:
    case: Case
    parked: bool
    verdict: str = ""
    rms_ratio: float = float("nan")
    added: list[str] = field(default_factory=list)
    white: bool = True
    flags: list[str] = field(default_factory=list)
    raw_p: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """Each candidate's uncorrected score-test p-value."""
    top: str = ""
    """The best candidate with its corrected p-value."""
    flag_ratio: float = 0.0
    """Largest |correlation| (input or autocorrelation) over its flag band."""
    cpu_s: float = 0.0

    @property
    def alarms(self) -> dict[str, bool]:
        return {"diagnose": self.verdict != "fits to noise", "discover": bool(self.added),
                "residuals": not self.white}


def plan(seeds: int, realistic_arms: int, realistic_seeds: int, planned_seeds: int = 0) -> list[Case]:
    """``seeds`` times each (scenario, duration)'s share of the shipped arm, ``planned_seeds`` of the
    planned maneuver, ``realistic_seeds`` per (scenario, duration) of each realistic arm; every
    recording its own seed."""
    out = [Case("shipped", PLANNED, PLANNED_S, 15_000 + s) for s in range(planned_seeds)]
    for k, (scenario, dur, share) in enumerate(SHIPPED_PLAN):
        out += [Case("shipped", scenario, dur, 10_000 + 100 * k + s) for s in range(round(seeds * share))]
    for a in range(1, realistic_arms + 1):
        for k, (scenario, dur) in enumerate(REALISTIC_PLAN):
            out += [Case(f"realistic {a}", scenario, dur, 20_000 + 1000 * a + 100 * k + s)
                    for s in range(realistic_seeds)]
    return out


def realistic_arm(arm, arm_seed: int, calibration_s: float, folder: Path):
    """Seed ``arm_seed``'s realistic arm calibrated on its own maneuver: the calibrated config's
    path and the simulator's entries of its true effects."""
    res, truth, _ = calibrate(arm, arm_seed, calibration_s)
    path = folder / f"wmra_realistic_{arm_seed}.yaml"
    path.write_text(yaml.safe_dump(calibrated_config(res), sort_keys=False, width=110), encoding="utf-8")
    return str(path), truth["effects"]


def planned_maneuver(arm):
    """The planned maneuver (``PLANNED``), as ``plan-maneuver --duration PLANNED_S`` plans it."""
    from armfusion.fusion.cli.calibrate_sensors import build_model
    from armfusion.fusion.identification.planner import PlanSettings, plan_maneuver

    return plan_maneuver(build_model(arm, "all"), PlanSettings(duration_s=PLANNED_S)).maneuver


def run_case(case: Case, sim_arm, config_arm, effects, rungs: int, maneuver=None,
             window: int = WINDOW) -> Outcome:
    c0 = time.process_time()
    scenario = case.scenario
    if scenario == PLANNED:  # as ``simulate --maneuver`` plays it
        from armfusion.models.trajectories.planned import played_scenario

        scenario = played_scenario(sim_arm, maneuver, case.seed)
    rec, _ = simulate(sim_arm, scenario, case.duration_s, seed=case.seed, effects=effects)
    if chair_moves(config_arm, rec):
        return Outcome(case, parked=False, cpu_s=time.process_time() - c0)
    data = data_from_recording(config_arm, rec, window=window)
    disc = discover(model_from_arm(config_arm), data, DiscoverSettings(max_rungs=rungs))
    d = disc.first
    a = d.analysis
    raw = np.array([chi2_dist.sf(c.score, c.dof) for c in d.candidates])
    ratio = 0.0
    if a is not None:
        xc = max((abs(c.r) for c in a.correlations()), default=0.0) / a.band_flag
        ac = float(np.max(np.abs(a.autocorr[:, 1:]), initial=0.0)) / a.band_flag_autocorr
        ratio = max(xc, ac)
    flags = [] if a is None else ([f"{c.axis}~{c.input} r {c.r:+.3f}" for c in a.flagged()[:2]]
                                  + [f"{ax} not white {m:.3f}" for _s, ax, m in a.not_white()[:2]])
    top = f"{d.candidates[0].name} p {d.candidates[0].p_value:.2g}" if d.candidates else ""
    return Outcome(case, True, d.verdict, d.rms_ratio, [f.added for f in disc.findings],
                   a is None or a.white, flags, raw, top, ratio, time.process_time() - c0)


_WORKER: dict = {}


def _work(job: tuple) -> Outcome:
    """One case in a worker process: the arms loaded once per process (config paths)."""
    case, config_path, effects, rungs, maneuver, window = job
    if "base" not in _WORKER:
        _WORKER["base"] = load_arm("wmra")
    base = _WORKER["base"]
    key = config_path or "shipped"
    if key not in _WORKER:
        _WORKER[key] = base if config_path is None else load_arm(config_path)
    return run_case(case, base, _WORKER[key], effects, rungs, maneuver, window)


def _rate(k: int, n: int) -> str:
    if n == 0:
        return "–"
    lo, hi = wilson(k, n)
    return f"{k} of {n} ({100 * k / n:.1f} %, {100 * lo:.1f}–{100 * hi:.1f} %)"


def _met(k: int, n: int) -> str:
    """Met when the rate is at most the target; the interval says how sure that is."""
    if n == 0:
        return "–"
    return "met" if k / n <= TARGET else "**not met**"


def section(outs: list[Outcome], args: dict, cal_cpu: list[float]) -> str:
    parked = [o for o in outs if o.parked]
    skipped = [o for o in outs if not o.parked]
    groups: dict[tuple, list[Outcome]] = {}
    for o in parked:
        groups.setdefault(o.case.group, []).append(o)
    cpu = sum(o.cpu_s for o in outs) + sum(cal_cpu)
    lines = [
        "## False alarms on clean recordings (`tools/bench_null.py`)", "",
        f"{machine_line()}; BLAS on one thread. Clean: simulated with exactly the effects the config "
        "states (the shipped arm: none; the realistic arm: every library effect at datasheet-typical "
        f"size, the config calibrated on its own {args['calibration_s']:.0f} s `renk-maneuver` by "
        "`calibrate sensors --effects all`, then new recordings of the same arm with other seeds). "
        f"Scenarios: `renk-maneuver`, `static-poses` and a {PLANNED_S:.0f} s maneuver `plan-maneuver` "
        "plans for the shipped config, played with each seed's tilt and noise. "
        f"Window means of {args['window']} samples"
        + (", as `diagnose` by default" if args["window"] == WINDOW else "")
        + ". Counted: `diagnose`'s verdict other than "
        "\"fits to noise\"; `--discover` adding anything; the residual analysis flagging a correlation "
        "or a non-white axis. Rates with their Wilson 95 % interval; target ≤ 5 % each.", "",
        "| clean recordings | diagnose: not \"fits to noise\" | discover: added anything | "
        "residual analysis flagged |",
        "| --- | ---: | ---: | ---: |",
    ]

    def row(label: str, os_: list[Outcome]) -> str:
        n = len(os_)
        return (f"| {label} | " + " | ".join(_rate(sum(o.alarms[k] for o in os_), n) for k in KINDS) + " |")

    for (arm, scenario, dur), os_ in groups.items():
        lines.append(row(f"{arm}, `{scenario}`, {dur:.0f} s", os_))
    for arm in dict.fromkeys(o.case.group[0] for o in parked):
        lines.append(row(f"**{arm} arm, all**", [o for o in parked if o.case.group[0] == arm]))
    lines.append(row("**all**", parked))
    n = len(parked)
    lines += ["", "| target ≤ 5 % over all | " + " | ".join(
        _met(sum(o.alarms[k] for o in parked), n) for k in KINDS) + " |", ""]
    if skipped:
        lines += [f"Not parked (the command would send them to the innovations' analysis): "
                  f"{len(skipped)} recordings of " + ", ".join(sorted({o.case.scenario for o in skipped}))
                  + ".", ""]
    for scenario in dict.fromkeys(o.case.scenario for o in parked):
        raw = np.concatenate([o.raw_p for o in parked if o.case.scenario == scenario and o.raw_p.size]
                             or [np.zeros(0)])
        if raw.size:
            lines.append(f"The score tests one by one on `{scenario}` (uncorrected, {raw.size:,} tests): "
                         f"{100 * np.mean(raw < 0.05):.1f} % below p 0.05, {100 * np.mean(raw < 0.01):.2f} % "
                         "below 0.01 (5 % and 1 % if each test's χ² holds).")
    fr = np.array([o.flag_ratio for o in parked])
    lines += [f"The residual analysis's largest |correlation| over its flag band, per recording: "
              f"median {np.median(fr):.2f}, 95th percentile {np.percentile(fr, 95):.2f}, "
              f"largest {fr.max():.2f} (flagged above 1).", ""]
    rms = np.array([o.rms_ratio for o in parked])
    lines += [f"Whole-model RMS over the noise: median {np.median(rms):.3f}, largest {rms.max():.3f}. "
              f"CPU: {cpu / 60:.1f} min on one core in all ({len(outs)} recordings"
              + (f"; the realistic arms' calibrations and the maneuver's plan {sum(cal_cpu):.0f} s"
                 if cal_cpu else "") + ").", ""]
    bad = [o for o in parked if any(o.alarms.values())]
    if bad:
        lines += ["| recording | verdict (RMS / noise) | discovery added | residual analysis |",
                  "| --- | --- | --- | --- |"]
        for o in bad:
            c = o.case
            lines.append(f"| {c.arm}, `{c.scenario}` {c.duration_s:.0f} s, seed {c.seed} | {o.verdict} "
                         f"({o.rms_ratio:.3f}) | {', '.join(o.added) or '–'} | "
                         f"{'; '.join(o.flags) if not o.white else 'white'} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=40,
                    help="shipped arm: recordings per (scenario, duration), times its share in SHIPPED_PLAN")
    ap.add_argument("--realistic-arms", type=int, default=2, help="realistic arms (each calibrated once)")
    ap.add_argument("--realistic-seeds", type=int, default=6,
                    help="recordings per scenario and duration of each realistic arm")
    ap.add_argument("--calibration-s", type=float, default=300.0, help="the realistic arm's maneuver [s]")
    ap.add_argument("--planned-seeds", type=int, default=10, help="recordings of the planned maneuver")
    ap.add_argument("--rungs", type=int, default=1, help="discovery's rung limit")
    ap.add_argument("--window", type=int, default=WINDOW, help="samples per fit point (diagnose --window)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (CPU figures are per recording)")
    ap.add_argument("--only", help="run only the groups whose label (ARM SCENARIO DURATION s) contains "
                    "this, e.g. 'renk-maneuver 30 s'")
    ap.add_argument("--quick", action="store_true",
                    help="--seeds 2 (shares as SHIPPED_PLAN), no planned maneuver, no realistic arm")
    ap.add_argument("--out", type=Path, help="write the markdown section to this file")
    a = ap.parse_args(argv)
    if a.quick:
        a.seeds, a.realistic_arms, a.planned_seeds = 2, 0, 0
    if (min(a.seeds, a.realistic_arms, a.realistic_seeds, a.planned_seeds) < 0 or a.rungs < 1
            or a.jobs < 1 or a.window < 1 or a.calibration_s <= 0):
        ap.error("--seeds, --realistic-arms, --realistic-seeds and --planned-seeds must be >= 0, "
                 "--rungs, --jobs and --window >= 1, --calibration-s > 0")
    base = load_arm("wmra")
    cases = plan(a.seeds, a.realistic_arms, a.realistic_seeds, a.planned_seeds)
    if a.only:
        cases = [c for c in cases if a.only in f"{c.arm} {c.scenario} {c.duration_s:.0f} s"]
    folder = Path(tempfile.mkdtemp(prefix="bench_null_"))
    arms: dict[str, tuple] = {"shipped": (None, None)}
    cal_cpu: list[float] = []
    for name in dict.fromkeys(c.arm for c in cases if c.arm != "shipped"):
        c0 = time.process_time()
        arms[name] = realistic_arm(base, int(name.split()[1]), a.calibration_s, folder)
        cal_cpu.append(time.process_time() - c0)
        print(f"{name}: calibrated in {cal_cpu[-1]:.0f} s of CPU", flush=True)
    maneuver = None
    if any(c.scenario == PLANNED for c in cases):
        c0 = time.process_time()
        maneuver = planned_maneuver(base)
        cal_cpu.append(time.process_time() - c0)
        print(f"planned the maneuver in {cal_cpu[-1]:.0f} s of CPU", flush=True)
    jobs = [(c, *arms[c.arm], a.rungs, maneuver, a.window) for c in cases]
    outs: list[Outcome] = []
    pool = ProcessPoolExecutor(a.jobs) if a.jobs > 1 else None
    results = pool.map(_work, jobs) if pool is not None else map(_work, jobs)
    for k, o in enumerate(results):
        c = o.case
        outs.append(o)
        print(f"[{k + 1}/{len(cases)}] {c.arm} {c.scenario} {c.duration_s:.0f} s seed {c.seed}: "
              + (f"{o.verdict} ({o.rms_ratio:.3f}x; {o.top}); added {o.added or '-'}; "
                 f"residuals {'white' if o.white else 'FLAGGED ' + '; '.join(o.flags)} "
                 f"(max/band {o.flag_ratio:.2f}); min raw p {o.raw_p.min(initial=1):.2g}"
                 if o.parked else "not parked") + f" [{o.cpu_s:.1f} s]", flush=True)
    if pool is not None:
        pool.shutdown()
    body = section(outs, vars(a), cal_cpu)
    print(body)
    publish("bench_null", body, a.out, a.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
