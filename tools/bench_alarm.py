"""The model-change alarm (#21 item 2): detection, naming and false alarms on simulated
daily use.

Each trial simulates a ``daily-use`` recording of the calibrated WMRA (seeded), starts the
tracker on its first still stretch, and injects one change at a random time in the raw
streams: a link accelerometer's mount turned by ``--mount-deg`` about a random axis (its
counts rotated), its bias jumping by ``--bias-g`` in a random direction, or the
magnetometer gaining ``--iron-ut`` of hard iron. A trial counts as detected when the
alarm names the right sensor within ``--within-s`` of the injection, and as named when the
effect is right too. Clean recordings (no injection) give the false-alarm rate per
simulated hour. The table goes to stdout and its section of docs/benchmarks.md (``--out FILE``:
to that file instead; ``--quick``: neither unless ``--out``).

Each recording is independent and seeded (``--jobs N``: N at once, each in its own
process); ``--seeds`` reruns single injections; ``--clean-wall-s`` starts no clean
recording after that much wall time and reports the hours actually run. Rates carry their
Wilson 95 % interval, the false-alarm rate its exact Poisson 95 % interval.

``--cost`` measures instead what the alarm costs the tracker: the same ``daily-use``
recording tracked alternately with the alarm and with a stand-in that listens for nothing
(:class:`SilentAlarm`; every other part of the tracker the same), ``--rounds`` times each,
in one process; CPU per step of both, their ratio, and the live step (``update_instant``)
the same way. Its table goes to its own section (``bench_alarm_cost``).

    python tools/bench_alarm.py [--quick] [--out FILE] [--trials 40] [--clean-hours 100]
        [--jobs 2] [--clean-wall-s S] [--kinds mount_rotation,bias_jump] [--seeds 1002,1017]
    python tools/bench_alarm.py --cost [--rounds 5] [--cost-duration 300] [--out FILE]
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import multiprocessing  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.stats import chi2  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.tracking.tracker import start_from_recording  # noqa: E402
from armfusion.models.rotations import DEG, exp_so3  # noqa: E402
from armfusion.models.sensor_models import AK8975_UT_PER_LSB  # noqa: E402
from armfusion.models.simulator import simulate  # noqa: E402
from armfusion.sensors.samples import Recording  # noqa: E402

from tools.bench_track import calibrated_wmra, with_stream  # noqa: E402
from tools.benchdoc import machine_line, publish, wilson  # noqa: E402

KINDS = ("mount_rotation", "bias_jump", "hard_iron")
ADXL345_G_PER_LSB = 0.0039  # full resolution (the driver's scale)


def mount_turned(rec: Recording, sensor: str, t0: float, axis_angle: np.ndarray) -> Recording:
    """``sensor``'s counts from ``t0`` on as read by a board turned by ``axis_angle`` (rad)."""
    s = rec.get(sensor)
    v = s.values.copy()
    after = s.t_s >= t0
    v[after] = np.round(v[after].astype(float) @ exp_so3(axis_angle)).astype(v.dtype)
    return with_stream(rec, sensor, v)


def bias_jumped(rec: Recording, sensor: str, t0: float, jump_g: np.ndarray) -> Recording:
    s = rec.get(sensor)
    v = s.values.copy()
    v[s.t_s >= t0] += np.round(jump_g / ADXL345_G_PER_LSB).astype(v.dtype)
    return with_stream(rec, sensor, v)


def iron_gained(rec: Recording, t0: float, dB_ut: np.ndarray) -> Recording:
    m = rec.get("imu_mag")
    v = m.values.copy()
    v[m.t_s >= t0] += np.round(dB_ut / AK8975_UT_PER_LSB).astype(v.dtype)
    return with_stream(rec, "imu_mag", v)


def alarms_of(arm, rec: Recording):
    tr, _ = start_from_recording(arm, rec)
    tr.run(rec)
    return tr.alarm.raised


