"""The workbench on the UR5 twin (tools/twin_ur5.py): does the config `diagnose --discover`
writes ever track worse, on data its fit did not see, than the config it started from?

Each seed's twin (a UR5 bolted to a table, two IMUs with the real arm's errors: scales
3.5-4.4 % low, mounts about 1° off, clocks drifting within ±13 ms, logged at 100 Hz and
resampled to 125 Hz) is written as its CSV and imported, then, each command a subprocess:

1. `armfusion diagnose --discover --write fitted.yaml --json` with the shipped
   `config/ur5_two_imu.yaml` (fitted on the recording's first 70 %, every rung judged on the
   rest);
2. `armfusion track` over the whole recording with the shipped config and with the written
   one (where one was written), each scored on the held-out part only (the last 30 %, which
   the fit did not see) against the controller's angles: what gravity reads (the forearm's
   pitch, joints 2 + 3; the wrist's, 2 + 3 + 4; joint 4 alone) as RMS error, and the share of
   instants each of joints 2-4 is within 3 σ of the truth.

Named: whether the final model (its findings, groups included) carries each IMU's
`accel_scale`, a `time_offset` or `time_drift` of either IMU, and whether both IMU streams
were recognised as resampled from 100 Hz.

Targets: the written config never tracks worse on the held-out part than the shipped one;
with it, forearm and wrist pitch ≤ 0.3° RMS and within 3 σ ≥ 95 %; the scale error and the
time offsets named in ≥ 90 % of recordings.

    python tools/bench_workbench_twin.py [--seeds 20] [--duration 20] [--jobs 2] [--out FILE] [--quick]

The seeds run in ``--jobs`` processes at once (each seed's commands one after the other);
the CPU figures are each command's own.
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.fusion.workbench.heldout import CHANCE_Z, HELD_OUT_SHARE  # noqa: E402

from tools.bench_real_arm import armfusion  # noqa: E402
from tools.benchdoc import machine_line, measured_on, publish, record_headline  # noqa: E402
from tools.twin_ur5 import CONFIG, make_twin, write_csv  # noqa: E402

IMUS = ("forearm", "wrist")
JOINTS = ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
PITCH_TARGET_DEG = 0.3
ENCODER_STEP_DEG = 360.0 / 2**20
"""One count of the controller's angles as the shipped config reads them (2^20 a turn)."""
WITHIN_TARGET = 0.95


def children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def held_out_score(est: Path, twin, t_split: float) -> dict:
    """The tracked angles on the held-out part (t ≥ ``t_split``) against the truth."""
    e = np.genfromtxt(est, delimiter=",", names=True)
    late = e["t"] >= t_split
    truth = {nm: np.interp(e["t"], twin.columns["time_s"], twin.columns[f"q{i + 1}_deg"])
             for i, nm in enumerate(JOINTS)}
    err = {nm: np.degrees(e[f"q_{nm}"]) - truth[nm] for nm in JOINTS}
    sig = {nm: np.degrees(e[f"sigma_{nm}"]) for nm in JOINTS}

    def rms(x):
        return float(np.sqrt(np.mean(x[late] ** 2)))

    within = {nm: float(np.mean(np.abs(err[nm][late]) <= 3.0 * sig[nm][late]))
              for nm in ("shoulder", "elbow", "wrist1")}
    return {"forearm_pitch_rms": rms(err["shoulder"] + err["elbow"]),
            "wrist_pitch_rms": rms(err["shoulder"] + err["elbow"] + err["wrist1"]),
            "j4_rms": rms(err["wrist1"]), "within_3_sigma": within,
            "within_3_sigma_min": min(within.values()), "instants": int(late.sum())}


def named(doc: dict) -> dict:
    disc = doc.get("discovery") or {}
    members = [m for f in disc.get("findings", []) for m in f["members"]]
    return {
        "scale": all(f"accel_scale:{s}" in members for s in IMUS),
        "scale_any": any(f"accel_scale:{s}" in members for s in IMUS),
        "time": any(f"{e}:{s}" in members for e in ("time_offset", "time_drift") for s in IMUS),
        "resampled": sorted(r["stream"] for r in doc.get("resampled_streams", [])
                            if abs(r["source_hz"] - 100.0) < 1.0) == sorted(IMUS),
        "findings": [f["added"] for f in disc.get("findings", [])],
    }


