"""Startup calibration over many random still poses: accuracy, the Cramér-Rao bound,
flags, confident wrong answers and solve time; armfusion's joint solve against the
thesis's sequential method in the same run. Writes its section of docs/benchmarks.md.

    python tools/bench_startup.py [--poses 10000] [--realistic] [--config C]

Each pose: a random WMRA pose inside the joint limits (a tenth of them near the park
pose's gimbal lock), the chair tilted by up to a few degrees, 1 s of ADXL345 and MPU-9150
samples at 100 Hz (noise, rounding to counts, saturation: `armfusion.models.sensor_models`),
averaged exactly as `calibrate joints` averages a still window. Three priors on the same
poses: none (no saved pose), a stale saved pose (another pose's: the arm was moved by hand
while off), and a saved pose near the truth (the true pose + N(0, 10 deg)); after each, the
proposed disambiguating move is made and the pose solved again. With
``--realistic`` every sensor carries datasheet-typical errors the solver's config does not
know (the simulator's `--realistic` draw of every effect in the library, a new imperfect arm
every 100 poses), which is the thesis's situation, and
the solver uses the shipped config's unmodelled-error floor; without it the sensors are
exactly as configured and the config claims no unmodelled error.

The solve time is the CPU time (``time.process_time``) of one ``solve_still`` call (every
branch, sigma checks included, no unlock move), median over the poses, against the
target of 5 ms: the machine is shared, and wall-clock time would measure the other
processes too.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.startup.problem import expected_sigma, make_problem  # noqa: E402
from armfusion.fusion.startup.solve import (  # noqa: E402
    StartupPrior,
    StartupSettings,
    move_delta_rad,
    prior_after_move,
    readings_from_counts,
    solve_still,
)
from armfusion.models.kinematics import gravity_in_sensors, joint_axis_angle_to_vertical  # noqa: E402
from armfusion.models.rotations import DEG, up_from_tilt, wrap_angle  # noqa: E402
from armfusion.models.sensor_models import stream_models  # noqa: E402

from tools.benchdoc import machine_line, record_headline, write_section  # noqa: E402

THESIS_RAD = 0.1
TARGET_S = 5e-3  # target: median solve time, all 7 joints, every branch


def draw_poses(arm, n, rng):
    q = rng.uniform(arm.min_rad, arm.max_rad, size=(n, arm.n_joints))
    near = rng.random(n) < 0.1  # near the park pose's lock: joint 3's axis within ~5 deg
    q[near, 0] = (90 + rng.uniform(-4, 4, near.sum())) * DEG
    q[near, 1] = (90 + rng.uniform(-4, 4, near.sum())) * DEG
    tilt = rng.normal(0, 3, size=(n, 2)) * DEG
    return q, tilt


def simulate_means(arm, q, tilt, rng, n_samples=100, rate_hz=100.0, realistic=False,
                   arm_every=100, seed=0):
    """Mean counts over 1 s per sensor, ``{stream: (N, 3)}``, from digitised samples.

    ``realistic``: the physical readings come from the simulator's own effects model with
    every effect of the library drawn at datasheet-typical magnitudes (``--realistic``), a
    new imperfect arm every ``arm_every`` poses.
    """
    models = stream_models(arm, rate_hz)
    names = [s.name for s in arm.link_accelerometers]
    streams = [*names, "imu_acc"]
    up = up_from_tilt(tilt[:, 0], tilt[:, 1])
    if realistic:
        from armfusion.models.motion import MotionState
        from armfusion.models.simulator import build_model

        phys = {s: np.empty((len(q), 3)) for s in streams}
        for a in range(0, len(q), arm_every):
            sl = slice(a, min(a + arm_every, len(q)))
            model, x = build_model(arm, realistic=True, seed=seed * 100_003 + a)
            x = np.array(x, float)
            for e in model.effects:  # a still arm sees no time offset (and a batch's rows are
                if e.stage == "time":  # unrelated poses: no time derivative across them)
                    x[model.index[e.block_name]] = 0.0
            state = MotionState.static(q[sl], tilt[sl, 0], tilt[sl, 1])
            pred = model.predict(state, x, streams, units="physical")
            for s in streams:
                phys[s][sl] = pred[s]
    else:
        f = gravity_in_sensors(arm, q, up)  # (N, S, 3) g
        phys = {name: f[:, i] for i, name in enumerate(names)}
        phys["imu_acc"] = up
    out = {}
    for s in streams:
        ideal = models[s].to_counts(phys[s])
        out[s] = models[s].digitise(np.repeat(ideal[:, None], n_samples, 1), rng).mean(1)
    return out


def run(arm, q, tilt, means, priors, settings, method):
    """Solve every pose; ``priors``: per pose a :class:`StartupPrior` or None."""
    n = len(q)
    est = np.full((n, arm.n_joints), np.nan)
    sig = np.full((n, arm.n_joints), np.nan)
    flags = np.empty((n, arm.n_joints), dtype=object)
    crb = np.full((n, arm.n_joints), np.nan)
    thesis = np.zeros((n, arm.n_joints), dtype=bool)  # the thesis's detector said "locked"
    times = np.empty(n)
    results = []
    for k in range(n):
        readings = readings_from_counts(arm, {s: m[k] for s, m in means.items()}, n_samples=100,
                                        rate_hz=100.0)
        t0 = time.process_time()
        res = solve_still(arm, readings, settings, prior=priors[k], method=method, propose_unlock=False)
        times[k] = time.process_time() - t0
        results.append(res)
        for j, je in enumerate(res.joints):
            flags[k, j] = je.flag
            thesis[k, j] = bool(je.thesis_detector_locked)
            if je.angle_rad is not None:
                est[k, j] = je.angle_rad
                sig[k, j] = je.sigma_rad if je.sigma_rad is not None else np.nan
        x = np.concatenate([q[k], tilt[k]])[None]
        crb[k] = expected_sigma(make_problem(arm, readings), x)[0, : arm.n_joints]
    err = wrap_angle(est - q)
    return err, sig, flags, crb, times, thesis, results


def moved_poses(arm, q, results):
    """The poses left with an ambiguous joint, those of them with a proposed disambiguating
    move, and every pose after its move (the others as they were)."""
    amb = [k for k, r in enumerate(results) if any(j.flag == "ambiguous" for j in r.joints)]
    moved = [k for k in amb if results[k].disambiguating_move is not None]
    q2 = q.copy()
    for k in moved:
        q2[k] += move_delta_rad(results[k].disambiguating_move, arm)
    return amb, moved, q2


def after_move(arm, q, tilt, results, settings, rng, realistic, seed):
    """Every pose left with ambiguous joints: make its proposed disambiguating move (the
    encoders count it), simulate a second still second there, and solve again with the first
    window's candidates carried through the encoders. Returns (ambiguous poses, with a move,
    resolved, confident wrong answers after the move, numeric answers of the second solve)."""
    amb, moved, q2 = moved_poses(arm, q, results)
    if not moved:
        return len(amb), 0, 0, 0, 0
    # the whole set again (the same imperfect arm per block of poses), only the moved ones used
    means2 = simulate_means(arm, q2, tilt, rng, realistic=realistic, seed=seed)
    resolved = wrong = numeric = 0
    for k in moved:
        r = readings_from_counts(arm, {s: m[k] for s, m in means2.items()}, n_samples=100, rate_hz=100.0)
        m = results[k].disambiguating_move
        res = solve_still(arm, r, settings, prior=prior_after_move(results[k], m, arm, settings),
                          propose_unlock=False)
        by = {je.name: je for je in res.joints}
        resolved += all(by[nm].flag != "ambiguous" for nm in m.resolves)
        for j, je in enumerate(res.joints):
            if je.angle_rad is not None:
                numeric += 1
                e = abs(wrap_angle(je.angle_rad - q2[k, j]))
                wrong += je.flag == "ok" and e > 4 * je.sigma_rad
    return len(amb), len(moved), resolved, wrong, numeric


def table(arm, q, tilt, err, sig, flags, crb, lock_deg, thesis):
    ok = flags == "ok"
    ang = np.degrees(joint_axis_angle_to_vertical(arm, q, up_from_tilt(tilt[:, 0], tilt[:, 1])))
    rows = []
    totals = {"wrong": 0, "missed_lock": 0, "thesis_missed": 0, "locked": 0}
    for j in range(arm.n_joints):
        m = ok[:, j]
        rms = np.degrees(np.sqrt(np.mean(err[m, j] ** 2))) if m.any() else np.nan
        num = np.isfinite(err[:, j])  # every pose that got a number, whatever its flag
        rms_all = np.degrees(np.sqrt(np.mean(err[num, j] ** 2))) if num.any() else np.nan
        med_sig = np.degrees(np.nanmedian(sig[num, j])) if num.any() else np.nan
        bound = np.degrees(np.sqrt(np.mean(crb[m, j] ** 2))) if m.any() else np.nan
        wrong = int(np.sum(m & (np.abs(err[:, j]) > 4 * sig[:, j])))
        # flagged numbers carry a sigma too (the tracker starts from it): is it honest?
        beyond_any = int(np.sum(num & (np.abs(err[:, j]) > 4 * sig[:, j])))
        locked_true = ang[:, j] < lock_deg
        # a locked joint must not come out as a confident number: any flag but ok will do
        missed = int(np.sum(locked_true & (flags[:, j] == "ok")))
        totals["wrong"] += wrong
        totals["missed_lock"] += missed
        totals["locked"] += int(locked_true.sum())
        totals["thesis_missed"] += int(np.sum(locked_true & ~thesis[:, j]))
        share = {f: np.mean(flags[:, j] == f) * 100 for f in
                 ("ill_conditioned", "gimbal_lock", "ambiguous", "out_of_limits")}
        rows.append((arm.joints[j].name, rms, bound, rms / bound if bound else np.nan,
                     100 - np.mean(m) * 100, share, wrong, int(locked_true.sum()), missed,
                     rms_all, med_sig, beyond_any, int(num.sum())))
    return rows, totals


def render(rows, totals, title, times, times_ref, n):
    lines = [f"### {title}", "",
             "| joint | RMS error, ok poses [deg] | Cramér-Rao bound [deg] | ratio | "
             "RMS error, every numeric answer [deg] | median sigma [deg] | flagged [%] "
             "(ill-cond / lock / ambiguous / limits) | confident wrong (ok, > 4 sigma) | "
             "numeric answers beyond 4 sigma, any flag | "
             "axis within 2 deg of vertical: poses / reported ok |",
             "| --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: |"]
    for (name, rms, bound, ratio, flagged, share, wrong, locked, missed, rms_all, med_sig,
         beyond_any, n_num) in rows:
        lines.append(
            f"| {name} | {rms:.4f} | {bound:.4f} | {ratio:.2f} | {rms_all:.3f} | {med_sig:.3f} | "
            f"{flagged:.1f} "
            f"({share['ill_conditioned']:.1f} / {share['gimbal_lock']:.1f} / "
            f"{share['ambiguous']:.1f} / {share['out_of_limits']:.1f}) | {wrong} | "
            f"{beyond_any} of {n_num:,} | {locked} / {missed} |")
    lines += ["", f"Thesis: ±{THESIS_RAD} rad = ±{np.degrees(THESIS_RAD):.1f} deg per joint. "
              f"Confident wrong answers in {n:,} poses: **{totals['wrong']}**; locked joints "
              f"reported ok: **{totals['missed_lock']}** of {totals['locked']} (the thesis's "
              f"own detector, at 0.95 g, misses {totals['thesis_missed']}).",
              (f"Solve time (all 7 joints, every branch; CPU time), median: joint "
               f"{np.median(times) * 1e3:.1f} ms, "
               f"thesis's sequential {np.median(times_ref) * 1e3:.1f} ms (ratio "
               f"{np.median(times) / np.median(times_ref):.2f}); 90th percentile: joint "
               f"{np.percentile(times, 90) * 1e3:.1f} ms. Target, median ≤ "
               f"{TARGET_S * 1e3:.0f} ms: "
               + ("met." if np.median(times) <= TARGET_S else
                  "**not met** (what limits it: docs/startup.md, Speed).")) if times is not times_ref else
              f"Solve time (CPU time), median: {np.median(times) * 1e3:.1f} ms."]
    return "\n".join(lines)


PRIORS = (
    ("none", "no prior: no saved pose (the data alone)"),
    ("stale", "a stale saved pose: the pose of another random sample (the arm was moved by hand "
              "while the power was off)"),
    ("near", "a saved pose near the truth: the true pose + N(0, 10 deg) per joint, checked "
             "with a 10 deg sigma (the helpful case the earlier tables measured)"),
)


def priors_for(kind, arm, q, rng):
    if kind == "none":
        return [None] * len(q)
    if kind == "stale":
        other = q[rng.permutation(len(q))]
        return [StartupPrior.saved_pose(p) for p in other]
    near = q + rng.normal(0, 10 * DEG, q.shape)
    return [StartupPrior.saved_pose(p, sigma_deg=10.0) for p in near]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", type=int, default=10_000, help="random still poses (default 10,000)")
    ap.add_argument("--config", default="wmra", help="arm config, by name or path")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--realistic", action="store_true",
                    help="datasheet-typical sensor errors the config does not know")
    ap.add_argument("--no-write", action="store_true",
                    help="print the section without writing docs/benchmarks.md")
    a = ap.parse_args()
    arm = load_arm(a.config)
    if not a.realistic:  # the sensors are exactly as configured: no unmodelled error
        arm = dataclasses.replace(arm, calibration=arm.calibration.with_accel_floor(0.0))
    rng = np.random.default_rng(a.seed)
    q, tilt = draw_poses(arm, a.poses, rng)
    means = simulate_means(arm, q, tilt, rng, realistic=a.realistic, seed=a.seed)
    st = StartupSettings()
    kind = "realistic: datasheet-typical unmodelled sensor errors" if a.realistic else \
        "sensors exactly as configured"
    floor = arm.calibration.accel_unmodelled_g
    flag = " --realistic" if a.realistic else ""
    head = [f"## Startup calibration, {kind} (`tools/bench_startup.py{flag}`)",
            "",
            f"{a.poses:,} random still poses of the WMRA (10 % near the park pose's lock), chair "
            f"tilt N(0, 3 deg), 1 s of 100 Hz ADXL345 + MPU-9150 counts each; config's "
            f"unmodelled-error floor {floor * 1000:.0f} mg; seed {a.seed}; {machine_line()}. "
            "Three priors, the same poses and readings: none, a stale saved pose, a saved pose "
            "near the truth. After each, every pose left with ambiguous joints makes its proposed "
            "disambiguating move, a second still second is simulated there, and the solve runs "
            "again with the first window's candidates carried through the encoders.", ""]
    parts = ["\n".join(head)]
    summary = []
    times_near = None
    for key, title in PRIORS:
        priors = priors_for(key, arm, q, rng)
        err, sig, flags, crb, times, th, results = run(arm, q, tilt, means, priors, st, "joint")
        rows, tot = table(arm, q, tilt, err, sig, flags, crb, 2.0, th)
        n_amb, n_moved, n_res, wrong2, num2 = after_move(arm, q, tilt, results, st, rng,
                                                         a.realistic, a.seed)
        ignored = sum(r.prior_used == "none" for r in results) if key != "none" else a.poses
        md = render(rows, tot, f"Prior: {title}", times, times, a.poses)
        md += (f"\nThe prior was used in {a.poses - ignored:,} poses and found not to fit (ignored, "
               f"with a note) in {ignored if key != 'none' else 0:,}. "
               f"Poses with an ambiguous joint: {n_amb:,}; a disambiguating move was proposed for "
               f"{n_moved:,}; after it, **{n_res:,} of {n_amb:,} resolved** "
               f"({100 * n_res / max(n_amb, 1):.1f} %), with {wrong2} confident wrong answers in "
               f"{num2:,} numeric answers of the second solve.")
        parts.append(md)
        summary.append((key, tot["wrong"], n_amb, n_res, wrong2, np.median(times)))
        if key == "near":
            times_near, near_priors = times, priors
    # the thesis's sequential method, on the helpful prior, as the reference
    err_s, sig_s, flags_s, crb_s, times_s, th_s, _ = run(arm, q, tilt, means, near_priors, st, "sequential")
    rows_s, tot_s = table(arm, q, tilt, err_s, sig_s, flags_s, crb_s, 2.0, th_s)
    parts.append(render(rows_s, tot_s, "The thesis's sequential method, same data, saved pose near "
                        "the truth", times_s, times_s, a.poses)
                 + f"\nSolve time, joint against sequential on the same prior: "
                   f"{np.median(times_near) * 1e3:.1f} / {np.median(times_s) * 1e3:.1f} ms (ratio "
                   f"{np.median(times_near) / np.median(times_s):.2f}).")
    lines = ["### Summary", "", "| prior | confident wrong (ok, > 4 sigma) | poses with an ambiguous "
             "joint | resolved after one move | confident wrong after it | median solve [ms] |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for key, wrong, n_amb, n_res, wrong2, t_med in summary:
        lines.append(f"| {key} | {wrong} | {n_amb:,} | {n_res:,} ({100 * n_res / max(n_amb, 1):.1f} %) "
                     f"| {wrong2} | {t_med * 1e3:.1f} |")
    parts.insert(1, "\n".join(lines))
    md = "\n\n".join(parts)
    print(md)
    if not a.no_write:
        name = "bench_startup_realistic" if a.realistic else "bench_startup"
        print(f"\nwritten to {write_section(name, md)}")
        if a.realistic:
            none = next(s for s in summary if s[0] == "none")
            record_headline(name, [
                {"what": f"Startup on {a.poses:,} random still WMRA poses, datasheet-typical sensor "
                         "errors, no saved pose: confident wrong answers (`ok` yet > 4σ off)",
                 "armfusion": f"{none[1]}", "baseline": ""}])


if __name__ == "__main__":
    main()
