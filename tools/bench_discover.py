"""Automatic model discovery (`armfusion diagnose --discover`) measured.

1. **Hidden effects.** ``--hidden`` recordings (``--duration`` s of the article's sweep,
   ``renk-maneuver``, window means of 10 samples), each with 2 or 3 effects of the library
   hidden at random: the effects and their targets drawn from every (effect, target) pair of
   the WMRA that a parked sweep can show (below), each element's size drawn between one and
   two of the library's datasheet-typical σ (docs/effects.md; the convention of the
   end-to-end tests), with a random sign (plays and sags positive). Seeded. Counted: the
   full hidden set found (each hidden effect added, or in a finding that groups it with
   effects the recording cannot tell apart) with nothing spurious (no finding without a
   hidden effect in it); the final RMS at or below 1.1x the noise.
2. **Clean recordings.** ``--clean`` recordings with nothing hidden: nothing added.
3. **Speed.** One recording of ``--hour-s`` (3600) s at 100 Hz with two effects hidden
   (acc2's bias and acc3's board turned, the worked example's pair): the CPU time of the
   whole discovery (BLAS on one thread).

Which pairs are drawn: every effect on every target the library offers on the WMRA, less
``joint_offset`` (the recording's encoder zeros are fitted: a joint's zero offset is one of
them, never a candidate), ``motion_acceleration`` (the sweep's 13.9 °/s puts a 2 cm lever
arm's centripetal term at 0.1 mg, below a minute's noise: docs/workbench.md) and the pairs
the workbench itself lists as ``unseen`` on a clean recording of the sweep (no direction of
their parameters known better than the prior: the gyro's scales on a parked chair, the
play and sag of joints whose gravity torque never changes, …).

Writes its section of docs/benchmarks.md (``--out FILE``: to that file instead; ``--quick``:
neither unless ``--out``) and prints it.

    nice python tools/bench_discover.py [--hidden 50] [--clean 20] [--duration 60]
        [--hour-s 3600] [--quick] [--jobs 1] [--seeds SEED ...] [--out FILE]
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

from fusion.configfile import load_arm  # noqa: E402
from fusion.identification.data import FIT_STREAMS_EXCLUDED, data_from_recording  # noqa: E402
from fusion.workbench.diagnose import DiagnoseSettings, diagnose, fit_model  # noqa: E402
from fusion.workbench.discover import Discovery, discover  # noqa: E402
from fusion.workbench.scores import EXCLUDED_CANDIDATES, candidate_effects, score_tests  # noqa: E402
from models.effects import all_effects, model_from_arm  # noqa: E402
from models.simulator import simulate  # noqa: E402
from tools.benchdoc import machine_line, publish  # noqa: E402

SCENARIO = "renk-maneuver"
WINDOW = 10
NOT_DRAWN = {"joint_offset": "the recording's encoder zeros are fitted; a joint's zero offset is one of them",
             "motion_acceleration": "the sweep is too slow for a lever arm's centripetal term to show"}
FOUND_TARGET, RMS_TARGET, CLEAN_TARGET, HOUR_TARGET_S = 0.90, 0.95, 0.95, 120.0
NOISE = 1.1
SPEED_HIDDEN = [
    {"effect": "accel_bias", "target": "acc2", "params": {"bias_g": [0.032, -0.027, 0.041]}},
    {"effect": "mount_rotation", "target": "acc3", "params": {"rotvec_rad": [0.021, -0.031, 0.012]}},
]


@dataclass
class Case:
    seed: int
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


def drawable(arm, duration_s: float) -> list:
    """Every (effect, target) the sweep can show (module docstring): the library's pairs less
    those never drawn and those a clean recording's diagnosis lists as unseen."""
    rec, _ = simulate(arm, SCENARIO, duration_s, seed=999)
    d = diagnose(model_from_arm(arm), data_from_recording(arm, rec, window=WINDOW))
    unseen = set(d.unseen)
    return [e for e in all_effects(arm) if e.name not in NOT_DRAWN and e.block_name not in unseen
            and e.block_name not in EXCLUDED_CANDIDATES]


def draw_hidden(pool: list, rng: np.random.Generator) -> list[dict]:
    """2 or 3 distinct (effect, target) pairs, each element between 1 and 2 typical σ."""
    n = int(rng.integers(2, 4))
    picks = rng.choice(len(pool), size=n, replace=False)
    out = []
    for i in picks:
        e = pool[int(i)]
        sig = e.default_sigma()
        mag = rng.uniform(1.0, 2.0, e.size) * sig
        sign = np.ones(e.size) if e.nonnegative else rng.choice([-1.0, 1.0], e.size)
        lo, hi = e.bounds()
        x = np.clip(sign * mag, lo, hi)
        out.append({"effect": e.name, "target": e.target, "params": {e.key: x.reshape(e.shape).tolist()},
                    "size_sigma": float(np.max(np.abs(x) / sig))})
    return out