def run_seed(seed: int, duration_s: float, tmp: Path) -> dict:
    twin = make_twin(seed, duration_s)
    csv = write_csv(twin, tmp / f"twin{seed}.csv")
    rec = tmp / f"twin{seed}.mcap"
    r = armfusion("import", str(csv), "--map", "ur5-csv", "--config", str(CONFIG), "--out", str(rec))
    if r.returncode:
        raise SystemExit(f"import failed: {r.stderr}")
    fitted = tmp / f"fitted{seed}.yaml"
    cpu0, t0 = children_cpu_s(), time.perf_counter()
    r = armfusion("diagnose", str(rec), "--config", str(CONFIG), "--discover", "--write", str(fitted),
                  "--history", str(tmp / f"h{seed}.json"), "--json")
    cpu, wall = children_cpu_s() - cpu0, time.perf_counter() - t0
    if r.returncode not in (0, 1):
        raise SystemExit(f"diagnose failed: {r.stderr[-2000:]}")
    doc = json.loads(r.stdout)
    disc = doc["discovery"]
    out = {"seed": seed, "offsets_ms": twin.offsets_ms, "discover_cpu_s": cpu, "discover_wall_s": wall,
           "rungs": [(g["label"], g["rms_ratio"], g["held_out_rms_ratio"]) for g in disc["rungs"]],
           "refused": disc["refused"], "write_refused": doc.get("write_refused"),
           "as_it_was_held_out": doc.get("as_it_was_held_out_rms_ratio"), "named": named(doc),
           "wrote": fitted.exists(), "tracked_held_out": doc.get("tracked_held_out")}
    t_split = float(twin.columns["time_s"][-1]) * (1.0 - HELD_OUT_SHARE)
    for name, cfg in (("shipped", CONFIG), ("fitted", fitted)):
        if not cfg.exists():
            continue
        est = tmp / f"est{seed}_{name}.csv"
        r = armfusion("track", str(rec), "--config", str(cfg), "--after-s", "0", "--json", "--out", str(est))
        if r.returncode:
            raise SystemExit(f"track failed ({name}): {r.stderr[-2000:]}")
        out[name] = held_out_score(est, twin, t_split)
    return out


SCORED = (("forearm_pitch_rms", "elbow"), ("wrist_pitch_rms", "wrist1"), ("j4_rms", "wrist1"))
"""Each figure scored, and the joint whose chance spread (the write gate's,
:func:`armfusion.fusion.workbench.heldout.chance_deg`) it carries: a sum of joints is read by
the accelerometers after its last one."""


def _worse(row: dict, chance: bool = False) -> bool:
    """The written config tracks the held-out part worse than the shipped one: a pitch RMS,
    joint 4's RMS (what gravity reads between the two IMUs) or the within-3σ share worse;
    with ``chance``, an RMS worse by more than the write gate's chance floor (CHANCE_Z times
    its spread for the joint, at least one encoder count)."""
    if "fitted" not in row:
        return False
    a, b = row["shipped"], row["fitted"]
    if b["within_3_sigma_min"] < a["within_3_sigma_min"]:
        return True
    spread = ((row.get("tracked_held_out") or {}).get("as_it_is") or {}).get("chance_deg", {})
    return any(b[k] - a[k] > (max(CHANCE_Z * spread.get(j, 0.0), ENCODER_STEP_DEG) if chance else 0.0)
               for k, j in SCORED)


def _refusals(rows: list[dict]) -> str:
    """The refused configs re-examined against the truth: the twin's controller angles are its
    encoders, so the gate's tracked figures of the config it refused (``tracked_held_out``)
    are its RMS off the truth on the held-out part, joint by joint and by the sums judged."""
    refused = [r for r in rows if not r["wrote"]]
    worse, ratios = [], []
    for r in refused:
        t = r.get("tracked_held_out") or {}
        a, w = t.get("as_it_is") or {}, t.get("written") or {}
        chance = a.get("chance_deg", {})
        excess = [(w["encoder_rms_deg"][j] - a["encoder_rms_deg"][j])
                  / max(CHANCE_Z * chance.get(j, 0.0), ENCODER_STEP_DEG)
                  for j in w.get("encoder_rms_deg", {}) if j in a.get("encoder_rms_deg", {})]
        if excess and max(excess) > 1.0:
            worse.append(r["seed"])
            ratios.append(max(excess))
    return (f"- Refused: {len(refused)} of {len(rows)}; of them, {len(worse)} would have tracked a joint "
            "(or a sum of joints) further off the controller's angles, which are the twin's truth, than the "
            "shipped config by more than the chance floor (the largest excess per refusal "
            + (f"{min(ratios):.1f}-{max(ratios):.0f} × the floor" if ratios else "none") + "); the other "
            f"{len(refused) - len(worse)} were refused for their held-out fit or innovations.")


