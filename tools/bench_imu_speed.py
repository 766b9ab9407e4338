"""IMU-only tracking speed at two revisions of the code, side by side, and sameness.

A BROAD trial (``--trial``, a hand-held 9-axis IMU; see ``tools/bench_heading_broad.py``)
imported with the shipped map onto the IMU-only config ``broad_imu`` and tracked after its
startup, exactly as ``armfusion import`` then ``armfusion track --config broad_imu`` do
(``Tracker.run``, everything included), with the code of the working tree and with the code
of another git revision (``--base``; checked out into a temporary worktree, removed
afterwards), each in its own process, alternately (``--repeats`` times each; the best CPU
time of each kept). Also the WMRA's simulated ``daily-use`` drive
(``tools/bench_track_revisions.py``'s run), so a speed-up of the IMU-only path is seen not to
cost the arm's tracker. For each: tracked instants per CPU second (``time.process_time``),
the ratio, and the largest difference of what the two revisions reported at every instant.

    python tools/bench_imu_speed.py [--base feacb19] [--trial 01_] [--seconds 60] [--repeats 1]
                                    [--wmra-duration 60] [--no-write]

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
DEFAULT_DATA = HERE.parent / "shared" / "data" / "broad"
CONFIG = "broad_imu"
FIELDS = ("rpy_rad", "rpy_sigma_rad", "gyro_bias_rad_s", "sensor_status", "flags")
TARGET_STEPS_PER_CPU_S = 10_000.0
"""The IMU-only tracker's speed target: a whole BROAD trial (about 50,000 instants) in about
5 CPU seconds, where a 9-axis peer filter (vqf) takes well under one."""
WARM_S = 2.0
"""Seconds tracked once before the timed run, in the same process (loads the compiled kernels)."""


def stage(root: str) -> str:
    """The code under ``root`` put first on the import path, laid out as installed
    (``armfusion.fusion`` etc. from its folders); the import prefix of its layers."""
    import importlib

    sys.path.insert(0, root)  # (its tools/)
    if (Path(root) / "armfusion" / "__init__.py").exists():
        staged = Path(tempfile.mkdtemp(prefix="armfusion-rev-")) / "armfusion"
        staged.mkdir()
        (staged / "__init__.py").symlink_to(Path(root) / "armfusion" / "__init__.py")
        for layer in ("fusion", "models", "sensors", "config"):
            (staged / layer).symlink_to(Path(root) / layer, target_is_directory=True)
        sys.path.insert(0, str(staged.parent))
        prefix = "armfusion."
    else:  # a revision whose layers were top-level packages
        prefix = ""
    layer = importlib.import_module(prefix + "fusion")
    if not str(Path(layer.__file__).resolve()).startswith(str(Path(root).resolve())):
        raise SystemExit(f"the code under {root} was not the one imported ({layer.__file__})")
    return prefix


def child_broad(root: str, out: str, trial: str, seconds: float) -> None:
    """In a process of its own: the code under ``root`` on the trial, a short run first
    (loads the compiled kernels), then the timed one; its per-instant outputs to ``out``."""
    import importlib

    prefix = stage(root)
    load_arm = importlib.import_module(prefix + "fusion.configfile").load_arm
    load_column_map = importlib.import_module(prefix + "fusion.importing.column_map").load_column_map
    import_recording = importlib.import_module(prefix + "fusion.importing.run").import_recording
    start_from_recording = importlib.import_module(prefix + "fusion.tracking.tracker").start_from_recording

    arm = load_arm(CONFIG)
    rec = import_recording(Path(trial), load_column_map("broad"), arm, CONFIG).recording
    tr, _start = start_from_recording(arm, rec)
    tr.run(rec, tr.t_s + WARM_S)
    tr, _start = start_from_recording(arm, rec)
    c0 = time.process_time()
    run = tr.run(rec, None if seconds <= 0 else tr.t_s + seconds)
    cpu = time.process_time() - c0
    arrays = {k: np.asarray(getattr(run, k), dtype=float) for k in FIELDS}
    np.savez(out, cpu_s=cpu, steps=run.steps, **arrays)


def run_child(kind: str, root: Path, out: Path, a) -> dict:
    if kind == "broad":
        args = ["--child-broad", str(root), str(out), str(a.trial_path), str(a.seconds)]
    else:
        args = ["--child-wmra", str(root), str(out), str(a.wmra_duration), str(a.seed)]
    subprocess.run([sys.executable, str(Path(__file__).resolve()), *args], check=True, cwd=root)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def largest_differences(b: dict, o: dict, fields: tuple[str, ...]) -> dict[str, float]:
    """Per output, the largest absolute difference (inf: shapes or NaNs differ)."""
    diffs = {}
    for k in fields:
        x, y = b[k], o[k]
        diffs[k] = (float("inf") if x.shape != y.shape else
                    float(np.nanmax(np.abs(x - y), initial=0.0)) if np.array_equal(np.isnan(x), np.isnan(y))
                    else float("inf"))
    return diffs


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=HERE, check=True, capture_output=True, text=True).stdout.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="feacb19", help="the git revision to compare against")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the folder of BROAD trials")
    ap.add_argument("--trial", default="01_", help="the trial: the start of its file name in --data")
    ap.add_argument("--seconds", type=float, default=60.0,
                    help="seconds tracked after the startup (0: the whole trial)")
    ap.add_argument("--wmra-duration", type=float, default=60.0,
                    help="the WMRA daily-use recording's length, s (0: not run)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=1, help="runs of each revision, alternating (best kept)")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--child-broad", nargs=4, help=argparse.SUPPRESS)
    ap.add_argument("--child-wmra", nargs=4, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child_broad:
        root, out, trial, seconds = a.child_broad
        child_broad(root, out, trial, float(seconds))
        return
    if a.child_wmra:
        root, out, duration, seed = a.child_wmra
        sys.path.insert(0, str(HERE))
        from tools.bench_track_revisions import child

        child(root, out, float(duration), int(seed))
        return
    if a.repeats < 1:
        raise SystemExit(f"--repeats must be at least 1, got {a.repeats}")
    matches = sorted(Path(a.data).glob(f"{a.trial}*.hdf5"))
    if len(matches) != 1:
        raise SystemExit(f"--trial {a.trial!r}: {len(matches)} files in {a.data} start so (one wanted)")
    a.trial_path = matches[0].resolve()
    base_sha, head_sha = git("rev-parse", "--short", a.base), git("rev-parse", "--short", "HEAD")
    dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    kinds = ("broad", "wmra") if a.wmra_duration > 0 else ("broad",)
    best: dict = {(k, w): None for k in kinds for w in ("base", "ours")}
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "base"
        subprocess.run(["git", "worktree", "add", "--detach", "--quiet", str(tree), a.base], cwd=HERE,
                       check=True)
        try:
            load_before = os.getloadavg()[0]
            for rep in range(a.repeats):
                for kind in kinds:
                    for who, root in (("base", tree), ("ours", HERE)):
                        r = run_child(kind, root, Path(tmp) / f"{kind}-{who}.npz", a)
                        if best[kind, who] is None or r["cpu_s"] < best[kind, who]["cpu_s"]:
                            best[kind, who] = r
                        print(f"[{rep + 1}/{a.repeats}] {kind} {who}: {int(r['steps'])} steps, "
                              f"{float(r['steps'] / r['cpu_s']):.0f} per CPU second", flush=True)
            load_after = os.getloadavg()[0]
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=HERE, check=False)
    rows, notes = [], []
    ratios = {}
    for kind in kinds:
        b, o = best[kind, "base"], best[kind, "ours"]
        rate_b, rate_o = float(b["steps"] / b["cpu_s"]), float(o["steps"] / o["cpu_s"])
        ratios[kind] = rate_o / rate_b
        if kind == "broad":
            rate_broad = rate_o
        fields = FIELDS if kind == "broad" else tuple(k for k in b if k not in ("cpu_s", "steps"))
        diffs = largest_differences(b, o, fields)
        same = all(v == 0.0 for v in diffs.values())
        label = (f"BROAD `{a.trial_path.stem}`, IMU-only (`{CONFIG}`)" if kind == "broad"
                 else f"WMRA simulated `daily-use`, {a.wmra_duration:.0f} s (seed {a.seed})")
        rows.append(f"| {label} | {int(b['steps'])} | {rate_b:.0f} | {rate_o:.0f} | **{ratios[kind]:.2f}** |")
        notes.append(f"- {label}: " + ("**the same numbers at every instant, to the bit**" if same else
                                       "different numbers") + " (largest difference: "
                     + ", ".join(f"`{k}` {v:.3g}" for k, v in diffs.items()) + ").")
        print(f"{kind}: steps per CPU second {a.base} ({base_sha}) {rate_b:.0f}, this tree {rate_o:.0f}: "
              f"ratio {ratios[kind]:.3f}; largest differences {json.dumps(diffs)}")
    sys.path.insert(0, str(HERE))
    from tools.benchdoc import machine_line, write_section

    span = "the whole trial" if a.seconds <= 0 else f"its first {a.seconds:.0f} s"
    md = [
        "## IMU-only tracking speed at two revisions (`tools/bench_imu_speed.py`)",
        "",
        f"`Tracker.run` (everything included) after the startup, over {span} for the BROAD trial; "
        f"{a.base} ({base_sha}) against the working tree ({head_sha}{', with changes' if dirty else ''}), "
        f"each in its own process, alternately, {a.repeats} run(s) each, the best CPU time kept (each "
        f"process first tracks {WARM_S:.0f} s untimed, which loads the compiled kernels); {machine_line()}; "
        f"load average {load_before:.1f} before, {load_after:.1f} after (a shared machine: the ratio, "
        "measured side by side, is the figure).",
        "",
        f"| recording | steps | {a.base} steps per CPU s | working tree steps per CPU s | ratio |",
        "| --- | ---: | ---: | ---: | ---: |",
        *rows,
        "",
        *notes,
        "",
        f"IMU-only target: at least {TARGET_STEPS_PER_CPU_S:,.0f} steps per CPU second: "
        + ("**met**" if rate_broad >= TARGET_STEPS_PER_CPU_S else
           f"**not met** ({rate_broad:,.0f}, {rate_broad / TARGET_STEPS_PER_CPU_S:.2f} of it, on this load)"),
    ]
    if not a.no_write:
        print("wrote", write_section("bench_imu_speed", "\n".join(md)))
    else:
        print("\n".join(md))


if __name__ == "__main__":
    main()