def trial(arm, kind: str, seed: int, duration_s: float, a) -> dict:
    rng = np.random.default_rng(seed)
    rec, _ = simulate(arm, "daily-use", duration_s, seed=seed)
    t0 = float(rng.uniform(0.3 * duration_s, 0.6 * duration_s))
    links = [s.name for s in arm.link_accelerometers]
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    if kind == "mount_rotation":
        sensor = str(rng.choice(links))
        rec = mount_turned(rec, sensor, t0, d * a.mount_deg * DEG)
    elif kind == "bias_jump":
        sensor = str(rng.choice(links))
        rec = bias_jumped(rec, sensor, t0, d * a.bias_g)
    else:
        sensor = "imu_mag"
        rec = iron_gained(rec, t0, d * a.iron_ut)
    raised = alarms_of(arm, rec)
    hit = [al for al in raised if al.sensor == sensor and t0 <= al.raised_s <= t0 + a.within_s]
    early = [al for al in raised if al.raised_s < t0]
    elsewhere = [al for al in raised if al.sensor != sensor and al.raised_s >= t0]
    h = hit[0] if hit else None
    named_by_end = h is not None and h.decided and h.effect == kind
    return {"kind": kind, "seed": seed, "sensor": sensor, "t0": t0, "detected": h is not None,
            "named": named_by_end and h.named_s <= t0 + a.within_s, "named_by_end": named_by_end,
            "delay_s": h.raised_s - t0 if h else None, "size": h.size if named_by_end else None,
            "sigma": h.sigma if named_by_end else None, "false_before": len(early),
            "elsewhere": len(elsewhere),
            "visible": visible(rec, sensor, t0, kind, d), "cpu_s": 0.0,
            "got": [(al.sensor, "/".join(al.candidates), al.raised_s, al.named_s) for al in raised]}


def visible(rec: Recording, sensor: str, t0: float, kind: str, d: np.ndarray) -> float:
    """The share of a change that a sensor at rest sees at ``t0``: ``|d x f|`` for the unit
    direction ``d`` of the turn's axis (or the bias) and the direction of the sensor's
    reading ``f`` over the second before (a turn about the measured force changes nothing; a
    bias across it is what a turn would give too); 1 for the compass."""
    if kind not in ("mount_rotation", "bias_jump"):
        return 1.0
    s = rec.get(sensor)
    f = s.values[(s.t_s >= t0 - 1.0) & (s.t_s < t0)].astype(float).mean(0)
    return float(np.linalg.norm(np.cross(d, f / np.linalg.norm(f))))


def clean(arm, i: int, duration_s: float, seed: int) -> dict:
    rec, _ = simulate(arm, "daily-use", duration_s, seed=seed + 100_003 + i)
    return {"i": i, "duration_s": duration_s, "cpu_s": 0.0,
            "got": [(al.sensor, "/".join(al.candidates), al.raised_s) for al in alarms_of(arm, rec)]}


class SilentAlarm:
    """The baseline of ``--cost``: a tracker's alarm that listens for nothing and never
    raises (the interface the tracker calls, doing no work)."""

    active = False
    version = 0
    alarms: tuple = ()
    raised: tuple = ()

    def listen(self, *args, **kwargs) -> None:
        pass

    def compass(self, *args) -> None:
        pass

    def reacquired(self, *args) -> None:
        pass

    def widen(self, *args) -> None:
        pass