def report(rows: list[dict], seconds: float, duration_s: float, load: float | None = None) -> str:
    n = len(rows)
    wrote = [r for r in rows if "fitted" in r]
    worse = [r["seed"] for r in rows if _worse(r)]
    beyond = [r["seed"] for r in rows if _worse(r, chance=True)]
    lines = [
        "## The workbench on the UR5 twin: held out, then tracked (`tools/bench_workbench_twin.py`)",
        "",
        f"{n} twins of {duration_s:.0f} s (seeds 0-{n - 1}), each fitted on its first "
        f"{100 * (1 - HELD_OUT_SHARE):.0f} % by `diagnose --discover` and tracked with the shipped and the "
        f"written config; every figure on the held-out last {100 * HELD_OUT_SHARE:.0f} % only. "
        f"{machine_line()}; {seconds:.0f} s in all"
        + (f", beside other work (the one-minute load average {load:.1f} as it ended)"
           if load is not None else "") + ".",
        "",
        "| seed | rungs (refused) | held out: first → last rung | written "
        "| forearm pitch RMS ° shipped → written | wrist pitch RMS ° | j4 RMS ° "
        "| within 3σ (min of j2-j4) | named: scale / time / resampled | discover CPU s |",
        "| ---: | ---: | --- | --- | --- | --- | --- | --- | --- | ---: |",
    ]
    for r in rows:
        s, w = r["shipped"], r.get("fitted")
        first, last = r["rungs"][0][2], r["rungs"][-1][2]

        def pair(k, fmt="{:.2f}", s=s, w=w):
            return fmt.format(s[k]) + (" → " + fmt.format(w[k]) if isinstance(w, dict) else "")

        nm = r["named"]
        lines.append(
            f"| {r['seed']} | {len(r['rungs']) - 1} ({len(r['refused'])}) | {first:.2f} → {last:.2f} | "
            f"{'yes' if r['wrote'] else 'refused: ' + str(r['write_refused'])} | "
            f"{pair('forearm_pitch_rms')} | {pair('wrist_pitch_rms')} | {pair('j4_rms')} | "
            f"{pair('within_3_sigma_min', '{:.1%}')} | "
            f"{'yes' if nm['scale'] else ('one' if nm['scale_any'] else 'no')} / "
            f"{'yes' if nm['time'] else 'no'} / {'yes' if nm['resampled'] else 'no'} | "
            f"{r['discover_cpu_s']:.0f} |")
    fitted = [r["fitted"] for r in wrote]
    lines += [
        "",
        f"- Written: {len(wrote)} of {n}; tracking the held-out part worse than the shipped config "
        f"(a pitch RMS, joint 4's RMS or the within-3σ share): {len(worse)} of {len(wrote)}"
        + (f" (seeds {', '.join(map(str, worse))})" if worse else "") + "; by more than the write gate's "
        f"chance floor ({CHANCE_Z:.0f} × the spread the accelerometers' datasheet noise gives two RMS "
        f"figures over the held-out part, at least one count): {len(beyond)}"
        + (f" (seeds {', '.join(map(str, beyond))})" if beyond else "") + ". Target: none.",
        _refusals(rows),
    ]
    if fitted:
        fp = np.array([f["forearm_pitch_rms"] for f in fitted])
        wp = np.array([f["wrist_pitch_rms"] for f in fitted])
        wi = np.array([f["within_3_sigma_min"] for f in fitted])
        lines.append(
            f"- With the written config: forearm pitch ≤ {PITCH_TARGET_DEG}° RMS in "
            f"{int(np.sum(fp <= PITCH_TARGET_DEG))} of {len(fitted)} (median {np.median(fp):.2f}°), wrist "
            f"pitch in {int(np.sum(wp <= PITCH_TARGET_DEG))} (median {np.median(wp):.2f}°), within 3σ ≥ "
            f"{WITHIN_TARGET:.0%} in {int(np.sum(wi >= WITHIN_TARGET))} (median {np.median(wi):.1%}).")
    lines += [
        f"- Named in the final model: both IMUs' scale {sum(r['named']['scale'] for r in rows)} of {n}, "
        f"at least one {sum(r['named']['scale_any'] for r in rows)} of {n}; a time offset or drift "
        f"{sum(r['named']['time'] for r in rows)} of {n}; both streams resampled from 100 Hz "
        f"{sum(r['named']['resampled'] for r in rows)} of {n}. Target: ≥ 90 % each.",
        f"- Discovery's CPU: median {np.median([r['discover_cpu_s'] for r in rows]):.0f} s, "
        f"most {max(r['discover_cpu_s'] for r in rows):.0f} s for {duration_s:.0f} s of data "
        f"(the whole command: import of the modules, the split fit, the ladder, the revisit, the write).",
    ]
    return "\n".join(lines)


