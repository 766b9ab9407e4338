"""Draw the tracker's figure for docs/tracking.md: a simulated WMRA driving and reaching,
tracked from its first still stretch; per joint the size of the error against the truth
beside three of its reported sigmas (log scale), shaded where the joint was flagged
``gimbal_lock`` (held: its sigma grows until gravity reads it again), and the heading's
error beside its 3σ.

    python tools/figure_tracking.py [--config wmra] [--seed 1] [--duration 120]
        [--joints j3,j6] [--out docs/img/tracking_gimbal.png]

Every value drawn is the tracker's own output (``TrackRun``), on the simulator's recording
with its truth; nothing is fitted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.tracking.settings import JOINT_FLAGS  # noqa: E402
from armfusion.fusion.tracking.tracker import start_from_recording  # noqa: E402
from armfusion.models.simulator import simulate  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="wmra")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=120.0, help="simulated seconds")
    ap.add_argument("--joints", default="j3,j6", help="joints to draw (comma-separated)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "tracking_gimbal.png")
    args = ap.parse_args(argv)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arm = load_arm(args.config)
    rec, _truth = simulate(arm, "daily-use", duration_s=args.duration, seed=args.seed)
    tracker, _start = start_from_recording(arm, rec)
    run = tracker.run(rec)
    if run.q_error_rad is None:
        raise SystemExit("the simulated recording carries no truth to draw errors against")
    names = [n.strip() for n in args.joints.split(",") if n.strip()]
    unknown = [n for n in names if n not in run.joint_names]
    if unknown:
        raise SystemExit(f"--joints: {unknown} not in the config's joints {list(run.joint_names)}")
    locked = JOINT_FLAGS.index("gimbal_lock")
    t = run.t_s - run.t_s[0]

    fig, axes = plt.subplots(len(names) + 1, 1, figsize=(9, 2.3 * (len(names) + 1)), sharex=True)
    floor = 1e-4  # deg: the log axis's bottom, below any error the tracker reports

    def draw(ax, err_deg, sigma_deg, held=None):
        if held is not None and held.any():
            ax.fill_between(t, 0, 1, where=held, color="0.85", lw=0, zorder=0,
                            transform=ax.get_xaxis_transform(), label="flagged gimbal_lock (held)")
        ax.semilogy(t, np.maximum(np.abs(err_deg), floor), color="#d62728", lw=0.7,
                    label="|error| against the truth")
        ax.semilogy(t, np.maximum(3 * sigma_deg, floor), color="#1f77b4", lw=1.0, label="3σ reported")
        ax.set_ylim(bottom=floor)
        ax.legend(loc="upper right", fontsize=7, ncol=3)

    for ax, name in zip(axes[:-1], names, strict=True):
        j = run.joint_names.index(name)
        draw(ax, np.degrees(run.q_error_rad[:, j]), np.degrees(run.sigma_rad[:, j]),
             run.flags[:, j] == locked)
        ax.set_ylabel(f"{name} [deg]")
    ax = axes[-1]
    if run.yaw_error_rad is not None:
        draw(ax, np.degrees(run.yaw_error_rad), np.degrees(run.rpy_sigma_rad[:, 2]))
    ax.set_ylabel("heading [deg]")
    ax.set_xlabel("time since the tracker started [s]")
    fig.suptitle(f"{args.config}, simulated daily use (seed {args.seed}), tracked from its first "
                 "still stretch", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
