"""The sensor-calibration article (Renk et al., seed 003), reproduced with ``fusion/identification/renk.py``.

    python tools/reproduce_renk.py [--seed 0] [--runs 25] [--img docs/img] [--no-figures]

Prints Markdown (pasted into ``docs/reproduction-output.md``) and draws the article's Figures 3
and 4 as ``docs/img/renk_fig3.png`` and ``renk_fig4.png``.

What the article gives and what is done with it:

* **Simulated experiment** (its Table 2 truth, gravity along -k̂, 6,656 orientations of its
  maneuver, noise N(0, 13.4 / 13.6 / 14.6 mV) and ×10): the article reports it only in
  words and in Figures 3 and 4 (S1 and δ1 against the number of data points), no table.
  We print Table 2 beside our separate (eq. 14) and simultaneous (eq. 15) estimates with
  their σ, the angles between the axes as in its Tables 4 and 6, its stated bounds beside
  our errors, and, over ``--runs`` noise draws, how often those bounds hold and whether
  the errors scatter as the σ say (the estimator's consistency, which the article doubts).
* **Magnetometer**: the article simulates none; its Table 10 estimates serve as the truth
  (as in ``armfusion.fusion.identification.renk.TABLE10``), noise 8.5 / 6.8 / 11.7 mV and ×10, field magnitude 1 G.
* **Tables 3-12** are estimates from the real sensor, whose data we do not have. Two
  things can be checked: the angles between axes recomputed from its Tables 3, 5, 8, 10
  (our reading of eq. 6) against its Tables 4, 6, 9, 11; and its Tables 7 and 12 (the
  spread over 25 offset subsets of the 166,400 samples) against the same procedure on
  data simulated from its own estimates at its noise levels.

The maneuver is the simulator's ``renk-maneuver`` with joints 1, 5, 6 on
``config/crs_a465.yaml`` (the article's Fig. 2 rates; ranges from the config's limits).
Everything is seeded; one run takes about a minute.
"""

from __future__ import annotations

import argparse
import sys
import time
from math import erf, sqrt
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.identification.renk import (  # noqa: E402
    ACCEL_NOISE_V,
    ARTICLE_JOINTS,
    GRAVITY_ARTICLE_MPS2,
    MAG_NOISE_V,
    TABLE2,
    TABLE10,
    TriaxParams,
    angles_between_deg,
    fit_triax,
    simulate_article,
)

# ------------------------------------------------------------------------------------
# the article's numbers, typed in from the text
# ------------------------------------------------------------------------------------
# (table, figure, mode, noise scale, parameter, first n it applies from, bound, the words)
ARTICLE_CLAIMS = [
    ("Fig. 3", "separate", 1.0, "S1", 1000, None, "close to the actual value at about 1,000 data points"),
    ("Fig. 3", "separate", 1.0, "delta1", 2500, 1e-4, "from about 2,500 data points onward within 0.0001 V"),
    ("Fig. 3", "separate", 10.0, "S1", 6656, 2e-4, "last estimate within 0.0002 V·s²/m"),
    ("Fig. 3", "separate", 10.0, "delta1", 6656, 8e-4, "last estimate within 0.0008 V"),
    ("Fig. 4", "simultaneous", 1.0, "S1", 1000, None, "reaches the actual value at about 1,000 data points"),
    ("Fig. 4", "simultaneous", 1.0, "delta1", 6500, 3e-4, "within 0.0003 V at about 6,500 data points"),
    ("Fig. 4", "simultaneous", 10.0, "S1", 6500, 2e-4, "at about 6,500 points within 0.0002 V·s²/m"),
    ("Fig. 4", "simultaneous", 10.0, "delta1", 6500, 1e-3, "at about 6,500 points within 0.0010 V"),
]
# experimental estimates (real sensor): beta, gamma [deg], S, delta [V], phi, psi [deg]
TABLE3 = {"beta_deg": [85.3089, -1.2396, 1.2837], "gamma_deg": [89.8536, 0.89466, 272.1405],
          "S": [0.14259, 0.14251, 0.14197], "delta_v": [2.3757, 2.4491, 2.1096],
          "phi_deg": [89.7507, 89.9933, 89.8723], "psi_deg": [351.3317, 94.3114, 216.0829]}
