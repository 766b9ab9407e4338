"""Automatic model discovery (`armfusion diagnose --discover`) measured, on each sweep asked.

The sweeps (``--maneuvers``, a comma-separated list; by default both, in this order):
``renk-maneuver``, the article's generic sweep (``--duration`` s, 60 by default), and
``planned``, the shipped 60 s plan of ``armfusion plan-maneuver`` (config/maneuvers/wmra-60s.yaml:
poses chosen for information over every effect's parameters, what a calibration engineer
commissioning a chair records), played as ``armfusion simulate --maneuver --seed S`` plays it
(each seed's chair tilt and heading, and noise); a path instead of ``planned`` plays that
maneuver file (refused if not safe to play on the WMRA; with ``--duration``, its poses that end
within it).

1. **Hidden effects.** ``--hidden`` recordings of each sweep (window means of 10 samples), each
   with 2 or 3 effects of the library hidden at random: the effects and their targets drawn
   from every (effect, target) pair of the WMRA that a parked recording of *that* sweep can
   show (below), each element's size drawn between one and two of the library's
   datasheet-typical σ (docs/effects.md; the convention of the end-to-end tests), with a
   random sign (plays and sags positive). Seeded. Counted: the full hidden set found (each
   hidden effect added, or in a finding that groups it with effects the recording cannot tell
   apart) with nothing spurious (no finding without a hidden effect in it); the final RMS at
   or below 1.1x the noise.
2. **Clean recordings.** ``--clean`` recordings of each sweep with nothing hidden: nothing added.
3. **Speed.** One recording of ``--hour-s`` (3600) s of ``renk-maneuver`` at 100 Hz with two
   effects hidden (acc2's bias and acc3's board turned, the worked example's pair): the CPU
   time of the whole discovery (BLAS on one thread).

Which pairs are drawn: every effect on every target the library offers on the WMRA, less
``joint_offset`` (the recording's encoder zeros are fitted: a joint's zero offset is one of
them, never a candidate), ``motion_acceleration`` (the sweep's 13.9 °/s puts a 2 cm lever
arm's centripetal term at 0.1 mg, below a minute's noise: docs/workbench.md) and the pairs
the workbench itself lists as ``unseen`` on a clean recording of the sweep (no direction of
their parameters known better than the prior: the gyro's scales on a parked chair, the
play and sag of joints whose gravity torque never changes, …). A more informative sweep
may show more pairs: its benchmark draws from them all.

The same seeds on every sweep (3000 + k hidden, 4000 + k clean) and the same hidden draw
where the pairs allow: the draw is made on ``renk-maneuver``'s pairs (the run of before this
option, unchanged); on another sweep each drawn pair is kept if that sweep can show it, and
each slot is redrawn (:func:`redraw`, its own seeded stream) with the probability that keeps
every pair of that sweep equally likely: to a pair only that sweep shows, or, for a pair it
cannot show, to another one both can.

Writes its section of docs/benchmarks.md only when run with the default sweeps (both, so
that the file cannot show one without the other) and neither ``--quick`` nor ``--seeds``
(``--out FILE``: to that file instead, whatever the sweeps) and prints it.

    nice python tools/bench_discover.py [--maneuvers renk-maneuver,planned] [--hidden 50]
        [--clean 20] [--duration S] [--hour-s 3600] [--quick] [--jobs 1] [--seeds SEED ...]
        [--out FILE]
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.identification.data import FIT_STREAMS_EXCLUDED, data_from_recording  # noqa: E402
from armfusion.fusion.identification.planner import safe_maneuver  # noqa: E402
from armfusion.fusion.workbench.diagnose import DiagnoseSettings, diagnose, fit_model  # noqa: E402
from armfusion.fusion.workbench.discover import Discovery, discover  # noqa: E402
from armfusion.fusion.workbench.scores import EXCLUDED_CANDIDATES, candidate_effects, score_tests  # noqa: E402
from armfusion.models.effects import all_effects, model_from_arm  # noqa: E402
from armfusion.models.simulator import simulate  # noqa: E402
from armfusion.models.trajectories import Scenario  # noqa: E402
from armfusion.models.trajectories.planned import PlannedManeuver, played_scenario  # noqa: E402

from tools.benchdoc import machine_line, publish  # noqa: E402

SCENARIO = "renk-maneuver"
"""The generic sweep (the article's), and the timed hour's."""
PLANNED = "planned"
SHIPPED_PLAN = ROOT / "config" / "maneuvers" / "wmra-60s.yaml"
"""What ``--maneuvers planned`` plays: the shipped 60 s plan of ``plan-maneuver``."""
DEFAULT_SWEEPS = f"{SCENARIO},{PLANNED}"
DEFAULT_DURATION_S = 60.0
"""``renk-maneuver``'s length unless ``--duration`` (a plan plays whole unless it is given)."""
REDRAW_STREAM = 0xD15C
WINDOW = 10
NOT_DRAWN = {"joint_offset": "the recording's encoder zeros are fitted; a joint's zero offset is one of them",
             "motion_acceleration": "the sweep is too slow for a lever arm's centripetal term to show"}
FOUND_TARGET, RMS_TARGET, CLEAN_TARGET, HOUR_TARGET_S = 0.90, 0.95, 0.95, 120.0
NOISE = 1.1
SPEED_HIDDEN = [
    {"effect": "accel_bias", "target": "acc2", "params": {"bias_g": [0.032, -0.027, 0.041]}},
    {"effect": "mount_rotation", "target": "acc3", "params": {"rotvec_rad": [0.021, -0.031, 0.012]}},
]


@dataclass(frozen=True, eq=False)
class Sweep:
    """The motion of a run's recordings: ``renk-maneuver`` (``maneuver`` None) or a planned
    maneuver played with each recording's seed."""

    label: str
    """How the section names it (``renk-maneuver``, or the maneuver file's name)."""
    duration_s: float
    maneuver: PlannedManeuver | None = None

    def scenario(self, arm, seed: int) -> str | Scenario:
        """What recording ``seed`` plays: the named sweep, or the plan with the seed's chair."""
        return SCENARIO if self.maneuver is None else played_scenario(arm, self.maneuver, seed)

    def recording(self, arm, seed: int, effects: list[dict] | None = None):
        """Recording ``seed`` of this sweep with ``effects`` hidden (the simulator's entries)."""
        rec, _ = simulate(arm, self.scenario(arm, seed), self.duration_s, seed=seed, effects=effects)
        return rec

    @property
    def words(self) -> str:
        if self.maneuver is None:
            return f"`{SCENARIO}` {self.duration_s:.0f} s (the article's generic sweep)"
        return f"`{self.label}` {self.duration_s:.0f} s (planned: {len(self.maneuver.poses_rad)} poses)"


def sweep_named(arm, name: str, duration_s: float | None) -> Sweep:
    """``renk-maneuver``, ``planned`` (the shipped plan) or a maneuver file's path, as a sweep;
    a maneuver not safe to play on ``arm`` is refused (``ValueError``)."""
    if name in (SCENARIO, "renk"):
        return Sweep(SCENARIO, DEFAULT_DURATION_S if duration_s is None else duration_s)
    path = SHIPPED_PLAN if name == PLANNED else Path(name)
    plan = safe_maneuver(arm, path)  # (its first poses are as safe)
    if duration_s is not None:
        plan = plan.until(duration_s)
    label = str(SHIPPED_PLAN.relative_to(ROOT)) if path == SHIPPED_PLAN else path.name
    return Sweep(label, plan.duration_s, plan)


@dataclass
class Case:
    seed: int
    sweep: str
    """The sweep's label."""
    hidden: list[dict]
    """Simulator entries, each with ``size_sigma`` (its largest element in typical σ)."""
    discovery: Discovery
    cpu_s: float
    detectable: list[bool]
    """Per hidden effect: whether, alone, it would pass the score test (:func:`detectability`)."""

    @property
    def hidden_names(self) -> list[str]:
        return [f"{h['effect']}:{h['target']}" for h in self.hidden]

    @property
    def missed(self) -> list[str]:
        return [h for h in self.hidden_names if not any(h in f.members for f in self.discovery.findings)]

    @property
    def spurious(self) -> list[str]:
        hid = set(self.hidden_names)
        return [f.added for f in self.discovery.findings if not hid & set(f.members)]

    @property
    def found_all(self) -> bool:
        return not self.missed and not self.spurious

    @property
    def all_detectable(self) -> bool:
        return all(self.detectable)

    @property
    def rms_ok(self) -> bool:
        return self.discovery.final.rms_ratio <= NOISE


def drawable(arm, sweep: Sweep) -> list:
    """Every (effect, target) the sweep can show (module docstring): the library's pairs less
    those never drawn and those a clean recording's diagnosis lists as unseen."""
    rec = sweep.recording(arm, 999)
    d = diagnose(model_from_arm(arm), data_from_recording(arm, rec, window=WINDOW))
    unseen = set(d.unseen)
    return [e for e in all_effects(arm) if e.name not in NOT_DRAWN and e.block_name not in unseen
            and e.block_name not in EXCLUDED_CANDIDATES]


def _entry(e, rng: np.random.Generator) -> dict:
    """Effect ``e`` hidden with each element between 1 and 2 typical σ, a random sign."""
    sig = e.default_sigma()
    mag = rng.uniform(1.0, 2.0, e.size) * sig
    sign = np.ones(e.size) if e.nonnegative else rng.choice([-1.0, 1.0], e.size)
    lo, hi = e.bounds()
    x = np.clip(sign * mag, lo, hi)
    return {"effect": e.name, "target": e.target, "params": {e.key: x.reshape(e.shape).tolist()},
            "size_sigma": float(np.max(np.abs(x) / sig))}


def draw_hidden(pool: list, rng: np.random.Generator) -> list[dict]:
    """2 or 3 distinct (effect, target) pairs, each element between 1 and 2 typical σ."""
    n = int(rng.integers(2, 4))
    picks = rng.choice(len(pool), size=n, replace=False)
    return [_entry(pool[int(i)], rng) for i in picks]


def _block(h: dict) -> str:
    return f"{h['target']}.{h['effect']}"


def redraw(drawn: list[dict], base_pool: list, pool: list, rng: np.random.Generator) -> list[dict]:
    """A draw made on ``base_pool`` (the generic sweep's pairs) for a sweep that can show
    ``pool``: each slot goes, with the probability ``e / len(pool)`` (``e``: the pairs only
    ``pool`` holds), to one of those; else it keeps its pair where ``pool`` holds it, or goes
    to one of the pairs both hold. Each pair of ``pool`` is then as likely in a slot as any
    other (as :func:`draw_hidden` on ``pool`` would make it); no pair twice."""
    base = {e.block_name for e in base_pool}
    extra = [e for e in pool if e.block_name not in base]
    common = [e for e in pool if e.block_name in base]
    names = {e.block_name for e in pool}
    taken = {_block(h) for h in drawn if _block(h) in names}
    out = []
    for h in drawn:
        if extra and rng.random() < len(extra) / len(pool):
            free = [e for e in extra if e.block_name not in taken]
        elif _block(h) in names:
            out.append(h)
            continue
        else:
            free = [e for e in common if e.block_name not in taken]
        if not free:  # every pair taken: the slot keeps its pair if it can, else is dropped
            if _block(h) in names:
                out.append(h)
            continue
        e = free[int(rng.integers(len(free)))]
        taken.add(e.block_name)
        taken.discard(_block(h))
        out.append(_entry(e, rng))
    return out


def detectability(arm, seed: int, sweep: Sweep, hidden: list[dict]) -> list[bool]:
    """Per hidden effect: whether it alone would be significant in this recording's motion.
    On the same recording without effects (same seed: the same sweep and noise), the score
    test's information ``M`` of each hidden block (the fitted parameters projected out) gives
    the expected rise of its statistic, the noncentrality ``λ = δᵀ M δ`` at the hidden value
    ``δ``; detectable when λ exceeds both the corrected critical value of the score test and
    BIC's price ``dof · ln n``. (Each effect alone: the others hidden with it may bend this.)"""
    from scipy.stats import chi2

    data = data_from_recording(arm, sweep.recording(arm, seed), window=WINDOW)
    st = DiagnoseSettings()
    streams = [s for s in data.counts if s not in FIT_STREAMS_EXCLUDED]
    fit = fit_model(model_from_arm(arm), data, streams, st.identify)
    n_cands = len(candidate_effects(fit.model, None))
    cands = [e for e in candidate_effects(fit.model, sorted({h["effect"] for h in hidden}))
             if any(e.block_name == _block(h) for h in hidden)]
    tests = score_tests(fit, data, cands, streams, st.identify, st.chunk_rows, st.evidence_points,
                        lambda _m, _f: None)
    by_block = {c.effect.block_name: c for c in tests.tested}
    out = []
    for h in hidden:
        c = by_block.get(_block(h))
        if c is None:  # unseen
            out.append(False)
            continue
        delta = np.ravel(next(iter(h["params"].values())))
        lam = float(delta @ c.information @ delta)
        out.append(lam > max(chi2.isf(st.alpha / n_cands, c.dof), c.dof * tests.log_n))
    return out


def run_case(arm, seed: int, hidden: list[dict], sweep: Sweep) -> Case:
    entries = [{k: v for k, v in h.items() if k != "size_sigma"} for h in hidden]
    rec = sweep.recording(arm, seed, entries)
    c0 = time.process_time()
    disc = discover(model_from_arm(arm), data_from_recording(arm, rec, window=WINDOW))
    cpu = time.process_time() - c0
    return Case(seed, sweep.label, hidden, disc, cpu,
                detectability(arm, seed, sweep, hidden) if hidden else [])


_WORKER: dict = {}


def _work(job: tuple) -> Case:
    """One recording in a worker process (the arm loaded once per process)."""
    seed, hidden, sweep = job
    if "arm" not in _WORKER:
        _WORKER["arm"] = load_arm("wmra")
    return run_case(_WORKER["arm"], seed, hidden, sweep)


def speed(arm, hour_s: float) -> dict:
    t0 = time.perf_counter()
    rec, _ = simulate(arm, SCENARIO, hour_s, seed=5, effects=SPEED_HIDDEN)
    t_sim = time.perf_counter() - t0
    c0, t0 = time.process_time(), time.perf_counter()
    data = data_from_recording(arm, rec, window=WINDOW)
    disc = discover(model_from_arm(arm), data)
    return {"hour_s": hour_s, "fit_points": data.n, "cpu_s": time.process_time() - c0,
            "wall_s": time.perf_counter() - t0, "simulate_s": t_sim, "load": os.getloadavg()[0],
            "ladder": " → ".join(f"{r.rms_ratio:.2f}" for r in disc.rungs),
            "added": [f.added for f in disc.findings], "stop": disc.stop}


def _share(n: int, of: int) -> str:
    return f"{n} of {of} ({100 * n / max(of, 1):.0f} %)"


def _met(ok: bool) -> str:
    return "met" if ok else "**not met**"


@dataclass
class SweepRun:
    """One sweep's results: its recordings and the pairs it drew from."""

    sweep: Sweep
    hidden: list[Case]
    clean: list[Case]
    pool: list[str]
    """The drawable pairs' block names (``target.effect``)."""

    @property
    def found(self) -> int:
        return sum(c.found_all for c in self.hidden)

    @property
    def found_met(self) -> bool:
        return self.found >= FOUND_TARGET * len(self.hidden)


def _pairs(names) -> str:
    return ", ".join(f"`{n.split('.')[1]}:{n.split('.')[0]}`" for n in names)


def _same_draws(a: SweepRun, b: SweepRun) -> int:
    """Hidden recordings of ``b`` that hide exactly what ``a``'s of the same seed hide."""
    drawn = {c.seed: c.hidden for c in a.hidden}
    return sum(drawn.get(c.seed) == c.hidden for c in b.hidden)


def section(runs: list[SweepRun], sp: dict | None) -> str:
    cols = [f"`{r.sweep.label}`" for r in runs]
    lines = [
        "## Automatic model discovery (`tools/bench_discover.py`)", "",
        f"{machine_line()}; BLAS on one thread. Sweeps: " + "; ".join(r.sweep.words for r in runs)
        + ("; a plan played as `armfusion simulate --maneuver` plays it (each seed's chair tilt, "
           "heading and noise)" if any(r.sweep.maneuver is not None for r in runs) else "")
        + f". Window means of {WINDOW} samples; a different seed per recording, the same seeds on each "
        "sweep. Hidden: 2 or 3 effects drawn at random among the (effect, target) pairs a parked "
        "recording of that sweep can show (the tool's docstring says which are left out and why; the "
        "same draw on each sweep where both show the pair), each element between 1 and 2 of the "
        "library's datasheet-typical σ with a random sign. Found: every hidden effect added, or named "
        "in a finding that groups it with effects the recording cannot tell apart, and no finding "
        "without a hidden effect in it. Detectable alone: on the same recording without effects, the "
        "effect's noncentrality δᵀMδ (M: the score test's information with the fitted parameters "
        "projected out) exceeds the corrected critical value and BIC's price (`detectability` in the "
        "tool); a miss of an effect that is not is one that recording's motion cannot show.", "",
        "| what | target | " + " | ".join(cols) + " |",
        "| --- | ---: | " + " | ".join("---:" for _ in runs) + " |",
        "| (effect, target) pairs drawn from | | " + " | ".join(str(len(r.pool)) for r in runs) + " |",
        f"| hidden draws the same as on `{runs[0].sweep.label}` | | "
        + " | ".join(_share(_same_draws(runs[0], r), len(r.hidden)) for r in runs) + " |",
        f"| hidden set found, nothing spurious | ≥ {100 * FOUND_TARGET:.0f} % | "
        + " | ".join(f"{_share(r.found, len(r.hidden))}, {_met(r.found_met)}" for r in runs) + " |",
    ]
    det = [[c for c in r.hidden if c.all_detectable] for r in runs]
    lines.append("| the same, over the recordings whose every hidden effect is detectable alone "
                 "(an explanation of the misses, not the target) | | "
                 + " | ".join(_share(sum(c.found_all for c in d), len(d)) for d in det) + " |")
    rms = [sum(c.rms_ok for c in r.hidden) for r in runs]
    lines.append(f"| final RMS ≤ {NOISE}x the noise | ≥ {100 * RMS_TARGET:.0f} % | "
                 + " | ".join(f"{_share(k, len(r.hidden))}, {_met(k >= RMS_TARGET * len(r.hidden))}"
                              for k, r in zip(rms, runs, strict=True)) + " |")
    left = [sum(not c.discovery.findings for c in r.clean) for r in runs]
    lines.append(f"| clean recordings: nothing added | ≥ {100 * CLEAN_TARGET:.0f} % | "
                 + " | ".join(f"{_share(k, len(r.clean))}, {_met(k >= CLEAN_TARGET * len(r.clean))}"
                              for k, r in zip(left, runs, strict=True)) + " |")
    lines.append("| findings that grouped effects the recording cannot tell apart | | "
                 + " | ".join(str(sum(f.is_group for c in r.hidden for f in c.discovery.findings))
                              for r in runs) + " |")
    lines.append("| CPU per recording: median, worst | | "
                 + " | ".join(f"{np.median(cpu):.1f} s, {np.max(cpu):.1f} s" if cpu else "–"
                              for cpu in ([c.cpu_s for c in r.hidden + r.clean] for r in runs)) + " |")
    met = [f"`{r.sweep.label}`" for r in runs if r.found_met]
    unmet = [f"`{r.sweep.label}`" for r in runs if not r.found_met]
    lines += ["", f"The issue's target (the hidden set found with nothing spurious in ≥ "
              f"{100 * FOUND_TARGET:.0f} %): " + (f"met on {', '.join(met)}" if met else "met on no sweep")
              + (f"; not met on {', '.join(unmet)}" if unmet else "") + "."]
    base = runs[0]
    for r in runs[1:]:
        more = [p for p in r.pool if p not in base.pool]
        less = [p for p in base.pool if p not in r.pool]
        if more or less:
            lines += ["", f"Pairs `{r.sweep.label}` can show and `{base.sweep.label}` cannot: "
                      f"{_pairs(more) or 'none'}; the other way: {_pairs(less) or 'none'}."]
    lines.append("")
    if sp is not None:
        lines += [f"Speed ({sp['hour_s'] / 3600:.3g} h of 100 Hz `{SCENARIO}` discovered, CPU of one core; "
                  f"target ≤ {HOUR_TARGET_S:.0f} s): **{sp['cpu_s']:.0f} s, "
                  f"{_met(sp['cpu_s'] <= HOUR_TARGET_S)}**. {sp['fit_points']:,} fit points (acc2's bias "
                  f"and acc3's board turned hidden): ladder {sp['ladder']} ({', '.join(sp['added'])}; "
                  f"{sp['stop']}); {sp['cpu_s']:.1f} s of CPU, {sp['wall_s']:.1f} s of wall time at load "
                  f"average {sp['load']:.1f} on this shared machine.", ""]
    for r in runs:
        bad = [c for c in r.hidden if not c.found_all or not c.rms_ok]
        if bad:
            lines += [f"On `{r.sweep.label}`, recordings where the hidden set was not found exactly or the "
                      "RMS stayed above the noise:", "",
                      "| seed | hidden (largest element in typical σ) | found (in order) | final RMS / noise "
                      "| missed | spurious |", "| --- | --- | --- | ---: | --- | --- |"]
            for c in bad:
                hid = ", ".join(f"{n} ({h['size_sigma']:.1f}σ{'' if ok else ', not detectable alone'})"
                                for n, h, ok in zip(c.hidden_names, c.hidden, c.detectable, strict=True))
                got = ", ".join(f.added + (f" (or {', '.join(f.members[1:])})" if f.is_group else "")
                                for f in c.discovery.findings)
                lines.append(f"| {c.seed} | {hid} | {got or '–'} | {c.discovery.final.rms_ratio:.3f} | "
                             f"{', '.join(c.missed) or '–'} | {', '.join(c.spurious) or '–'} |")
            lines.append("")
        noisy = [c for c in r.clean if c.discovery.findings]
        if noisy:
            lines += [f"On `{r.sweep.label}`, clean recordings where something was added: "
                      + "; ".join(f"seed {c.seed}: {', '.join(f.added for f in c.discovery.findings)}"
                                  for c in noisy) + ".", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--maneuvers", default=DEFAULT_SWEEPS,
                    help=f"comma-separated sweeps: {SCENARIO}, {PLANNED} (the shipped plan) or a maneuver "
                    f"file's path (default: {DEFAULT_SWEEPS}; the file is written only with the default)")
    ap.add_argument("--hidden", type=int, default=50)
    ap.add_argument("--clean", type=int, default=20)
    ap.add_argument("--duration", type=float,
                    help=f"seconds per recording ({SCENARIO}: {DEFAULT_DURATION_S:.0f} by default; a "
                    "plan: its poses that end within it, whole by default)")
    ap.add_argument("--hour-s", type=float, default=3600.0, help="the timed recording's length (0: skip)")
    ap.add_argument("--quick", action="store_true", help="8 hidden, 4 clean, no timed hour")
    ap.add_argument("--seed", type=int, default=0, help="the draw's seed")
    ap.add_argument("--out", type=Path, help="write the markdown section to this file")
    ap.add_argument("--jobs", type=int, default=1,
                    help="worker processes for the recordings (CPU figures are per recording; the "
                    "timed hour runs after them, alone)")
    ap.add_argument("--seeds", type=int, nargs="+", metavar="SEED",
                    help="run only these recordings' seeds (3000 + k: hidden, 4000 + k: clean; the draw "
                    "is the whole run's, so a hidden seed gets the effects it gets in the whole run); "
                    "nothing is published unless --out")
    a = ap.parse_args(argv)
    if a.quick:
        a.hidden, a.clean, a.hour_s = 8, 4, 0.0
    if a.hidden < 0 or a.clean < 0 or (a.duration is not None and a.duration <= 0) or a.jobs < 1:
        ap.error("--hidden and --clean must be >= 0, --duration > 0 and --jobs >= 1")
    arm = load_arm("wmra")
    names = [n.strip() for n in a.maneuvers.split(",") if n.strip()]
    if not names:
        ap.error("--maneuvers: name at least one sweep")
    try:
        sweeps = [sweep_named(arm, n, a.duration) for n in names]
    except (OSError, ValueError) as err:
        ap.error(f"--maneuvers: {err}")
    if len({s.label for s in sweeps}) < len(sweeps):
        ap.error(f"--maneuvers: a sweep named twice in {a.maneuvers}")
    generic = sweeps[0] if sweeps[0].maneuver is None else sweep_named(arm, SCENARIO, a.duration)
    base_pool = drawable(arm, generic)
    rng = np.random.default_rng(a.seed)
    draws = [draw_hidden(base_pool, rng) for _ in range(a.hidden)]
    chosen = None if a.seeds is None else set(a.seeds)
    jobs, pools = [], {}
    for sweep in sweeps:
        pool = base_pool if sweep.label == generic.label else drawable(arm, sweep)
        pools[sweep.label] = pool
        again = np.random.default_rng([a.seed, REDRAW_STREAM])
        for k, drawn in enumerate(draws):  # redrawn for every k: a chosen seed's draw is the whole run's
            hidden = drawn if pool is base_pool else redraw(drawn, base_pool, pool, again)
            if chosen is None or 3000 + k in chosen:
                jobs.append((3000 + k, hidden, sweep))
        jobs += [(4000 + k, [], sweep) for k in range(a.clean) if chosen is None or 4000 + k in chosen]
    workers = ProcessPoolExecutor(a.jobs) if a.jobs > 1 else None
    results = workers.map(_work, jobs) if workers is not None else map(_work, jobs)
    runs = {s.label: SweepRun(s, [], [], [e.block_name for e in pools[s.label]]) for s in sweeps}
    for c in results:
        r = runs[c.sweep]
        if c.hidden:
            r.hidden.append(c)
            print(f"{c.sweep} hidden seed {c.seed}: {', '.join(c.hidden_names)} -> "
                  f"{'; '.join(f.words() if f.is_group else f.added for f in c.discovery.findings)} "
                  f"[{c.discovery.final.rms_ratio:.3f}x, {'found' if c.found_all else 'MISSED'}; "
                  f"{c.cpu_s:.1f} s]", flush=True)
        else:
            r.clean.append(c)
            print(f"{c.sweep} clean seed {c.seed}: {[f.added for f in c.discovery.findings]} "
                  f"[{c.discovery.final.rms_ratio:.3f}x; {c.cpu_s:.1f} s]", flush=True)
    if workers is not None:
        workers.shutdown()
    sp = None
    if a.hour_s > 0 and chosen is None:
        sp = speed(arm, a.hour_s)
        print(f"speed: {sp}", flush=True)
    body = section(list(runs.values()), sp)
    print(body)
    partial = a.quick or chosen is not None or names != DEFAULT_SWEEPS.split(",")
    publish("bench_discover", body, a.out, partial)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