def cost(arm, seed: int, duration_s: float, rounds: int) -> str:
    """The alarm's share of the tracker's CPU, side by side (see the module's docstring)."""
    rec, _ = simulate(arm, "daily-use", duration_s, seed=seed)
    runs: dict[str, list[float]] = {"alarm": [], "silent": []}
    live: dict[str, list[float]] = {"alarm": [], "silent": []}
    raised = 0
    for r in range(-1, rounds):  # round -1 warms up (compiled kernels, caches) and is not kept
        for name in (("alarm", "silent") if r % 2 else ("silent", "alarm")):  # ABBA: no order bias
            tr, start = start_from_recording(arm, rec)
            if name == "silent":
                tr.alarm = SilentAlarm()
            c0 = time.process_time()
            tr.run(rec)
            if r >= 0:
                runs[name].append(time.process_time() - c0)
            raised = len(tr.alarm.raised) if name == "alarm" else raised
            # the live path: the same instants one at a time, as serve feeds them
            tr2, _ = start_from_recording(arm, rec)
            if name == "silent":
                tr2.alarm = SilentAlarm()
            takes = set(tr2.sensor_names) | {"imu_temp"}  # what serve hands it
            instants = _instants(rec, tr2.t_s, 1500)
            c0 = time.process_time()
            for t, samples in instants:
                tr2.update_instant(t, {k: v for k, v in samples.items() if k in takes})
            if r >= 0:
                live[name].append((time.process_time() - c0) / len(instants) * 1e3)
    best = {k: min(v) for k, v in runs.items()}
    med = {k: float(np.median(v)) for k, v in runs.items()}
    lbest = {k: min(v) for k, v in live.items()}
    return "\n".join([
        "## What the model-change alarm costs (`tools/bench_alarm.py --cost`)", "",
        f"One {duration_s:.0f} s `daily-use` recording of the calibrated WMRA (seed {seed}; the alarm "
        f"raised {raised} alarms on it), tracked {rounds} times with the alarm and {rounds} times with a "
        "tracker whose alarm listens for nothing (`SilentAlarm`), alternating (ABBA, after one "
        "untimed run of each), in one process; "
        f"{machine_line()}. CPU time; ratios are what count on a shared machine.", "",
        "| | with the alarm | without | ratio |",
        "| --- | ---: | ---: | ---: |",
        f"| whole recording, CPU s (best / median of {rounds}) | {best['alarm']:.2f} / {med['alarm']:.2f} | "
        f"{best['silent']:.2f} / {med['silent']:.2f} | {best['alarm'] / best['silent']:.3f} / "
        f"{med['alarm'] / med['silent']:.3f} |",
        f"| live step (`update_instant`, 1,500 instants after the start), ms (best of {rounds}) | "
        f"{lbest['alarm']:.3f} | {lbest['silent']:.3f} | {lbest['alarm'] / lbest['silent']:.3f} |",
    ])


def _instants(rec: Recording, t_from: float, n: int):
    """The first ``n`` instants of ``rec`` after ``t_from``: ``(t, {stream: values})``, every
    stream's samples at the same time together (the recording's streams share a clock)."""
    from armfusion.fusion.service.reorder import Reorder

    reorder = Reorder(0.0)
    for s in rec.raw().values():
        part = s.between(t_from + 1e-9, t_from + 2.0 * n / (s.rate_hz or 100.0))
        if len(part):
            reorder.push(part)
    return reorder.release(flush=True)[:n]


_ARM: list = []


def _work(job: tuple) -> dict:
    """One recording, in a worker: ``("inject", kind, seed, args)`` or ``("clean", i, args)``."""
    if not _ARM:
        _ARM.append(calibrated_wmra())
    c0 = time.process_time()
    if job[0] == "inject":
        out = trial(_ARM[0], job[1], job[2], job[3].duration, job[3])
    else:
        out = clean(_ARM[0], job[1], job[2].clean_duration, job[2].seed)
    out["cpu_s"] = time.process_time() - c0
    return out


def poisson_interval(k: int, exposure: float) -> tuple[float, float]:
    """The exact (Garwood) 95 % interval on a rate of ``k`` events in ``exposure``."""
    lo = 0.5 * float(chi2.ppf(0.025, 2 * k)) if k > 0 else 0.0
    return lo / exposure, 0.5 * float(chi2.ppf(0.975, 2 * k + 2)) / exposure


