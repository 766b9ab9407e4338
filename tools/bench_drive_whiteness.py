"""The tracker's innovations while the chair drives: how many clean driving recordings does
`armfusion diagnose` call white?

Each recording is simulated with a correct model (the shipped WMRA, no hidden effect, the
sensors' own noise) and diagnosed as `diagnose` diagnoses a recording in which the chair
moves (:func:`armfusion.fusion.workbench.innovations.innovation_diagnosis`: the tracker's normalised
innovations over 0.5 s blocks, their whiteness and their correlation with the inputs). A
correct model should be called "innovations white" on all but about 1 % of them (the
analysis's corrected 99 % band). The scenarios:

- ``daily-use`` (``--daily-s`` each): reaching while the chair drives (starts and stops,
  turns at speed, turns on the spot, ramps and cross slopes);
- ``excitation`` (``--excitation-s`` each): every joint moving while the chair turns on the
  spot back and forth and rocks on ramps.

A recording in which the chair does not turn (:func:`armfusion.fusion.workbench.innovations.chair_moves`
false: `diagnose` would fit it as parked) is not a driving recording and is counted apart.
The default 24 seeds of each give at least 40 driving recordings (a few ``daily-use`` seeds
do not turn within their 90 s).

    python tools/bench_drive_whiteness.py [--seeds 24] [--first-seed 0] [--daily-s 90]
        [--excitation-s 60] [--scenarios daily-use,excitation] [--quick] [--out FILE]

``--first-seed K``: seeds K … K+N-1 (other seeds than the documented run's). ``--scenarios``:
one or both. ``--quick``: 4 seeds of each, shorter (docs/benchmarks.md untouched).
``--out FILE`` writes the markdown section there instead of into its section of
docs/benchmarks.md.
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.workbench.innovations import chair_moves, innovation_diagnosis  # noqa: E402
from armfusion.models.simulator import simulate  # noqa: E402

from tools.benchdoc import machine_line, write_section  # noqa: E402


def diagnose_one(arm, scenario: str, seed: int, duration_s: float) -> dict:
    """One clean recording, simulated and diagnosed: its verdict, its worst axes."""
    rec, _ = simulate(arm, scenario, duration_s, seed=seed)
    if not chair_moves(arm, rec):
        return {"scenario": scenario, "seed": seed, "duration_s": duration_s, "drives": False}
    t0 = time.process_time()
    inn = innovation_diagnosis(arm, rec)
    cpu = time.process_time() - t0
    worst = inn.not_white()[:1]
    flag = inn.flagged()[:1]
    return {"scenario": scenario, "seed": seed, "duration_s": duration_s, "drives": True,
            "white": inn.white, "cpu_s": cpu,
            "worst_autocorr": (worst[0][1], round(worst[0][2], 2)) if worst else None,
            "worst_input": (flag[0].axis, flag[0].input, round(flag[0].r, 2), flag[0].lag) if flag else None}


def _commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return out.stdout.strip() + (" (uncommitted changes)" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=24, help="seeds per scenario (K … K+N-1)")
    ap.add_argument("--first-seed", type=int, default=0, help="the first seed K")
    ap.add_argument("--scenarios", default="daily-use,excitation",
                    help="comma-separated: daily-use, excitation or both")
    ap.add_argument("--daily-s", type=float, default=90.0, help="length of each daily-use recording, s")
    ap.add_argument("--excitation-s", type=float, default=60.0, help="length of each excitation recording, s")
    ap.add_argument("--quick", action="store_true", help="4 seeds of each, 60 s and 40 s")
    ap.add_argument("--out", type=Path, default=None, help="write the markdown section to this file")
    a = ap.parse_args()
    if a.quick:
        a.seeds, a.daily_s, a.excitation_s = 4, 60.0, 40.0
    if a.seeds < 1 or a.first_seed < 0 or not (a.daily_s > 0 and a.excitation_s > 0):
        ap.error("--seeds must be at least 1, --first-seed at least 0 and the durations positive")
    length = {"daily-use": a.daily_s, "excitation": a.excitation_s}
    scenarios = [x.strip() for x in a.scenarios.split(",") if x.strip()]
    if not scenarios or any(x not in length for x in scenarios):
        ap.error(f"--scenarios: one or both of {', '.join(length)}, comma-separated "
                 f"(got {a.scenarios[:40]!r})")
    arm = load_arm("wmra")
    seeds = range(a.first_seed, a.first_seed + a.seeds)
    plan = [(sc, s, length[sc]) for sc in scenarios for s in seeds]
    rows = []
    t_start = time.perf_counter()
    for i, (sc, seed, dur) in enumerate(plan):
        r = diagnose_one(arm, sc, seed, dur)
        rows.append(r)
        what = ("not driving" if not r["drives"] else ("white" if r["white"] else
                f"NOT white (autocorr {r['worst_autocorr']}, input {r['worst_input']})"))
        print(f"[{i + 1}/{len(plan)}] {sc} seed {seed} ({dur:.0f} s): {what}", flush=True)
    wall = time.perf_counter() - t_start
    driving = [r for r in rows if r["drives"]]
    white = [r for r in driving if r["white"]]
    share = len(white) / len(driving) if driving else float("nan")
    per = {}
    for sc in scenarios:
        d = [r for r in driving if r["scenario"] == sc]
        per[sc] = (sum(r["white"] for r in d), len(d))
    print(f"white: {len(white)} of {len(driving)} driving recordings ({100 * share:.1f} %); "
          + "; ".join(f"{sc} {w}/{n}" for sc, (w, n) in per.items())
          + f"; not driving: {len(rows) - len(driving)}; {wall:.0f} s")
    md = [
        "## The tracker's innovations while the chair drives (`tools/bench_drive_whiteness.py`)",
        "",
        f"Clean recordings (the shipped WMRA, no hidden effect), seeds {seeds[0]}-{seeds[-1]} of "
        + " and of ".join(f"`{sc}` ({length[sc]:.0f} s each)" for sc in scenarios) + ", each diagnosed as "
        "`armfusion diagnose` diagnoses a moving chair (the tracker's normalised innovations over 0.5 s "
        f"blocks, `armfusion.fusion.workbench.innovations.innovation_diagnosis`); code {_commit()}; {machine_line()}.",
        "",
        "| scenario | driving recordings | called white |",
        "| --- | ---: | ---: |",
    ]
    for sc, (w, n) in per.items():
        md.append(f"| `{sc}` | {n} | {w} ({100 * w / n:.0f} %) |" if n else f"| `{sc}` | 0 | - |")
    md += ["", f"**{len(white)} of {len(driving)} ({100 * share:.1f} %)** called \"innovations white\" "
           f"(target ≥ 95 %); {len(rows) - len(driving)} recording(s) in which the chair did not turn "
           "left out."]
    bad = [r for r in driving if not r["white"]]
    if bad:
        md += ["", "Called not white:", ""]
        md += [f"- `{r['scenario']}` seed {r['seed']}: worst autocorrelation {r['worst_autocorr']}, "
               f"strongest input correlation {r['worst_input']}" for r in bad]
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text("\n".join(md) + "\n", encoding="utf-8")
        print("wrote", a.out)
    elif not a.quick:
        print("wrote", write_section("bench_drive_whiteness", "\n".join(md)))


if __name__ == "__main__":
    main()
