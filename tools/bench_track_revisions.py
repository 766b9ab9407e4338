"""The tracker at two revisions of the code, side by side: speed and sameness.

Runs the tracker (``Tracker.run``, everything included) over one simulated WMRA ``daily-use``
recording with the code of the working tree and with the code of another git revision
(``--base``, default ``main``; checked out into a temporary worktree, removed afterwards),
each in its own process, alternately (``--repeats`` times each; the best CPU time of each
kept), and compares what the two reported at every instant (joint angles, sigmas, attitude,
gyro bias, statuses: the largest difference). For a change meant to leave the filter's
numbers alone (a refactor) it says whether they are; for one meant to speed it up, by how
much, measured in one run on the same machine.

    python tools/bench_track_revisions.py [--base main] [--duration 120] [--repeats 1] [--no-write]

BLAS runs on one thread (``OPENBLAS_NUM_THREADS=1`` unless set).
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent.parent
FIELDS = ("q_rad", "sigma_rad", "rpy_rad", "rpy_sigma_rad", "gyro_bias_rad_s", "sensor_status", "flags")


def child(root: str, out: str, duration_s: float, seed: int) -> None:
    """In a process of its own: the code under ``root`` over the recording, run twice (the
    first loads the compiled kernels), the second timed; its per-instant outputs to ``out``."""
    sys.path.insert(0, root)

    if not str(Path(fusion.__file__).resolve()).startswith(str(Path(root).resolve())):
        raise SystemExit(f"the code under {root} was not the one imported ({fusion.__file__})")
    from armfusion.fusion.tracking.tracker import start_from_recording
    from armfusion.models.simulator import simulate

    from tools.bench_track import calibrated_wmra

    arm = calibrated_wmra()
    rec, _ = simulate(arm, "daily-use", duration_s, seed=seed)
    for _ in range(2):
        tr, _start = start_from_recording(arm, rec)
        c0 = time.process_time()
        run = tr.run(rec)
        cpu = time.process_time() - c0
    arrays = {k: np.asarray(getattr(run, k), dtype=float) for k in FIELDS}
    np.savez(out, cpu_s=cpu, steps=run.steps, **arrays)


def run_child(root: Path, out: Path, a) -> dict:
    subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(root), str(out),
                    "--duration", str(a.duration), "--seed", str(a.seed)], check=True, cwd=root)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="main", help="the git revision to compare against")
    ap.add_argument("--duration", type=float, default=120.0, help="daily-use recording length, s")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=1, help="runs of each revision, alternating (best kept)")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--child", nargs=2, metavar=("ROOT", "OUT"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child[0], a.child[1], a.duration, a.seed)
        return
    base_sha = subprocess.run(["git", "rev-parse", "--short", a.base], cwd=HERE, check=True,
                              capture_output=True, text=True).stdout.strip()
    head_sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, check=True,
                              capture_output=True, text=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=HERE,
                                check=True, capture_output=True, text=True).stdout.strip())
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "base"
        subprocess.run(["git", "worktree", "add", "--detach", "--quiet", str(tree), a.base], cwd=HERE,
                       check=True)
        try:
            best = {"base": None, "ours": None}
            load_before = os.getloadavg()[0]
            for rep in range(a.repeats):
                for who, root in (("base", tree), ("ours", HERE)):
                    r = run_child(root, Path(tmp) / f"{who}.npz", a)
                    if best[who] is None or r["cpu_s"] < best[who]["cpu_s"]:
                        best[who] = r
                    print(f"[{rep + 1}/{a.repeats}] {who}: {int(r['steps'])} steps, "
                          f"{float(r['steps'] / r['cpu_s']):.0f} per CPU second")
            load_after = os.getloadavg()[0]
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=HERE, check=False)
    b, o = best["base"], best["ours"]
    rate_b, rate_o = float(b["steps"] / b["cpu_s"]), float(o["steps"] / o["cpu_s"])
    diffs = {}
    for k in FIELDS:
        x, y = b[k], o[k]
        diffs[k] = (float("inf") if x.shape != y.shape else
                    float(np.nanmax(np.abs(x - y), initial=0.0)) if np.array_equal(np.isnan(x), np.isnan(y))
                    else float("inf"))
    same = all(v == 0.0 for v in diffs.values())
    print(f"steps per CPU second: {a.base} ({base_sha}) {rate_b:.0f}, this tree {rate_o:.0f}: "
          f"ratio {rate_o / rate_b:.3f}")
    print("largest difference per output:", json.dumps(diffs))
    sys.path.insert(0, str(HERE))
    from tools.benchdoc import machine_line, write_section

    md = [
        "## Tracker at two revisions (`tools/bench_track_revisions.py`)",
        "",
        f"Simulated `daily-use`, {a.duration:.0f} s at 100 Hz (seed {a.seed}), the WMRA with calibrated "
        f"sensors, `Tracker.run` over the whole recording after the startup; {a.base} ({base_sha}) against "
        f"the working "
        f"tree ({head_sha}{', with changes' if dirty else ''}), each in its own process, alternately, "
        f"{a.repeats} run(s) each, the best CPU time kept (the first run of each process loads the compiled "
        f"kernels and is not timed); {machine_line()}; load average {load_before:.1f} before, "
        f"{load_after:.1f} after (a shared machine: the ratio, measured side by side, is the figure).",
        "",
        "| code | steps | steps per CPU second |",
        "| --- | ---: | ---: |",
        f"| {a.base} ({base_sha}) | {int(b['steps'])} | {rate_b:.0f} |",
        f"| working tree ({head_sha}) | {int(o['steps'])} | {rate_o:.0f} |",
        "",
        f"Ratio (working tree / {a.base}): **{rate_o / rate_b:.3f}**. The two reported "
        + ("**the same numbers at every instant, to the bit** (" if same else "different numbers (")
        + ", ".join(f"`{k}` {v:.3g}" for k, v in diffs.items()) + ": the largest difference of each).",
    ]
    if not a.no_write:
        print("wrote", write_section("bench_track_revisions", "\n".join(md)))
    else:
        print("\n".join(md))


if __name__ == "__main__":
    main()