def detectability(arm, seed: int, duration_s: float, hidden: list[dict]) -> list[bool]:
    """Per hidden effect: whether it alone would be significant in this recording's motion.
    On the same recording without effects (same seed: the same sweep and noise), the score
    test's information ``M`` of each hidden block (the fitted parameters projected out) gives
    the expected rise of its statistic, the noncentrality ``λ = δᵀ M δ`` at the hidden value
    ``δ``; detectable when λ exceeds both the corrected critical value of the score test and
    BIC's price ``dof · ln n``. (Each effect alone: the others hidden with it may bend this.)"""
    from scipy.stats import chi2

    rec, _ = simulate(arm, SCENARIO, duration_s, seed=seed)
    data = data_from_recording(arm, rec, window=WINDOW)
    st = DiagnoseSettings()
    streams = [s for s in data.counts if s not in FIT_STREAMS_EXCLUDED]
    fit = fit_model(model_from_arm(arm), data, streams, st.identify)
    n_cands = len(candidate_effects(fit.model, None))
    cands = [e for e in candidate_effects(fit.model, sorted({h["effect"] for h in hidden}))
             if any(e.block_name == f"{h['target']}.{h['effect']}" for h in hidden)]
    tests = score_tests(fit, data, cands, streams, st.identify, st.chunk_rows, st.evidence_points,
                        lambda _m, _f: None)
    by_block = {c.effect.block_name: c for c in tests.tested}
    out = []
    for h in hidden:
        c = by_block.get(f"{h['target']}.{h['effect']}")
        if c is None:  # unseen
            out.append(False)
            continue
        delta = np.ravel(next(iter(h["params"].values())))
        lam = float(delta @ c.information @ delta)
        out.append(lam > max(chi2.isf(st.alpha / n_cands, c.dof), c.dof * tests.log_n))
    return out


def run_case(arm, seed: int, hidden: list[dict], duration_s: float) -> Case:
    entries = [{k: v for k, v in h.items() if k != "size_sigma"} for h in hidden]
    rec, _ = simulate(arm, SCENARIO, duration_s, seed=seed, effects=entries)
    c0 = time.process_time()
    disc = discover(model_from_arm(arm), data_from_recording(arm, rec, window=WINDOW))
    cpu = time.process_time() - c0
    return Case(seed, hidden, disc, cpu, detectability(arm, seed, duration_s, hidden) if hidden else [])


_WORKER: dict = {}


def _work(job: tuple) -> Case:
    """One recording in a worker process (the arm loaded once per process)."""
    seed, hidden, duration_s = job
    if "arm" not in _WORKER:
        _WORKER["arm"] = load_arm("wmra")
    return run_case(_WORKER["arm"], seed, hidden, duration_s)


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


