"""The planned self-calibration maneuver against ``renk-maneuver``: the identification and
the startup after each, on several realistic arms. Writes its section of docs/benchmarks.md
(``--out FILE``: to that file instead; ``--quick``: neither unless ``--out``).

    python tools/bench_maneuver.py [--seeds 10] [--duration 60] [--renk-duration 300]
        [--poses 200] [--dwells 1,1.5,2,3] [--jobs 1] [--out FILE]
        [--figure docs/img/maneuver_sigma.png] [--quick]

1. ``armfusion plan-maneuver --config wmra --duration D`` (the same functions), once: the plan
   does not depend on the arm's true errors, only on the config's priors;
2. per seed S: seed S's realistic arm (every effect drawn at datasheet-typical magnitudes)
   plays the plan (the chair parked at seed S's tilt) and ``renk-maneuver`` for
   ``--renk-duration`` s; ``calibrate sensors --effects all`` on each (``tools/bench_calibrated``'s
   ``calibrate``); each estimate against the truth in σ; the predicted σ against the fitted;
3. the startup on ``--poses`` random still poses of the same physical sensors at 25 °C on
   each calibrated config (``tools/bench_calibrated``'s ``still_means`` and ``solve_poses``):
   per joint the RMS error and the median σ of the ok answers.

Targets: ≥ 99 % of the estimated elements within 3σ of the truth and none beyond
5σ; startup ≤ 0.1° on every ok joint; the planned maneuver's worst joint startup σ below
``renk-maneuver``'s. ``--figure``: the predicted σ against the maneuver's length, planned
and ``renk-maneuver`` (predictions only: no fit). ``--quick``: 1 seed, 30 s against 60 s,
30 poses, the accelerometers' effects only (the realistic arm's values of those, nothing else
drawn; a smoke run of well under a minute).
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.cli.calibrate_sensors import build_model  # noqa: E402
from armfusion.fusion.configfile import load_arm, read_yaml, resolve_config_path  # noqa: E402
from armfusion.fusion.identification.identify import compare_with_truth  # noqa: E402
from armfusion.fusion.identification.planner import (  # noqa: E402
    CRITERIA,
    PlanSettings,
    maneuver_problems,
    plan_maneuver,
    predicted_identification,
    startup_sigmas,
)
from armfusion.fusion.startup.solve import StartupPrior  # noqa: E402
from armfusion.models.effects import entries_from_model  # noqa: E402
from armfusion.models.rotations import DEG  # noqa: E402
from armfusion.models.simulator import build_model as simulated_model  # noqa: E402
from armfusion.models.trajectories import make_scenario  # noqa: E402
from armfusion.models.trajectories.planned import planned_scenario, played_scenario  # noqa: E402

from tools.bench_calibrated import calibrate, calibrated_config, solve_poses, still_means, summary  # noqa: E402
from tools.bench_startup import draw_poses  # noqa: E402
from tools.benchdoc import machine_line, write_section  # noqa: E402

QUICK_EFFECTS = "accel_bias,accel_scale,mount_rotation"


def true_entries(arm, seed: int, model) -> list[dict] | None:
    """Seed ``seed``'s realistic arm restricted to ``model``'s blocks (config entries), or None
    when the model has every effect the realistic arm draws (the realistic arm itself)."""
    true_model, x = simulated_model(arm, realistic=True, seed=seed)
    if all(b.name in model.index for b in true_model.blocks):
        return None
    return [e for e in entries_from_model(true_model, x) if f"{e['target']}.{e['effect']}" in model.index]


def fit_and_start(arm, seed, scenario, duration_s, effects, q, tilt, near, noise_seed, truth_entries=None,
                  temperatures_c=(25.0,)):
    """Seed ``seed``'s realistic arm (or ``truth_entries``) on ``scenario``: the fit, its truth
    rows, the startup rows at each of ``temperatures_c`` (the same sensors at that temperature,
    the correction taken there; the readings' noise drawn from ``noise_seed`` at each)."""
    res, truth, (t_sim, t_fit) = calibrate(arm, seed, duration_s, scenario=scenario, fit_effects=effects,
                                           true_effects=truth_entries)
    rows = compare_with_truth(res, truth)
    out = Path(tempfile.mkdtemp()) / "cal.yaml"
    out.write_text(yaml.safe_dump(calibrated_config(res), sort_keys=False), encoding="utf-8")
    cal = load_arm(str(out))
    starts = []
    for T in temperatures_c:
        means, offset = still_means(arm, seed, q, tilt, np.random.default_rng(noise_seed),
                                    temperature_c=T, true_effects=truth_entries)
        est, sig, flags, _ = solve_poses(cal, means, near, temperature_c=T)
        starts.append(summary(arm, est, sig, flags, q + offset))
    return res, rows, starts, t_fit


def mean_temperature_c(scenario) -> float:
    """The electronics' mean temperature over a maneuver (the temperature it calibrates at)."""
    return float(np.mean(scenario.temperature(np.linspace(0.0, scenario.duration_s, 401))))


def run_seed(arm, m, model, pred, effects, renk_duration, q, tilt, near, seed: int) -> dict:
    """Seed ``seed``: the plan ``m`` and ``renk-maneuver`` played by its realistic arm, fitted,
    and the startup after each at 25 °C and at the maneuver's mean temperature. Per maneuver:
    (its results row, its elements beyond 4σ, that temperature, a line to print)."""
    sc = played_scenario(arm, m, seed)
    renk = make_scenario(arm, "renk-maneuver", renk_duration, seed)
    out = {}

    def per_joint(rows):
        return ", ".join(f"{r['joint']} {r['rms_ok_deg']:.3f}/{r['median_sigma_deg']:.3f}" for r in rows)

    for key, scen, dur in (("planned", sc, m.duration_s), ("renk", "renk-maneuver", renk_duration)):
        temp = mean_temperature_c(sc if key == "planned" else renk)
        res, rows, starts, t_fit = fit_and_start(arm, seed, scen, dur, effects, q, tilt, near,
                                                 [seed, 0x57], true_entries(arm, seed, model), (25.0, temp))
        start = starts[0]
        z = np.array([r["z"] for r in rows])
        ratio = sigma_ratio(pred, res) if key == "planned" else np.array([np.nan])
        worst = max((r["median_sigma_deg"] for r in start if r["ok_pct"] > 0), default=np.nan)
        beyond = ", ".join(f"{r['name']} {r['z']:+.1f}" for r in rows if abs(r["z"]) > 3)
        wrong = ", ".join(f"{r['joint']} {r['wrong_4sigma']} (RMS {r['rms_ok_deg']:.3f}°)"
                          for r in start if r["wrong_4sigma"])
        text = (f"seed {seed} {key}: {np.mean(np.abs(z) <= 3) * 100:.1f} % within 3σ, "
                f"{int(np.sum(np.abs(z) > 5))} beyond 5σ, worst startup σ {worst:.4f}°, "
                f"fit {t_fit:.0f} s ({res.iterations} Jacobians); beyond 3σ: {beyond or 'none'}; "
                f"startup ok answers beyond 4σ: {wrong or 'none'}; at 25 °C: "
                + per_joint(start) + f"; at {temp:.1f} °C: " + per_joint(starts[1]))
        print(text, flush=True)
        out[key] = ((z, start, t_fit, res.iterations, ratio, starts[1]),
                    [(seed, r["name"], r["z"]) for r in rows if abs(r["z"]) > 4], temp, text)
    return out


def sigma_ratio(pred, res) -> np.ndarray:
    """Fitted σ over predicted σ of the elements both estimate (neither holds)."""
    both = ~pred.held & ~res.held
    return res.sigma[both] / pred.sigma[both]


def draw_figure(out: dict, path: Path) -> None:
    """``out[kind] = (lengths, median σ / prior σ, worst joint's startup σ [deg])`` drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, NullFormatter, ScalarFormatter

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ticks = sorted({L for Ls, _, _ in out.values() for L in Ls})
    for kind, (Ls, med, worst) in out.items():
        ax[0].loglog(Ls, med, "o-", label=kind)
        ax[1].loglog(Ls, worst, "o-", label=kind)
    ax[0].set_ylabel("median σ / prior σ, estimated elements")
    ax[1].set_ylabel("worst joint's startup σ [deg] (25 °C)")
    ax[1].axhline(0.1, color="grey", ls=":", label="0.1°")
    nice = np.array([0.01, 0.02, 0.03, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.0])
    for a, k in ((ax[0], 1), (ax[1], 2)):
        v = [x for o in out.values() for x in o[k]] + ([0.1] if k == 2 else [])
        a.set_yticks(nice[(nice >= 0.9 * min(v)) & (nice <= 1.1 * max(v))])
    for a in ax:
        a.set_xlabel("maneuver length [s]")
        a.set_xticks(ticks)
        a.xaxis.set_major_formatter(ScalarFormatter())
        a.xaxis.set_minor_formatter(NullFormatter())
        a.yaxis.set_minor_formatter(NullFormatter())
        a.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        a.grid(True, which="both", alpha=0.3)
        a.legend()
    fig.suptitle("Predicted σ after the maneuver (WMRA, --effects all, the fit at the priors)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def figure(model, cfg, st: PlanSettings, lengths, renk_lengths, path: Path) -> list[str]:
    """Predicted σ against the maneuver's length: planned and renk-maneuver."""
    arm = model.arm
    rows = []
    out = {}
    for kind, Ls in (("planned", lengths), ("renk-maneuver", renk_lengths)):
        med, worst = [], []
        for L in Ls:
            if kind == "planned":
                sc = planned_scenario(arm, plan_maneuver(model, PlanSettings(
                    **{**st.__dict__, "duration_s": float(L)})).maneuver, np.random.default_rng(0), 0.0)
            else:
                sc = make_scenario(arm, "renk-maneuver", float(L), 0)
            p = predicted_identification(model, sc)
            free = ~p.held
            med.append(float(np.median(p.sigma[free] / p.prior_sigma[free])))
            js, _ = startup_sigmas(cfg, p, 48)
            worst.append(float(np.degrees(np.nanmax(js))))
            rows.append(f"| {kind} | {L:g} | {med[-1]:.3f} | {worst[-1]:.3f} |")
            print(rows[-1], flush=True)
        out[kind] = (Ls, med, worst)
    draw_figure(out, path)
    return ["| maneuver | length [s] | median σ / prior σ (estimated elements) "
            "| worst joint startup σ [deg] |",
            "| --- | ---: | ---: | ---: |", *rows]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--duration", type=float, default=60.0, help="the planned maneuver's length [s]")
    ap.add_argument("--renk-duration", type=float, default=300.0)
    ap.add_argument("--poses", type=int, default=200)
    ap.add_argument("--effects", default="all")
    ap.add_argument("--criterion", default="D", choices=list(CRITERIA))
    ap.add_argument("--dwells", default="", help="the dwells each pose may be held, s (e.g. 1,1.5,2,3); "
                                                 "default: every pose 2 s")
    ap.add_argument("--jobs", type=int, default=1, help="seeds run at once, each in its own process")
    ap.add_argument("--out", type=Path, default=None, help="write the markdown section to this file")
    ap.add_argument("--figure", type=Path, default=None, help="draw the predicted σ against length here")
    ap.add_argument("--quick", action="store_true", help="1 seed, 30 s against 60 s, 30 poses, the "
                                                         "accelerometers' effects only")
    a = ap.parse_args(argv)
    if a.quick:
        a.seeds, a.duration, a.renk_duration, a.poses, a.effects = 1, 30.0, 60.0, 30, QUICK_EFFECTS
    arm = load_arm("wmra")
    cfg = read_yaml(resolve_config_path("wmra"))
    model = build_model(arm, a.effects)
    dwells = tuple(float(v) for v in a.dwells.split(",") if v.strip())
    st = PlanSettings(duration_s=a.duration, criterion=a.criterion, dwell_choices_s=dwells)
    t0, c0 = time.perf_counter(), time.process_time()
    plan = plan_maneuver(model, st)
    t_plan, t_plan_cpu = time.perf_counter() - t0, time.process_time() - c0
    m = plan.maneuver
    assert not maneuver_problems(arm, m, st)
    pred = predicted_identification(model, m)
    pred_js, _ = startup_sigmas(cfg, pred, 64)
    print(f"plan: {len(m.poses_rad)} poses, {m.duration_s:.1f} s, {t_plan:.0f} s to plan", flush=True)
    rng_p = np.random.default_rng(7)
    q, tilt = draw_poses(arm, a.poses, rng_p)
    near = [StartupPrior.saved_pose(p, sigma_deg=10.0) for p in q + rng_p.normal(0, 10 * DEG, q.shape)]
    temps = {}
    results = {"planned": [], "renk": []}
    beyond4 = {"planned": [], "renk": []}
    job = partial(run_seed, arm, m, model, pred, a.effects, a.renk_duration, q, tilt, near)
    if a.jobs > 1:
        with ProcessPoolExecutor(a.jobs, mp_context=multiprocessing.get_context("fork")) as ex:
            done = list(ex.map(job, range(1, a.seeds + 1)))
    else:
        done = [job(seed) for seed in range(1, a.seeds + 1)]
    for out in done:
        for key, (res_row, b4, temp, _) in out.items():
            results[key].append(res_row)
            beyond4[key] += b4
            temps[key] = temp
    lines = ["## The planned self-calibration maneuver against renk-maneuver (`tools/bench_maneuver.py`"
             + (" --quick" if a.quick else "") + ")", "",
             f"`plan-maneuver --duration {a.duration:g} --criterion {a.criterion}"
             + (f" --dwells {a.dwells}" if dwells else "") + "` on the shipped WMRA "
             f"config, `--effects {a.effects}`: {len(m.poses_rad)} poses, {m.duration_s:.1f} s, planned in "
             f"{t_plan:.0f} s ({t_plan_cpu:.0f} s of CPU); against `renk-maneuver` for "
             f"{a.renk_duration:g} s. "
             f"Seeds 1-{a.seeds}'s realistic arms; the startup on {a.poses} random still poses (pose seed 7) "
             "of the same sensors at 25 °C (and at the maneuver's own mean temperature: "
             f"{temps['planned']:.1f} °C for the plan, {temps['renk']:.1f} °C for `renk-maneuver`, the "
             "electronics warming from 22 °C), "
             f"prior a saved pose at the truth + N(0, 10°). {machine_line()}.", "",
             "| maneuver | elements within 3σ | beyond 5σ | fit [s], median | per joint at 25 °C: RMS error "
             "of the ok answers / median σ [deg], j1…j7 (median over seeds) | startup ok answers beyond 4σ "
             "(all seeds) | worst ok joint at 25 °C: RMS / σ [deg], median over seeds | the same at the "
             "maneuver's temperature |",
             "| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: |"]
    worst_of, worst_rms = {}, {}
    labels = (("planned", f"planned {m.duration_s:.0f} s"), ("renk", f"renk-maneuver {a.renk_duration:g} s"))

    def worst_joint(starts):
        rms = np.array([[s_["rms_ok_deg"] for s_ in r] for r in starts])
        med = np.array([[s_["median_sigma_deg"] for s_ in r] for r in starts])
        w_sig = np.array([np.nanmax(m_) if np.isfinite(m_).any() else np.nan for m_ in med])
        w_rms = np.array([np.nanmax(r_) if np.isfinite(r_).any() else np.nan for r_ in rms])
        return rms, med, float(np.nanmedian(w_rms)), float(np.nanmedian(w_sig))

    for key, label in labels:
        R = results[key]
        z = np.concatenate([r[0] for r in R])
        rms, med, worst_rms[key], worst_of[key] = worst_joint([r[1] for r in R])
        _, _, rms_T, sig_T = worst_joint([r[5] for r in R])
        per = " / ".join("flagged" if np.all(np.isnan(rms[:, j]))
                         else f"{np.nanmedian(rms[:, j]):.3f}, {np.nanmedian(med[:, j]):.3f}"
                         for j in range(arm.n_joints))
        n_wrong = sum(s_["wrong_4sigma"] for r in R for s_ in r[1])
        lines.append(f"| {label} | {np.mean(np.abs(z) <= 3) * 100:.1f} % of {len(z):,} | "
                     f"{int(np.sum(np.abs(z) > 5))} | {np.median([r[2] for r in R]):.0f} | {per} | "
                     f"{n_wrong} | {worst_rms[key]:.3f} / {worst_of[key]:.4f} | {rms_T:.3f} / {sig_T:.4f} |")
    lines.append("")
    for key, label in labels:
        b4 = beyond4[key]
        lines.append(f"- Elements beyond 4σ after {label} (all seeds): "
                     + (", ".join(f"seed {sd} {n} {zz:+.1f}" for sd, n, zz in b4) if b4 else "none") + ".")
    ratio = np.concatenate([r[4] for r in results["planned"]])
    z_plan = np.abs(np.concatenate([r[0] for r in results["planned"]]))
    lines += [f"- Predicted before any recording (`plan-maneuver`): worst joint's startup σ "
              f"{np.degrees(np.nanmax(pred_js)):.4f}° (per joint "
              + ", ".join("flagged" if not np.isfinite(v) else f"{np.degrees(v):.3f}" for v in pred_js)
              + f"); fitted σ over predicted σ of the elements both estimate: median {np.median(ratio):.2f}, "
              f"{np.mean(np.abs(ratio - 1) <= 0.3) * 100:.0f} % within 30 %.",
              f"- Target: the planned maneuver's worst joint startup σ below renk-maneuver's: "
              f"{worst_of['planned']:.4f}° against {worst_of['renk']:.4f}° "
              f"({'met' if worst_of['planned'] < worst_of['renk'] else 'not met'}).",
              f"- Target: startup ≤ 0.1° on every ok joint (at 25 °C): worst ok joint's RMS "
              f"{worst_rms['planned']:.3f}°, "
              f"σ {worst_of['planned']:.4f}° after the plan "
              f"({'met' if max(worst_rms['planned'], worst_of['planned']) <= 0.1 else 'not met'}).",
              "- Target: ≥ 99 % of the elements within 3σ and none beyond 5σ after the plan: "
              + ("met" if np.mean(z_plan <= 3) >= 0.99 and not np.any(z_plan > 5) else "not met") + "."]
    if a.figure is not None:
        lens = [30, 60, 120] if not a.quick else [20, 30]
        renk_lens = [60, 120, 300, 600] if not a.quick else [30, 60]
        lines += ["", *figure(model, cfg, st, lens, renk_lens, a.figure),
                  "", f"Figure: `{a.figure}`."]
    md = "\n".join(lines)
    print(md)
    if a.out is not None:
        print(f"\nwritten to {write_section('bench_maneuver', md, a.out)}")
    elif not a.quick:
        print(f"\nwritten to {write_section('bench_maneuver', md)}")


if __name__ == "__main__":
    main()