def headline_rows(rows: list[dict]) -> list[dict]:
    """The README's row: how many written configs track the held-out part worse than the
    shipped one, and the forearm's pitch with them against the shipped config's."""
    wrote = [r for r in rows if "fitted" in r]
    fp = np.median([r["fitted"]["forearm_pitch_rms"] for r in wrote]) if wrote else float("nan")
    shipped = np.median([r["shipped"]["forearm_pitch_rms"] for r in wrote]) if wrote else float("nan")
    return [{"what": f"UR5 twin ({len(rows)} simulated recordings of a real arm's errors), `diagnose "
                     "--discover --write` judged on the held-out 30 %: configs tracking worse than the one "
                     "they replace; forearm pitch RMS with them, median",
             "armfusion": f"{sum(_worse(r) for r in wrote)} of {len(wrote)} written; {fp:.2f}°",
             "baseline": f"shipped config {shipped:.2f}°"}]


def _publish(rows: list[dict], body: str, out: Path | None, quick: bool,
             measured: dict | None = None) -> None:
    """The section where asked; the headline rows with it when it goes on its page (with
    ``measured``, when and on what code they were measured; default now)."""
    publish("bench_workbench_twin", body, out, quick)
    if out is None and not quick:
        record_headline("bench_workbench_twin", headline_rows(rows), measured=measured)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--duration", type=float, default=20.0, help="each twin's length, s")
    ap.add_argument("--jobs", type=int, default=2, help="seeds run at once (processes)")
    ap.add_argument("--out", type=Path, help="write the section here instead of docs/benchmarks.md")
    ap.add_argument("--quick", action="store_true", help="2 seeds of 20 s; docs/benchmarks.md untouched")
    ap.add_argument("--rows", type=Path, help="also keep each seed's figures here (JSON)")
    ap.add_argument("--from-rows", type=Path, help="write the section from a --rows file, running nothing")
    a = ap.parse_args(argv)
    if a.from_rows is not None:
        kept = json.loads(a.from_rows.read_text(encoding="utf-8"))
        body = report(kept["rows"], kept["seconds"], kept["duration_s"], kept.get("load_average"))
        print(body)
        _publish(kept["rows"], body, a.out, a.quick, kept.get("measured_on"))
        return 0
    seeds = 2 if a.quick else a.seeds
    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as d, ProcessPoolExecutor(max(1, a.jobs)) as pool:
        tmp = Path(d)
        futures = [pool.submit(run_seed, seed, a.duration, tmp) for seed in range(seeds)]
        for seed, fut in enumerate(futures):
            rows.append(fut.result())
            r = rows[-1]
            w = r.get("fitted")
            print(f"seed {seed}: {len(r['rungs']) - 1} rungs, held out {r['rungs'][0][2]:.2f} -> "
                  f"{r['rungs'][-1][2]:.2f}; forearm pitch {r['shipped']['forearm_pitch_rms']:.2f}"
                  + (f" -> {w['forearm_pitch_rms']:.2f}" if w else "") + f" deg; named {r['named']}"
                  + ("" if r["wrote"] else f"; not written: {r['write_refused']}"), flush=True)
    seconds = time.perf_counter() - t0
    if a.rows is not None:
        kept = {"rows": rows, "seconds": seconds, "duration_s": a.duration,
                "load_average": os.getloadavg()[0], "measured_on": measured_on()}
        a.rows.write_text(json.dumps(kept, default=float), encoding="utf-8")
    body = report(rows, seconds, a.duration, os.getloadavg()[0])
    print(body)
    _publish(rows, body, a.out, a.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