def section(hidden: list[Case], clean: list[Case], sp: dict | None, duration_s: float, pool_n: int) -> str:
    nh, nc = len(hidden), len(clean)
    found = sum(c.found_all for c in hidden)
    rms = sum(c.rms_ok for c in hidden)
    left = sum(not c.discovery.findings for c in clean)
    groups = sum(f.is_group for c in hidden for f in c.discovery.findings)
    cpu = [c.cpu_s for c in hidden + clean]
    det = [c for c in hidden if c.all_detectable]
    found_det = sum(c.found_all for c in det)
    lines = [
        "## Automatic model discovery (`tools/bench_discover.py`)", "",
        f"{machine_line()}; BLAS on one thread. Each recording {duration_s:.0f} s of `{SCENARIO}` "
        f"(window means of {WINDOW} samples), a different seed each. Hidden: 2 or 3 effects drawn at "
        f"random among the {pool_n} (effect, target) pairs a parked sweep can show (the tool's docstring "
        "says which are left out and why), each element between 1 and 2 of the library's datasheet-typical "
        "σ with a random sign. Found: every hidden effect added, or named in a finding that groups it with "
        "effects the recording cannot tell apart, and no finding without a hidden effect in it. "
        "Detectable alone: on the same sweep without effects, the effect's noncentrality δᵀMδ (M: the score "
        "test's information with the fitted parameters projected out) exceeds the corrected critical value "
        "and BIC's price (`detectability` in the tool); a miss of an effect that is not is one a minute of "
        "this sweep cannot show.", "",
        "| what | result | target | |", "| --- | ---: | ---: | --- |",
        f"| hidden set found, nothing spurious | {_share(found, nh)} | ≥ {100 * FOUND_TARGET:.0f} % | "
        f"{_met(found >= FOUND_TARGET * nh)} |",
        f"| the same, over the {len(det)} recordings whose every hidden effect "
        f"is detectable alone | {_share(found_det, len(det))} "
        "| | (not the target: an explanation of the misses) |",
        f"| final RMS ≤ {NOISE}x the noise | {_share(rms, nh)} | ≥ {100 * RMS_TARGET:.0f} % | "
        f"{_met(rms >= RMS_TARGET * nh)} |",
        f"| clean recordings: nothing added | {_share(left, nc)} | ≥ {100 * CLEAN_TARGET:.0f} % | "
        f"{_met(left >= CLEAN_TARGET * nc)} |",
    ]
    if sp is not None:
        lines.append(f"| {sp['hour_s'] / 3600:.3g} h of 100 Hz data discovered, CPU of one core | "
                     f"{sp['cpu_s']:.0f} s | ≤ {HOUR_TARGET_S:.0f} s | "
                     f"{_met(sp['cpu_s'] <= HOUR_TARGET_S)} |")
    lines += ["", f"Findings that grouped effects the recording cannot tell apart: {groups}. "
              f"CPU per {duration_s:.0f} s recording: median {np.median(cpu):.1f} s, "
              f"worst {np.max(cpu):.1f} s.", ""]
    if sp is not None:
        lines += [f"Speed: {sp['fit_points']:,} fit points (acc2's bias and acc3's board turned hidden): "
                  "ladder "
                  f"{sp['ladder']} ({', '.join(sp['added'])}; {sp['stop']}); {sp['cpu_s']:.1f} s of CPU, "
                  f"{sp['wall_s']:.1f} s of wall time at load average {sp['load']:.1f} on this shared "
                  "machine.", ""]
    bad = [c for c in hidden if not c.found_all or not c.rms_ok]
    if bad:
        lines += ["Recordings where the hidden set was not found exactly or the RMS stayed above the noise:",
                  "",
                  "| seed | hidden (largest element in typical σ) | found (in order) | final RMS / noise "
                  "| missed | "
                  "spurious |", "| --- | --- | --- | ---: | --- | --- |"]
        for c in bad:
            hid = ", ".join(f"{n} ({h['size_sigma']:.1f}σ{'' if ok else ', not detectable alone'})"
                            for n, h, ok in zip(c.hidden_names, c.hidden, c.detectable, strict=True))
            got = ", ".join(f.added + (f" (or {', '.join(f.members[1:])})" if f.is_group else "")
                            for f in c.discovery.findings)
            lines.append(f"| {c.seed} | {hid} | {got or '–'} | {c.discovery.final.rms_ratio:.3f} | "
                         f"{', '.join(c.missed) or '–'} | {', '.join(c.spurious) or '–'} |")
        lines.append("")
    noisy = [c for c in clean if c.discovery.findings]
    if noisy:
        lines += ["Clean recordings where something was added: "
                  + "; ".join(f"seed {c.seed}: {', '.join(f.added for f in c.discovery.findings)}"
                              for c in noisy)
                  + ".", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hidden", type=int, default=50)
    ap.add_argument("--clean", type=int, default=20)
    ap.add_argument("--duration", type=float, default=60.0, help="seconds per recording")
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
    if a.hidden < 0 or a.clean < 0 or a.duration <= 0 or a.jobs < 1:
        ap.error("--hidden and --clean must be >= 0, --duration > 0 and --jobs >= 1")
    arm = load_arm("wmra")
    pool = drawable(arm, a.duration)
    rng = np.random.default_rng(a.seed)
    chosen = None if a.seeds is None else set(a.seeds)
    jobs = []
    for k in range(a.hidden):
        drawn = draw_hidden(pool, rng)  # drawn for every k: a chosen seed's draw is the whole run's
        if chosen is None or 3000 + k in chosen:
            jobs.append((3000 + k, drawn, a.duration))
    jobs += [(4000 + k, [], a.duration) for k in range(a.clean) if chosen is None or 4000 + k in chosen]
    workers = ProcessPoolExecutor(a.jobs) if a.jobs > 1 else None
    results = workers.map(_work, jobs) if workers is not None else map(_work, jobs)
    hidden, clean = [], []
    for c in results:
        if c.hidden:
            hidden.append(c)
            print(f"hidden seed {c.seed}: {', '.join(c.hidden_names)} -> "
                  f"{'; '.join(f.words() if f.is_group else f.added for f in c.discovery.findings)} "
                  f"[{c.discovery.final.rms_ratio:.3f}x, {'found' if c.found_all else 'MISSED'}; "
                  f"{c.cpu_s:.1f} s]", flush=True)
        else:
            clean.append(c)
            print(f"clean seed {c.seed}: {[f.added for f in c.discovery.findings]} "
                  f"[{c.discovery.final.rms_ratio:.3f}x; {c.cpu_s:.1f} s]", flush=True)
    if workers is not None:
        workers.shutdown()
    sp = None
    if a.hour_s > 0 and chosen is None:
        sp = speed(arm, a.hour_s)
        print(f"speed: {sp}", flush=True)
    body = section(hidden, clean, sp, a.duration, len(pool))
    print(body)
    publish("bench_discover", body, a.out, a.quick or chosen is not None)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