TABLE4 = {"1 and 2": 91.1503, "1 and 3": 93.4037, "2 and 3": 88.7825}
TABLE5 = {"beta_deg": [85.3089, -1.2394, 1.2829], "gamma_deg": [89.8537, 0.8943, 272.1489],
          "S": [0.14259, 0.14251, 0.14198], "delta_v": [2.3754, 2.4491, 2.1096],
          "phi_deg": 90.0023, "psi_deg": 11.0511}
TABLE6 = {"1 and 2": 91.1501, "1 and 3": 93.4044, "2 and 3": 88.7738}
# Table 7: mean, std over 25 offset subsets (simultaneous accelerometer)
TABLE7 = {"S1": (0.1426, 2.8356e-5), "delta1": (2.3755, 1.8572e-4), "beta1": (85.3442, 0.0170),
          "gamma1": (89.8377, 0.1579), "S2": (0.1425, 4.1989e-5), "delta2": (2.4492, 2.6657e-4),
          "beta2": (-1.2566, 0.0230), "gamma2": (0.8681, 0.0265), "S3": (0.1421, 5.0368e-5),
          "delta3": (2.1093, 2.8925e-4), "beta3": (1.3023, 0.0199), "gamma3": (272.1241, 0.0320),
          "phi": (90.0159, 0.0288), "psi": (134.1036, 88.7530)}
TABLE8 = {"beta_deg": [0.96609, -85.628, -4.0163], "gamma_deg": [270.1986, 185.9308, 1.216],
          "S": [1.3014, 1.329, 1.3342], "delta_v": [2.4216, 2.3965, 2.7643],
          "phi_deg": [59.5327, 59.2785, 59.4192], "psi_deg": [81.4606, 80.7460, 81.3364]}
TABLE9 = {"1 and 2": 90.5314, "1 and 3": 91.0743, "2 and 3": 90.3379}
TABLE11 = {"1 and 2": 90.5314, "1 and 3": 91.0742, "2 and 3": 90.3379}
# Table 12: mean, std over 25 offset subsets (simultaneous magnetometer); the units of
# beta3, gamma3 read "(V)" in the text, degrees meant
TABLE12 = {"S1": (1.3013, 2.7656e-4), "delta1": (2.4217, 1.2231e-4), "beta1": (0.9672, 0.0091),
           "gamma1": (270.2025, 0.0074), "S2": (1.3285, 1.8814e-4), "delta2": (2.3967, 1.3098e-4),
           "beta2": (-85.6327, 0.0082), "gamma2": (185.9310, 0.1691), "S3": (1.3344, 2.3063e-4),
           "delta3": (2.7643, 1.0935e-4), "beta3": (-4.0152, 0.0073), "gamma3": (1.2193, 0.0113),
           "phi": (59.4153, 5.4911e-5), "psi": (81.2401, 2.0431e-4)}

KEYS = ("beta", "gamma", "S", "delta", "phi", "psi")
ANGLE = {"beta", "gamma", "phi", "psi"}
SYM = {"beta": "β", "gamma": "γ", "S": "S", "delta": "δ", "phi": "φ", "psi": "ψ"}


# ------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------
def wrap_deg(d):
    return (np.asarray(d, float) + 180.0) % 360.0 - 180.0


def value(p: TriaxParams, key: str, k: int) -> float:
    """Parameter ``key`` of axis ``k`` in display units (degrees for angles)."""
    v = float(np.broadcast_to(getattr(p, key), (3,))[k])
    return float(np.degrees(v)) if key in ANGLE else v


def error(p: TriaxParams, truth: TriaxParams, key: str, k: int) -> float:
    e = value(p, key, k) - value(truth, key, k)
    return float(wrap_deg(e)) if key in ANGLE else e


def digits(key: str, unit_s: str) -> int:
    return {"beta": 3, "gamma": 3, "phi": 3, "psi": 1, "delta": 5}.get(key, 6 if unit_s == "acc" else 5)


def fmt_vs(v: float, s: float, nd: int) -> str:
    if not np.isfinite(s):
        return f"{v:.{nd}f} (undefined)"
    return f"{v:.{nd}f} ± {s:.{max(nd, 1) if s >= 10 ** -nd else nd + 1}f}"


