"""Drawing the arm and its sensors (matplotlib, no screen needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.kinematics import chain_poses, joint_axis_angle_to_vertical, sensor_poses


def _mpl():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_arm(arm: ArmModel, q_rad: np.ndarray, path: str | Path, title: str | None = None) -> Path:
    """A 3-D drawing of the arm at ``q_rad``: links, joint axes (red where vertical: gravity
    cannot read that joint), every sensor with its x/y/z axes. Written as PNG to ``path``."""
    plt = _mpl()
    q = np.asarray(q_rad, dtype=float).reshape(1, -1)
    poses = chain_poses(arm, q)
    p = poses.p_0L_m[0]
    vertical_deg = np.degrees(joint_axis_angle_to_vertical(arm, q))[0]
    fig = plt.figure(figsize=(8, 6.5), dpi=110)
    ax = fig.add_subplot(projection="3d")
    # the base: a plate under frame 0
    ax.plot(*np.array([[-0.1, -0.1, 0], [0.1, -0.1, 0], [0.1, 0.1, 0], [-0.1, 0.1, 0],
                       [-0.1, -0.1, 0]]).T, color="0.5", lw=1)
    ax.plot(p[:, 0], p[:, 1], p[:, 2], "-", color="0.25", lw=5, solid_capstyle="round",
            label="links")
    L = 0.09
    for j in range(arm.n_joints):
        o, a = poses.origin_0_m[0, j], poses.axis_0[0, j]
        locked = vertical_deg[j] < 2.0
        c = "tab:red" if locked else "tab:blue"
        ax.plot(*np.stack([o - L * a, o + L * a]).T, color=c, lw=2)
        ax.text(*(o + 1.25 * L * a), f"{arm.joints[j].name}" + (" (vertical)" if locked else ""),
                color=c, fontsize=8)
    names = list(arm.sensor_names)
    R_0S, p_0S = sensor_poses(arm, q, names)
    colors = ["tab:red", "tab:green", "tab:blue"]
    for s, name in enumerate(names):
        o = p_0S[0, s]
        ax.scatter(*o, s=60, color="tab:orange", edgecolor="k", zorder=5)
        for k in range(3):
            ax.plot(*np.stack([o, o + 0.06 * R_0S[0, s, :, k]]).T, color=colors[k], lw=1.5)
        ax.text(*(o + np.array([0.02, 0.02, 0.03])), f"{name} ({arm.sensor(name).type})",
                fontsize=8)
    allp = np.concatenate([p, p_0S[0]])
    c = allp.mean(axis=0)
    r = max(np.ptp(allp, axis=0).max() / 2, 0.2) * 1.1
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(min(c[2] - r, -0.05), c[2] + r)
    ax.set_xlabel("x [m] (forward)")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m] (up)")
    deg = ", ".join(f"{v:.0f}" for v in np.degrees(q[0]))
    ax.set_title(title or f"{arm.name} at q = [{deg}] deg\n"
                 "sensor axes x/y/z = red/green/blue; red joint axis = vertical (gravity-blind)",
                 fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from armfusion.sensors.output_files import replaced_when_done

    with replaced_when_done(path) as tmp:  # (the format from the real name's suffix)
        fig.savefig(tmp, format=path.suffix.lstrip(".").lower() or None)
    plt.close(fig)
    return path
