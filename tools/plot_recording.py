"""Draw a recording as a person wants to see it: one PNG, time running left to right.

Panels, top to bottom: each link accelerometer (x, y, z in g), the base IMU's accelerometer
(g) and gyro (°/s), the chair's acceleration (when the recording has the true base
attitude: the IMU's reading minus gravity, in the chair's forward / left / up axes), the
compass (µT) and temperature (°C), and the joint angles (°): the truth where the
recording has it, and what the relative encoders say (anchored to the truth's first value,
or to zero). Long recordings are drawn as a band (min to max per pixel column) around the
mean, so that no spike disappears. When ``REC.truth.json`` is beside the recording, the
chair's drives and the arm's reaches are shaded.

    python tools/plot_recording.py REC.csv [--config wmra] [--out REC.png] [--start s] [--end s]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.models.rotations import GRAVITY_MPS2, up_from_tilt  # noqa: E402
from armfusion.models.sensor_models import stream_models  # noqa: E402
from armfusion.sensors.recording import read_recording  # noqa: E402
from armfusion.sensors.samples import Recording  # noqa: E402

COLORS = ("#d62728", "#2ca02c", "#1f77b4", "#9467bd", "#8c564b", "#e377c2", "#17becf")
MAX_POINTS = 2500


def _band(ax, t, y, color, label, lw=0.9):
    """A line (mean per bin) and a band (min-max per bin) when there are many samples."""
    if len(t) <= MAX_POINTS:
        ax.plot(t, y, color=color, lw=lw, label=label)
        return
    edges = np.linspace(t[0], t[-1], MAX_POINTS + 1)
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, MAX_POINTS - 1)
    cnt = np.bincount(idx, minlength=MAX_POINTS)
    ok = cnt > 0
    mean = np.bincount(idx, y, minlength=MAX_POINTS)[ok] / cnt[ok]
    lo = np.full(MAX_POINTS, np.inf)
    hi = np.full(MAX_POINTS, -np.inf)
    np.minimum.at(lo, idx, y)
    np.maximum.at(hi, idx, y)
    tc = 0.5 * (edges[:-1] + edges[1:])[ok]
    ax.fill_between(tc, lo[ok], hi[ok], color=color, alpha=0.25, lw=0)
    ax.plot(tc, mean, color=color, lw=lw, label=label)


def _window(s, t0, t1):
    m = (s.t_s >= t0) & (s.t_s <= t1)
    return s.t_s[m], s.values[m]


def _shade(axes, events, t0, t1):
    for e in events:
        a, b = max(e["t_start_s"], t0), min(e["t_end_s"], t1)
        if b <= a:
            continue
        what = e["what"]
        color = "#ffe9c6" if what.startswith("arm") else "#dcebfa" if (
            "drive" in what or "turn" in what) else None
        if color:
            for ax in axes:
                ax.axvspan(a, b, color=color, zorder=0, lw=0)


def plot_recording(rec: Recording, out: str | Path, arm, truth: dict | None = None,
                   t_start: float | None = None, t_end: float | None = None,
                   title: str | None = None) -> Path:
    """Write the PNG ``out`` for ``rec`` (recorded by ``arm``'s sensors)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = rec.t_start_s if t_start is None else t_start
    t1 = rec.t_end_s if t_end is None else t_end
    sm = stream_models(arm)
    accs = [s.name for s in arm.link_accelerometers if s.name in rec.streams]
    has_imu = "imu_acc" in rec.streams
    has_truth_base = "true_base" in rec.streams
    panels = [("acc", a) for a in accs]
    if has_imu:
        panels += [("imu_acc", None), ("imu_gyro", None)]
        if has_truth_base:
            panels.append(("chair", None))
        if "imu_mag" in rec.streams:
            panels.append(("mag", None))
    panels.append(("joints", None))
    heights = [1.0] * (len(panels) - 1) + [1.6]
    fig, axes = plt.subplots(len(panels), 1, sharex=True, figsize=(12, 1.55 * sum(heights) + 1.2),
                             dpi=100, gridspec_kw={"height_ratios": heights})
    axes = np.atleast_1d(axes)
    xyz = ("x", "y", "z")
    for ax, (kind, name) in zip(axes, panels, strict=True):
        if kind == "acc":
            t, v = _window(rec.streams[name], t0, t1)
            g = sm[name].from_counts(v)
            for c in range(3):
                _band(ax, t, g[:, c], COLORS[c], xyz[c])
            ax.set_ylabel(f"{name} [g]")
        elif kind == "imu_acc":
            t, v = _window(rec.streams["imu_acc"], t0, t1)
            g = sm["imu_acc"].from_counts(v)
            for c in range(3):
                _band(ax, t, g[:, c], COLORS[c], xyz[c])
            ax.set_ylabel("IMU acc [g]")
        elif kind == "imu_gyro":
            t, v = _window(rec.streams["imu_gyro"], t0, t1)
            w = np.degrees(sm["imu_gyro"].from_counts(v))
            for c in range(3):
                _band(ax, t, w[:, c], COLORS[c], xyz[c])
            ax.set_ylabel("gyro [°/s]")
        elif kind == "chair":
            t, v = _window(rec.streams["imu_acc"], t0, t1)
            tb, rpy = _window(rec.streams["true_base"], t0, t1)
            r = np.interp(t, tb, rpy[:, 0])
            p = np.interp(t, tb, rpy[:, 1])
            a = (sm["imu_acc"].from_counts(v) - up_from_tilt(r, p)) * GRAVITY_MPS2
            k = max(1, int(round(0.25 * rec.streams["imu_acc"].rate_hz)))  # 0.25 s average
            kern = np.ones(k) / k
            for c, lab in enumerate(("forward", "left", "up")):
                _band(ax, t, np.convolve(a[:, c], kern, mode="same"), COLORS[c], lab)
            ax.set_ylabel("chair acc\n[m/s²]")
        elif kind == "mag":
            t, v = _window(rec.streams["imu_mag"], t0, t1)
            b = sm["imu_mag"].from_counts(v)
            for c in range(3):
                _band(ax, t, b[:, c], COLORS[c], xyz[c])
            _band(ax, t, np.linalg.norm(b, axis=1), "0.3", "|B|")
            ax.set_ylabel("compass [µT]")
            if "imu_temp" in rec.streams:
                tt, T = _window(rec.streams["imu_temp"], t0, t1)
                ax2 = ax.twinx()
                _band(ax2, tt, sm["imu_temp"].from_counts(T)[:, 0], "#ff7f0e", "temperature", lw=1.2)
                ax2.set_ylabel("°C", color="#ff7f0e")
        else:  # joints
            have_truth = "true_q" in rec.streams
            if have_truth:
                tq, q = _window(rec.streams["true_q"], t0, t1)
                for j in range(q.shape[1]):
                    _band(ax, tq, np.degrees(q[:, j]), COLORS[j % 7], f"q{j + 1}", lw=1.4)
            if "enc" in rec.streams:
                te, c = _window(rec.streams["enc"], t0, t1)
                rel = c / arm.counts_per_rad
                anchor = rec.streams["true_q"].values[0] if have_truth else np.zeros(arm.n_joints)
                for j in range(rel.shape[1]):
                    ax.plot(te[:: max(1, len(te) // MAX_POINTS)],
                            np.degrees(rel[:, j] + anchor[j])[:: max(1, len(te) // MAX_POINTS)],
                            color=COLORS[j % 7], lw=0.8, ls="--",
                            label=None if have_truth else f"enc{j + 1}")
            ax.set_ylabel("joint angle [°]\n(— truth, - - encoders)" if have_truth else "joint angle [°]\n"
                          "(encoders, from 0)")
        ax.grid(True, lw=0.3, alpha=0.6)
        ax.legend(loc="upper right", fontsize=7, ncol=7, framealpha=0.7)
    if truth:
        _shade(axes, truth.get("events", []), t0, t1)
    axes[-1].set_xlabel("time [s]")
    axes[-1].set_xlim(t0, t1)
    if title is None:
        meta = rec.meta or {}
        bits = [str(meta.get("scenario") or (truth or {}).get("scenario") or ""), arm.name,
                f"{t1 - t0:.0f} s"]
        if truth:
            bits.append(f"{len(truth.get('effects', []))} effects")
            bits.append("shaded: chair drives (blue), arm reaches (orange)")
        title = "   ·   ".join(b for b in bits if b)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path, help="REC.csv or REC.mcap")
    ap.add_argument("--config", default="wmra", help="arm config (shipped name or path)")
    ap.add_argument("--out", type=Path, help="PNG to write (default: REC.png)")
    ap.add_argument("--start", type=float, help="first second to draw")
    ap.add_argument("--end", type=float, help="last second to draw")
    a = ap.parse_args(argv)
    rec = read_recording(a.recording)
    tp = a.recording.with_suffix(".truth.json")
    truth = json.loads(tp.read_text()) if tp.exists() else None
    out = plot_recording(rec, a.out or a.recording.with_suffix(".png"), load_arm(a.config), truth,
                         a.start, a.end)
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    main()