def p_within(bound: float, sigma: float) -> float:
    """Probability that a N(0, σ) error lies within ±bound."""
    return erf(bound / (sigma * sqrt(2.0)))


def md_table(header: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def canonical_truth(t: dict) -> TriaxParams:
    """A table's parameters as TriaxParams (φ, ψ may be per axis), angles wrapped as the fit prints."""
    def arr(x):
        return np.radians(np.broadcast_to(np.asarray(x, float), (3,)).copy())
    g = np.radians(t["gamma_deg"]) % (2 * np.pi)
    return TriaxParams(np.radians(t["beta_deg"]), g, np.asarray(t["S"], float),
                       np.asarray(t["delta_v"], float),
                       arr(t["phi_deg"]), arr(t["psi_deg"]) % (2 * np.pi))


def estimates_table(truth_name: str, truth: TriaxParams, fits: dict, unit_s: str) -> str:
    """Rows per axis and parameter: truth, then each fit's estimate ± σ and its error in σ."""
    header = ["axis", "parameter", truth_name]
    for mode in fits:
        header += [f"{mode} (ours ± σ)", "error / σ"]
    rows = []
    units = {"beta": "°", "gamma": "°", "phi": "°", "psi": "°", "delta": "V",
             "S": "V·s²/m" if unit_s == "acc" else "V/G"}
    for k in range(3):
        for key in KEYS:
            nd = digits(key, unit_s)
            row = [str(k + 1), f"{SYM[key]}{k + 1 if key not in ('phi', 'psi') else ''} ({units[key]})",
                   f"{value(truth, key, k):.{nd}f}"]
            for f in fits.values():
                if key in ("phi", "psi") and f.mode == "simultaneous" and k > 0:
                    row += ["(same)", ""]
                    continue
                v, s = value(f.params, key, k), value(f.sigma, key, k)
                e = error(f.params, truth, key, k)
                row += [fmt_vs(v, s, nd), f"{e / s:+.2f}" if np.isfinite(s) and s > 0 else "—"]
            rows.append(row)
    return md_table(header, rows)


def angle_sigma(runs: list, truth_angles: dict) -> dict:
    a = np.array([[r.angles_between_deg()[k] for k in truth_angles] for r in runs])
    return dict(zip(truth_angles, a.std(0, ddof=1), strict=True))


def draw_figure(path: Path, title: str, curves: dict, truth: TriaxParams, claims: list):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(2, 2, figsize=(10, 7), dpi=110, sharex=True)
    for col, (scale, c) in enumerate(curves.items()):
        n = c["n"]
        for row, key, unit in ((0, "S", "V·s²/m"), (1, "delta", "V")):
            ax = axs[row, col]
            est, sig = c[key], c[key + "_sigma"]
            t = float(getattr(truth, key)[0])
            ax.fill_between(n, est - sig, est + sig, color="C0", alpha=0.25, lw=0, label="± σ (fit)")
            ax.plot(n, est, "o-", ms=3, color="C0", label="estimate (ours)")
            ax.axhline(t, color="k", lw=1, label="actual (Table 2)")
            for _fig, _mode, sc, par, n0, bound, _words in claims:
                if sc == scale and par == key + "1" and bound is not None:
                    if n0 < n[-1] - 1000:
                        ax.fill_between([n0, n[-1]], t - bound, t + bound, color="C3", alpha=0.15, lw=0,
                                        label=f"article: ±{bound:g} from n = {n0:,}")
                    else:
                        ax.errorbar([n0], [t], yerr=[bound], color="C3", capsize=5, lw=2,
                                    label=f"article: ±{bound:g} at n ≈ {n0:,}")
            ax.set_ylabel(f"{'S₁' if key == 'S' else 'δ₁'} ({unit})")
            ax.set_title(f"{'S₁' if key == 'S' else 'δ₁'}, noise N(0, {0.0134 * scale:.4g} V)", fontsize=10)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
            span = max(4 * float(np.median(sig[len(sig) // 2:])), 1.5 * max(
                [b for _, _, sc, par, _, b, _ in claims if sc == scale and par == key + "1" and b] or [0]))
            ax.set_ylim(t - span, t + span)
            if row == 1:
                ax.set_xlabel("number of data points")
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


# ------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0, help="the seed of the single run shown in the tables")
    ap.add_argument("--runs", type=int, default=25,
                    help="noise draws for the spread (the article used 25 subsets)")
    ap.add_argument("--img", default="docs/img", help="where the figures go")
    ap.add_argument("--no-figures", action="store_true")
    a = ap.parse_args(argv)
    t_start = time.perf_counter()
    arm = load_arm("crs_a465")
    truth = TriaxParams.from_table(TABLE2)
    mag_truth = TriaxParams.from_table(TABLE10)
    acc_noise = np.asarray(ACCEL_NOISE_V)
    mag_noise = np.asarray(MAG_NOISE_V)
    P = print

    # ---------------- setup -------------------------------------------------------
    q, R, _ = simulate_article(arm, truth, acc_noise, 0.0, seed=a.seed)
    a_k = np.einsum("nji,j,nki->nk", R, [0, 0, -1.0], np.broadcast_to(
        np.stack([np.cos(truth.beta) * np.cos(truth.gamma), np.cos(truth.beta) * np.sin(truth.gamma),
                  -np.sin(truth.beta)], 1), (len(R), 3, 3)))
    P("## Setup\n")
    P(f"Arm `config/crs_a465.yaml` (the article's Table 1), maneuver `renk-maneuver` moving "
      f"{', '.join(ARTICLE_JOINTS)}; {len(q):,} orientations (every 25th of 166,400 at 100 Hz), "
      f"seed {a.seed}. Joint ranges covered: " + ", ".join(
          f"{arm.joint_names[i]} {np.degrees(q[:, i].min()):+.0f}° to {np.degrees(q[:, i].max()):+.0f}°"
          for i in (0, 4, 5)) + ".")
    P(f"Gravity component along each Table 2 axis over the maneuver (in g): spread (std) "
      f"{', '.join(f'{s:.3f}' for s in a_k.std(0))} for axes 1, 2, 3; the σ of S_k is about "
      "noise_k / (9.8 · spread_k · √n).\n")

    # ---------------- Table 2: single seeded run at each noise level -------------
    P("## Accelerometer, simulated (Table 2 truth, gravity along -k̂)\n")
    single = {}
    for scale in (0.0, 1.0, 10.0):
        _, R, V = simulate_article(arm, truth, acc_noise, scale, seed=a.seed)
        w = acc_noise * max(scale, 1e-3)
        fits = {m: fit_triax(R, V, m, w) for m in ("separate", "simultaneous")}
        single[scale] = fits
        mv = ", ".join(f"{x * scale * 1e3:.1f}" for x in acc_noise)
        label = "no noise" if scale == 0 else f"noise ×{scale:g}: N(0, {mv} mV)"
        P(f"### {label}\n")
        P(estimates_table("Table 2 (actual)", truth, fits, "acc"))
        P("\nFit RMS per axis (V): " + "; ".join(
            f"{m} " + ", ".join(f"{r:.4f}" for r in f.rms_v) for m, f in fits.items()))
        und = sorted({u for f in fits.values() for u in f.undefined})
        if und:
            P("Reported undefined: " + ", ".join(und) + ". " + next(
                (msg for f in fits.values() for msg in f.messages if msg.startswith("psi")), ""))
        P()

    # ---------------- many noise draws --------------------------------------------
    t_mc = time.perf_counter()
    runs = {(sc, m): [] for sc in (1.0, 10.0) for m in ("separate", "simultaneous")}
    for r in range(a.runs):
        for sc in (1.0, 10.0):
            _, R, V = simulate_article(arm, truth, acc_noise, sc, seed=1000 + r)
            for m in ("separate", "simultaneous"):
                runs[(sc, m)].append(fit_triax(R, V, m, acc_noise * sc))
    t_mc = time.perf_counter() - t_mc

    truth_angles = angles_between_deg(truth.beta, truth.gamma)
    P("### Angles between the accelerometers (the article's Tables 4 and 6)\n")
    P(f"Ours: seed {a.seed}; σ is the spread over {a.runs} noise draws (seeds 1000-{999 + a.runs}).\n")
    header = ["axes", "Table 2 (actual)"]
    for sc in (1.0, 10.0):
        header += [f"separate ×{sc:g}", f"simultaneous ×{sc:g}"]
    rows = []
    for pair in truth_angles:
        row = [pair, f"{truth_angles[pair]:.4f}"]
        for sc in (1.0, 10.0):
            for m in ("separate", "simultaneous"):
                s = angle_sigma(runs[(sc, m)], truth_angles)[pair]
                row.append(f"{single[sc][m].angles_between_deg()[pair]:.4f} ± {s:.4f}")
        rows.append(row)
    P(md_table(header, rows))
    P()

    P("### The article's statements on Figures 3 and 4 against ours\n")
    P(f"Ours: the seeded run (seed {a.seed}) at n = 6,656, and over {a.runs} draws how often the "
      "article's bound holds, beside the chance a N(0, σ) error has of it (σ: the fit's).\n")
    rows = []
    for fig_name, mode, sc, par, _n0, bound, words in ARTICLE_CLAIMS:
        key, k = par[:-1], int(par[-1]) - 1
        f = single[sc][mode]
        e = error(f.params, truth, key, k)
        s = value(f.sigma, key, k)
        errs = np.array([error(x.params, truth, key, k) for x in runs[(sc, mode)]])
        if bound is None:
            rows.append([fig_name, mode, f"×{sc:g}", par.replace("delta", "δ"), words,
                         f"{e:+.2e} ({e / s:+.1f}σ)", "—", "—"])
            continue
        rows.append([fig_name, mode, f"×{sc:g}", par.replace("delta", "δ"), words,
                     f"{e:+.2e} ({e / s:+.1f}σ) {'✓' if abs(e) <= bound else '✗'}",
                     f"{np.mean(np.abs(errs) <= bound):.0%}", f"{p_within(bound, s):.0%}"])
    P(md_table(["figure", "fit", "noise", "param", "article", f"ours, seed {a.seed}",
                f"within, {a.runs} draws", "expected"], rows))
    P()
    P("The same bounds at ×10 for all three axes (the article states them for axis 1 only):\n")
    rows = []
    for mode, (bS, bd) in (("separate", (2e-4, 8e-4)), ("simultaneous", (2e-4, 1e-3))):
        for k in range(3):
            f = single[10.0][mode]
            row = [mode, str(k + 1)]
            for key, b in (("S", bS), ("delta", bd)):
                e, s = error(f.params, truth, key, k), value(f.sigma, key, k)
                errs = np.array([error(x.params, truth, key, k) for x in runs[(10.0, mode)]])
                row += [f"{e:+.2e} ({e / s:+.1f}σ)", f"{s:.2e}",
                        f"{np.mean(np.abs(errs) <= b):.0%} / {p_within(b, s):.0%}"]
            rows.append(row)
    P(md_table(["fit", "axis", "S error", "σ(S)", "S within 0.0002: draws / expected",
                "δ error", "σ(δ)", "δ within bound: draws / expected"], rows))
    P()

    P(f"### Consistency: {a.runs} noise draws\n")
    P("Mean error in units of its standard error (σ_spread / √runs: |z| < 2.5 for an unbiased "
      "estimator) and the spread of the estimates over the fit's mean σ (1 if the σ are honest).\n")
    rows = []
    for (sc, m), rr in runs.items():
        for k in range(3):
            row = [m, f"×{sc:g}", str(k + 1)]
            for key in ("S", "delta", "beta", "gamma"):
                e = np.array([error(x.params, truth, key, k) for x in rr])
                s = np.array([value(x.sigma, key, k) for x in rr])
                sd = e.std(ddof=1)
                ratio = f"{sd / np.nanmean(s):.2f}" if np.isfinite(s).any() else "undef."
                row.append(f"{e.mean() / (sd / np.sqrt(len(e))):+.1f} / {ratio}")
            rows.append(row)
    P(md_table(["fit", "noise", "axis", "S: bias z / spread÷σ", "δ", "β", "γ"], rows))
    P()

    # ---------------- Figures 3 and 4 ---------------------------------------------
    ns = np.arange(256, 6657, 256)
    curves = {m: {} for m in ("separate", "simultaneous")}
    t_fig = time.perf_counter()
    for sc in (1.0, 10.0):
        _, R, V = simulate_article(arm, truth, acc_noise, sc, seed=a.seed)
        for m in curves:
            c = {"n": ns, "S": [], "S_sigma": [], "delta": [], "delta_sigma": []}
            for n in ns:
                f = fit_triax(R[:n], V[:n], m, acc_noise * sc)
                c["S"].append(f.params.S[0])
                c["S_sigma"].append(f.sigma.S[0])
                c["delta"].append(f.params.delta[0])
                c["delta_sigma"].append(f.sigma.delta[0])
            curves[m][sc] = {k: np.asarray(v) for k, v in c.items()}
    t_fig = time.perf_counter() - t_fig
    P("### Figures 3 and 4: S₁ and δ₁ against the number of data points\n")
    P(f"The first n of the 6,656 orientations (in time order), seed {a.seed}; the band is the fit's ±σ, "
      "in red the article's stated bound where it states it. The ×10 curves use the same noise draw "
      "scaled by ten: their errors are ten times the ×1 errors (the estimator is linear at this noise).\n")
    for fig_no, m in ((3, "separate"), (4, "simultaneous")):
        if not a.no_figures:
            draw_figure(Path(a.img) / f"renk_fig{fig_no}.png",
                        f"Fig. {fig_no} reproduced: {m} accelerometer calibration, accelerometer 1",
                        curves[m], truth, [c for c in ARTICLE_CLAIMS if c[1] == m])
            P(f"![Figure {fig_no}, {m}](img/renk_fig{fig_no}.png)\n")
        rows = []
        for sc in (1.0, 10.0):
            c = curves[m][sc]
            for n in (1024, 2560, 4096, 6656):
                i = int(np.searchsorted(ns, n))
                rows.append([f"×{sc:g}", f"{ns[i]:,}",
                             f"{c['S'][i] - truth.S[0]:+.2e} ± {c['S_sigma'][i]:.1e}",
                             f"{c['delta'][i] - truth.delta[0]:+.2e} ± {c['delta_sigma'][i]:.1e}"])
        P(md_table(["noise", "n", "S₁ error ± σ", "δ₁ error ± σ"], rows))
        P()

    # ---------------- magnetometer ------------------------------------------------
    P("## Magnetometer, simulated (Table 10 estimates as the truth, 1 G field)\n")
    mag_single = {}
    for scale in (1.0, 10.0):
        _, R, V = simulate_article(arm, mag_truth, mag_noise, scale, magnitude=1.0, seed=a.seed)
        fits = {m: fit_triax(R, V, m, mag_noise * scale, magnitude=1.0) for m in ("separate", "simultaneous")}
        mag_single[scale] = fits
        P(f"### noise ×{scale:g}: N(0, {', '.join(f'{x * scale * 1e3:.1f}' for x in mag_noise)} mV)\n")
        P(estimates_table("Table 10 (actual)", mag_truth, fits, "mag"))
        P("\nFit RMS per axis (V): " + "; ".join(
            f"{m} " + ", ".join(f"{r:.4f}" for r in f.rms_v) for m, f in fits.items()))
        und = sorted({u for f in fits.values() for u in f.undefined})
        P(("Reported undefined: " + ", ".join(und)) if und else "Nothing reported undefined.")
        P()
    mag_angles = angles_between_deg(mag_truth.beta, mag_truth.gamma)
    P("### Angles between the magnetometers (the article's Tables 9 and 11)\n")
    rows = []
    for pair in mag_angles:
        row = [pair, f"{mag_angles[pair]:.4f}"]
        for sc in (1.0, 10.0):
            for m in ("separate", "simultaneous"):
                row.append(f"{mag_single[sc][m].angles_between_deg()[pair]:.4f}")
        rows.append(row)
    P(md_table(["axes", "from Table 10 (actual)", "separate ×1", "simultaneous ×1", "separate ×10",
                "simultaneous ×10"], rows))
    P()
    P("Field direction, simultaneous fit, error ± σ: " + "; ".join(
        f"×{sc:g}: φ {error(f.params, mag_truth, 'phi', 0):+.4f}° ± {value(f.sigma, 'phi', 0):.4f}°, "
        f"ψ {error(f.params, mag_truth, 'psi', 0):+.4f}° ± {value(f.sigma, 'psi', 0):.4f}°"
        for sc, f in ((sc, mag_single[sc]['simultaneous']) for sc in (1.0, 10.0))) + ".\n")

    # ---------------- the article's experimental tables ---------------------------
    P("## The article's experimental tables (real sensor)\n")
    P("Their estimates come from data we do not have. Checked: the angles between axes, "
      "recomputed by our eq. 6 from its own β, γ, against its printed angles.\n")
    rows = []
    for src, t, dst, angles in (("Table 3", TABLE3, "Table 4", TABLE4),
                                ("Table 5", TABLE5, "Table 6", TABLE6),
                                ("Table 8", TABLE8, "Table 9", TABLE9),
                                ("Table 10", TABLE10, "Table 11", TABLE11)):
        ours = angles_between_deg(np.radians(t["beta_deg"]), np.radians(t["gamma_deg"]))
        for pair in angles:
            rows.append([f"{src} → {dst}", pair, f"{angles[pair]:.4f}", f"{ours[pair]:.4f}",
                         f"{ours[pair] - angles[pair]:+.4f}"])
    P(md_table(["from", "axes", "article", "ours from its β, γ", "difference (°)"], rows))
    P()

    t_sub = time.perf_counter()
    P("### Tables 7 and 12: 25 offset subsets\n")
    P("The article's procedure on simulated data: 166,400 samples with white noise at its levels "
      "(×1), truth = its Table 5 (accelerometer) / Table 10 (magnetometer), every 25th sample "
      "from offsets 0-24, simultaneous fit of each. Our mean ± std over the 25 beside its Table 7 / 12.\n")
    for name, tab_truth, table, noise, mag in (
            ("Accelerometer (Table 7)", TABLE5, TABLE7, acc_noise, GRAVITY_ARTICLE_MPS2),
            ("Magnetometer (Table 12)", TABLE10, TABLE12, mag_noise, 1.0)):
        tr = TriaxParams.from_table(tab_truth)
        _, Rall, Vall = simulate_article(arm, tr, noise, 1.0, magnitude=mag, seed=a.seed, every=1)
        subs = [fit_triax(Rall[o::25], Vall[o::25], "simultaneous", noise, magnitude=mag) for o in range(25)]
        rows = []
        for par, (mean, sd) in table.items():
            key = par.rstrip("123")
            k = int(par[-1]) - 1 if par[-1].isdigit() else 0
            est = np.array([value(s.params, key, k) for s in subs])
            d = value(tr, key, k) - mean  # its single estimate against its subsets' mean
            if key in ANGLE:
                est = value(tr, key, k) + wrap_deg(est - value(tr, key, k))
            sig = np.array([value(s.sigma, key, k) for s in subs])
            nd = 4 if key != "S" else 5
            defined = np.isfinite(sig).any()
            fsd = f"{np.nanmean(sig):.2e}" if defined else "undefined"
            rows.append([par.replace("delta", "δ").replace("beta", "β").replace("gamma", "γ")
                         .replace("phi", "φ").replace("psi", "ψ"),
                         f"{value(tr, key, k):.{nd}f}", f"{mean} ± {sd:.2e}",
                         f"{est.mean():.{nd}f} ± {est.std(ddof=1):.2e}", fsd,
                         f"{sd / est.std(ddof=1):.2f}" if defined else "—",
                         f"{(wrap_deg(d) if key in ANGLE else d) / sd:+.1f}"])
        P(f"**{name}**\n")
        P(md_table(["param", "truth (its estimate)", "article: mean ± std", "ours: mean ± std",
                    "ours: fit σ", "article std ÷ ours", "its Table 5/10 − its mean, in its std"], rows))
        P()
        if mag == 1.0:
            sp = {key: np.std([value(s.params, key, 0) for s in subs], ddof=1) for key in ("phi", "psi")}
            P("Read as radians, Table 12's std of φ and ψ are " + ", ".join(
                f"{np.degrees(table[key][1]):.4f}° ({np.degrees(table[key][1]) / sp[key]:.2f}× ours)"
                for key in ("phi", "psi")) + ".\n")
    t_sub = time.perf_counter() - t_sub

    total = time.perf_counter() - t_start
    P(f"Runtime: {total:.0f} s in all ({t_mc:.0f} s for the {a.runs} draws, {t_fig:.0f} s for the "
      f"figures' {4 * len(ns)} fits, {t_sub:.0f} s for the 50 subset fits).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