def _pct(k: int, n: int) -> str:
    if n == 0:
        return "–"
    lo, hi = wilson(k, n)
    return f"{k}/{n} ({100 * k / n:.0f} %; {100 * lo:.0f}–{100 * hi:.0f} %)"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=40, help="injections of each kind")
    ap.add_argument("--clean-hours", type=float, default=100.0)
    ap.add_argument("--clean-wall-s", type=float,
                    help="start no clean recording after this much wall time (s)")
    ap.add_argument("--duration", type=float, default=180.0, help="each injected recording, s")
    ap.add_argument("--clean-duration", type=float, default=1800.0, help="each clean recording, s")
    ap.add_argument("--within-s", type=float, default=30.0)
    ap.add_argument("--mount-deg", type=float, default=2.0)
    ap.add_argument("--bias-g", type=float, default=0.05)
    ap.add_argument("--iron-ut", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--seeds", help="only these trial seeds (comma-separated), for each of --kinds")
    ap.add_argument("--kinds", default=",".join(KINDS), help="the changes to inject (comma-separated)")
    ap.add_argument("--jobs", type=int, default=1, help="recordings at once, each in its own process")
    ap.add_argument("--quick", action="store_true", help="3 injections of each kind, 0.5 clean hour")
    ap.add_argument("--out", type=Path, help="write the table (Markdown) here")
    ap.add_argument("--cost", action="store_true", help="measure the alarm's CPU cost instead (see above)")
    ap.add_argument("--rounds", type=int, default=5, help="--cost: runs of each")
    ap.add_argument("--cost-duration", type=float, default=300.0, help="--cost: the recording, s")
    a = ap.parse_args(argv)
    if a.cost:
        if a.rounds < 1 or a.cost_duration <= 0:
            ap.error("--rounds >= 1 and --cost-duration > 0")
        table = cost(calibrated_wmra(), a.seed, a.cost_duration, a.rounds)
        print(table)
        publish("bench_alarm_cost", table, a.out, a.quick)
        return 0
    if a.quick:
        a.trials, a.clean_hours = 3, 0.5
    kinds = a.kinds.split(",")
    bad = [k for k in kinds if k not in KINDS]
    if bad or a.jobs < 1 or a.trials < 0 or a.clean_hours < 0 or min(a.duration, a.clean_duration) <= 0:
        ap.error(f"--kinds: one or more of {', '.join(KINDS)} (got {', '.join(bad)[:60]!r}); --jobs >= 1; "
                 "--trials and --clean-hours >= 0; durations > 0")
    try:
        seeds = None if a.seeds is None else [int(x) for x in a.seeds.split(",")]
    except ValueError:
        ap.error(f"--seeds: comma-separated integers, not {a.seeds[:40]!r}")
    c0, w0 = time.process_time(), time.perf_counter()
    jobs = [("inject", kind, s, a) for kind in kinds
            for s in (seeds if seeds is not None else
                      [a.seed + 7919 * KINDS.index(kind) + i for i in range(a.trials)])]
    n_clean = int(np.ceil(a.clean_hours * 3600.0 / a.clean_duration - 1e-9))
    jobs += [("clean", i, a) for i in range(n_clean)]
    res: list[dict] = []
    stopped = 0

    def report(job, r) -> None:
        res.append(r)
        if job[0] == "inject":
            print(f"{r['kind']} seed {r['seed']} {r['sensor']} at {r['t0']:.1f} s "
                  f"(visible {r['visible']:.2f}): "
                  f"{'detected' if r['detected'] else 'MISSED'}, {'named' if r['named'] else 'not named'}"
                  f" -> {r['got']} [{r['cpu_s']:.0f} s]", flush=True)
        else:
            print(f"clean {r['i'] + 1}/{n_clean}: {len(r['got'])} alarms {r['got']} [{r['cpu_s']:.0f} s]",
                  flush=True)

    def budget_left(job) -> bool:
        return job[0] != "clean" or a.clean_wall_s is None or time.perf_counter() - w0 < a.clean_wall_s

    if a.jobs == 1:
        for job in jobs:
            if not budget_left(job):
                stopped += 1
                continue
            report(job, _work(job))
    else:
        # the pool is fed as it works, so that clean recordings stop with the wall budget
        with ProcessPoolExecutor(a.jobs, mp_context=multiprocessing.get_context("fork")) as pool:
            todo, running = list(jobs), {}
            while todo or running:
                while todo and len(running) < a.jobs:
                    job = todo.pop(0)
                    if budget_left(job):
                        running[pool.submit(_work, job)] = job
                    else:
                        stopped += 1
                if running:
                    done, _ = wait(running, return_when=FIRST_COMPLETED)
                    for fut in done:
                        report(running.pop(fut), fut.result())
    cpu = time.process_time() - c0 + (sum(r["cpu_s"] for r in res) if a.jobs > 1 else 0.0)
    wall = time.perf_counter() - w0
    rows = []
    for kind in kinds:
        rk = [r for r in res if r.get("kind") == kind]
        if not rk:
            continue
        n = len(rk)
        det, nam, end = (sum(r[k] for r in rk) for k in ("detected", "named", "named_by_end"))
        delays = [r["delay_s"] for r in rk if r["delay_s"] is not None]
        sz = [r["size"] for r in rk if r["size"] is not None]
        sg = [r["sigma"] for r in rk if r["sigma"] is not None]
        med = [float(np.median(v)) if v else float("nan") for v in (delays, sz, sg)]
        rows.append((kind, n, det, nam, end, *med, sum(r["elsewhere"] for r in rk),
                     sum(r["false_before"] for r in rk)))
    cl = [r for r in res if "i" in r]
    hours = sum(r["duration_s"] for r in cl) / 3600.0
    false = sum(len(r["got"]) for r in cl)
    units = {"mount_rotation": f"{a.mount_deg} deg", "bias_jump": f"{a.bias_g} g",
             "hard_iron": f"{a.iron_ut} uT"}
    short = [f"{n} {kind}" for kind, n, *_ in rows if n < 40]
    short += [f"{hours:.1f} clean hours"] if hours < 100 else []
    run = "this run meets both counts" if not short else "this run has fewer: " + ", ".join(short)
    lines = ["## The online model-change alarm (`tools/bench_alarm.py`)", "",
             f"The calibrated WMRA in `daily-use` ({a.duration:.0f} s each, a different seed each), one "
             f"change injected at a random time into the raw streams of a random sensor; {machine_line()}. "
             f"Targets: a 2° mount change found within {a.within_s:.0f} s in ≥ 95 %, named right in ≥ 90 %; "
             f"false alarms ≤ 1 per 20 h over ≥ 100 clean hours, and ≥ 40 injections of each kind "
             f"({run}). *Named* counts an alarm on the right sensor whose effect was decided, and "
             f"right, within {a.within_s:.0f} s of the change; an alarm that still names two "
             "candidate effects (the motion has not told them apart yet) is not named. Rates with "
             "their Wilson 95 % interval.", "",
             f"| change | injected | size | detected within {a.within_s:.0f} s | "
             f"named within {a.within_s:.0f} s | "
             "named by the recording's end | median delay s | median size found (sigma) | "
             "alarms on another sensor after the change |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for kind, n, det, nam, end, dl, sz, sg, other, _ in rows:
        lines.append(f"| {kind} | {n} | {units[kind]} | {_pct(det, n)} | {_pct(nam, n)} | {_pct(end, n)} | "
                     f"{dl:.1f} | {sz:.4g} ({sg:.3g}) | {other} |")
    lines.append("")
    if hours > 0:
        lo, hi = poisson_interval(false, hours / 20.0)
        cut = f"; {stopped} not started, past --clean-wall-s" if stopped else ""
        lines.append(f"Clean: {false} alarms in {hours:.1f} simulated hours ({len(cl)} recordings of "
                     f"{a.clean_duration:.0f} s{cut}): "
                     f"{false / hours * 20.0:.2f} per 20 h (exact Poisson 95 % interval {lo:.2f}–{hi:.2f}).")
    lines.append(f"Alarms before an injection: {sum(r[-1] for r in rows)}. CPU {cpu:.0f} s, "
                 f"wall {wall:.0f} s (--jobs {a.jobs}).")
    table = "\n".join(lines)
    print(table)
    publish("bench_alarm", table, a.out, a.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
