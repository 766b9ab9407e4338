"""Forward kinematics and gravity Jacobians of 100,000 WMRA poses, against a per-pose baseline.

The baseline is what one writes first: one 4x4 DH product per joint per pose, in a Python
loop (it is timed on a subset and scaled, so the run stays short). Writes its section of
docs/benchmarks.md.

    python tools/bench_kinematics.py [--poses 100000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.models.arm import dh_transform  # noqa: E402
from armfusion.models.kinematics import chain_poses, gravity_in_sensors, gravity_jacobian  # noqa: E402

from tools.benchdoc import machine_line, write_section  # noqa: E402


def best_of(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def baseline_fk(arm, q: np.ndarray) -> np.ndarray:
    dh = arm.dh
    out = np.empty((len(q), 4, 4))
    for k in range(len(q)):
        T = np.eye(4)
        for i in range(arm.n_joints):
            T = T @ dh_transform(dh.convention, dh.alpha_rad[i], dh.a_m[i], dh.d_m[i],
                                 q[k, i] + dh.offset_rad[i])
        out[k] = T
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=100_000)
    ap.add_argument("--baseline-poses", type=int, default=2_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    arm = load_arm("wmra")
    rng = np.random.default_rng(1)
    q = rng.uniform(arm.min_rad, arm.max_rad, size=(a.poses, arm.n_joints))
    # the compiled kernels (armfusion.models.chain_kernels) load from numba's cache on their first call,
    # once per process (about 0.5 s): done before the clock starts, as for every best-of
    gravity_jacobian(arm, q[:2])
    t_fk = best_of(lambda: chain_poses(arm, q), a.repeats)
    t_g = best_of(lambda: gravity_in_sensors(arm, q), a.repeats)
    t_j = best_of(lambda: gravity_jacobian(arm, q), a.repeats)
    qb = q[: a.baseline_poses]
    t_base = best_of(lambda: baseline_fk(arm, qb), 1) * (a.poses / a.baseline_poses)
    # same answer, or the timing means nothing
    ref = baseline_fk(arm, qb[:50])
    ours = chain_poses(arm, qb[:50])
    assert np.allclose(ours.R_0L[:, -1], ref[:, :3, :3]) and np.allclose(ours.p_0L_m[:, -1], ref[:, :3, 3])
    rows = [
        ("forward kinematics, every link frame", t_fk),
        ("static reading of the 4 accelerometers", t_g),
        ("... with its analytic Jacobian (4 x 3 x 7 per pose)", t_j),
    ]
    lines = [
        "## Kinematics (`tools/bench_kinematics.py`)",
        "",
        f"WMRA, {a.poses:,} random poses inside the joint limits, best of {a.repeats} (the compiled "
        f"kernels loaded first, once per process); "
        f"{machine_line()}.",
        "",
        "| what | time for all poses | per pose |",
        "| --- | ---: | ---: |",
    ]
    for name, t in rows:
        lines.append(f"| {name} | {t * 1e3:.0f} ms | {t / a.poses * 1e9:.0f} ns |")
    lines += [
        f"| baseline: per-pose loop of 4x4 DH products (timed on {a.baseline_poses:,}, scaled) "
        f"| {t_base * 1e3:.0f} ms | {t_base / a.poses * 1e9:.0f} ns |",
        "",
        f"Batched forward kinematics is **{t_base / t_fk:.0f}x** faster than the per-pose loop "
        f"and takes {t_fk:.2f} s for {a.poses:,} poses (target: well under 1 s).",
    ]
    md = "\n".join(lines)
    print(md)
    if not a.no_write:
        print(f"\nwritten to {write_section('bench_kinematics', md)}")


if __name__ == "__main__":
    main()
