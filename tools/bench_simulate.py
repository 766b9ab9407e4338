"""How fast the simulator is: one hour of `daily-use` at 100 Hz, on one core.

Times ``armfusion.models.simulator.simulate`` (motion, kinematics with every motion term, effects,
noise, rounding) for ideal sensors and for ``--realistic`` (every effect of the library on
every target), then writing the recording as CSV and as MCAP. BLAS is held to one thread
so the figure is a one-core figure. Writes its section of docs/benchmarks.md.

    python tools/bench_simulate.py [--duration 3600] [--rate 100] [--repeats 2] [--no-write]
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.models.simulator import build_model, simulate  # noqa: E402
from armfusion.sensors.recording import write_recording  # noqa: E402

from tools.benchdoc import machine_line, write_section  # noqa: E402

TARGET_S = 30.0


def timed(fn, repeats: int):
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3600.0, help="simulated seconds")
    ap.add_argument("--rate", type=float, default=100.0, help="Hz")
    ap.add_argument("--repeats", type=int, default=2, help="best of this many runs")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md")
    a = ap.parse_args()
    arm = load_arm("wmra")
    n = int(a.duration * a.rate)
    rows = []
    simulate(arm, "daily-use", 1.0, a.rate, seed=1)  # numba loads the compiled kinematics (once, ~0.5 s)
    t_ideal, (rec, truth) = timed(lambda: simulate(arm, "daily-use", a.duration, a.rate, seed=1), a.repeats)
    rows.append(("`daily-use`, ideal sensors (noise, rounding)", t_ideal))
    t_real, (rec_r, truth_r) = timed(
        lambda: simulate(arm, "daily-use", a.duration, a.rate, seed=1, realistic=True), a.repeats)
    n_eff = len(truth_r["effects"])
    n_par = build_model(arm, realistic=True)[0].size
    rows.append((f"`daily-use --realistic` ({n_eff} effects, {n_par} parameters)", t_real))
    sizes = {}
    with tempfile.TemporaryDirectory() as d:
        for suffix in (".csv", ".mcap"):
            p = Path(d) / f"rec{suffix}"
            t_w, _ = timed(lambda p=p: write_recording(rec, p), 1)
            sizes[suffix] = p.stat().st_size
            rows.append((f"writing it as {suffix[1:].upper()} ({sizes[suffix] / 1e6:.0f} MB)", t_w))
    streams = [s for s in rec.raw()]
    lines = [
        "## Simulator (`tools/bench_simulate.py`)",
        "",
        f"WMRA, {a.duration / 3600:g} h of `daily-use` at {a.rate:g} Hz ({n:,} instants; streams "
        f"{', '.join(streams)} and the truth columns), one BLAS thread, best of {a.repeats} (the "
        f"compiled kernels loaded first, once per process); "
        f"{machine_line()}.",
        "",
        "| what | wall time | x real time | instants / s |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name, t in rows:
        lines.append(f"| {name} | {t:.1f} s | {a.duration / t:,.0f} | {n / t:,.0f} |")
    lines += [
        "",
        f"Target: 1 h at 100 Hz in under {TARGET_S:.0f} s on one core. Ideal sensors: "
        f"**{t_ideal:.1f} s**; with every effect drawn: **{t_real:.1f} s** "
        f"({'met' if max(t_ideal, t_real) < TARGET_S else 'NOT met'}).",
    ]
    md = "\n".join(lines)
    print(md)
    if not a.no_write:
        print(f"\nwritten to {write_section('bench_simulate', md)}")


if __name__ == "__main__":
    main()
