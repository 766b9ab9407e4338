"""BROAD: armfusion's heading and tilt on a real hand-held 9-axis IMU, beside the peers.

For every BROAD trial in ``--data`` (``NN_<name>.hdf5``, the benchmark of Laidig, Caruso,
Cereatti and Seel, Data 6(7), 72, 2021, CC BY 4.0), in one process on the same samples:

- **armfusion**: the trial imported with the shipped map (``config/imports/broad.yaml``)
  onto the IMU-only config ``broad_imu`` (a base IMU and no joints), the startup on its
  first still stretch and the chair's tracker on every sample after it, exactly what
  ``armfusion import`` then ``armfusion track --config broad_imu`` do (its roll, pitch and
  yaw, and the yaw's sigma);
- **vqf** (``vqf.VQF(Ts)``, its defaults, ``updateBatch`` -> ``quat9D``),
  **imufusion** (x-io's Fusion: ``imufusion.Ahrs()`` with its defaults, ``update`` with the
  magnetometer every sample) and **ahrs Madgwick** (``ahrs.filters.Madgwick``, its default
  gain, batch mode with the magnetometer): one parameter set for every trial, none tuned.

Errors, as the benchmark defines them (its README, ``example_code/broad_utils.py``): with
``q_e = q_imu ⊗ q_opt⁻¹`` (both unit, w x y z; the error in the world frame), the total
error is the rotation angle of ``q_e``, the heading error ``2·atan(|z_e / w_e|)``, the
inclination error ``2·acos(sqrt(w_e² + z_e²))``; RMSE over the samples where ``movement``
is true and the optical reference is finite (the NaN reference samples are counted and
left out).

The alignment of the filters' worlds to the optical one, the same for every filter and
every trial: BROAD's reference (``opt_quat``) is given in an ENU frame that its authors
aligned to the IMU's magnetic world (x east, y magnetic north, z up); its evaluation turns
a filter's world into that frame by a fixed rotation only (its Madgwick and Mahony, whose
world is x north, y west, z up, are pre-multiplied by a +90 deg turn about z). Here too:
vqf's world is already ENU; imufusion's (its NWU convention), ahrs Madgwick's and
armfusion's (x magnetic north, z up, ``R_WB = Rz(yaw) Ry(pitch) Rx(roll)``) are turned by
``Q_ENU_FROM_NWU``. Nothing is fitted to a trial; the table lists each filter's median
heading offset to the reference on the still stretch before the motion as a check of
that alignment.

The 3-sigma share: armfusion's heading error against three times its own heading sigma,
the share of scored samples inside, reported for every trial (the issue's target is on the
magnetic-disturbance trials, the ones whose name says ``magnet``).

    python tools/bench_heading_broad.py [--data DIR] [--no-write] [--json OUT] [--jobs N]

needs the optional ``[bench]`` extra (``pip install -e '.[bench]'``) and ``h5py``. Without
``--no-write`` it rewrites its section of docs/benchmarks.md.
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from importlib.metadata import version  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.models.rotations import GRAVITY_MPS2  # noqa: E402

from tools.rig_peers import _qconj, _qmul  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "broad"
CONFIG = "broad_imu"
MAX_TRIAL_BYTES = 200_000_000
"""A BROAD trial is 3-5 MB; a file far larger is not one (refused before it is read)."""
Q_ENU_FROM_NWU = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
"""The world x north, y west, z up turned into x east, y north, z up: +90 deg about z."""
MAGNETIC = "magnet"
"""A trial whose name says this is one of the benchmark's magnetic-disturbance trials."""


# ------------------------------------------------------------------------------------ a trial
@dataclass(frozen=True)
class Trial:
    """One BROAD trial: its samples (``(N, 3)`` each), the reference orientation ``(N, 4)``
    (w x y z, ENU; NaN where the markers were not seen) and ``movement (N,)``."""

    name: str
    path: Path
    rate_hz: float
    acc_mps2: np.ndarray
    gyr_rad_s: np.ndarray
    mag_ut: np.ndarray
    opt_quat: np.ndarray
    movement: np.ndarray


def read_trial(path: Path) -> Trial:
    """A BROAD HDF5 trial, checked where it enters (datasets, shapes, rate)."""
    import h5py

    path = Path(path)
    size = path.stat().st_size
    if size > MAX_TRIAL_BYTES:
        raise ValueError(f"{path.name}: {size} bytes is more than a BROAD trial may be ({MAX_TRIAL_BYTES})")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path.name}: not a readable HDF5 file ({str(e)[:60]})") from None
    with f:
        missing = [k for k in ("imu_acc", "imu_gyr", "imu_mag", "opt_quat", "movement") if k not in f]
        if missing:
            raise ValueError(f"{path.name}: not a BROAD trial, it lacks {', '.join(missing)}")
        rate = f.attrs.get("sampling_rate")
        if rate is None or not np.isfinite(float(rate)) or not float(rate) > 0:
            raise ValueError(f"{path.name}: no positive attribute sampling_rate (got {str(rate)[:30]})")
        data = {k: np.asarray(f[k][()], float) for k in ("imu_acc", "imu_gyr", "imu_mag", "opt_quat")}
        movement = np.asarray(f["movement"][()]).astype(bool).reshape(-1)
    n = len(movement)
    for k, v in data.items():
        want = (n, 4) if k == "opt_quat" else (n, 3)
        if v.shape != want:
            raise ValueError(f"{path.name}: {k} has shape {v.shape}, expected {want} (one row per sample)")
    return Trial(path.stem, path, float(rate), data["imu_acc"], data["imu_gyr"], data["imu_mag"],
                 data["opt_quat"], movement)


# ------------------------------------------------------------------------------------ the errors
def error_quaternion(q_imu: np.ndarray, q_opt: np.ndarray) -> np.ndarray:
    """``q_e = q_imu ⊗ q_opt⁻¹`` (both normalised first), unit, ``(N, 4)``: the estimate's
    error expressed in the world frame."""
    a = np.asarray(q_imu, float)
    b = np.asarray(q_opt, float)
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    e = _qmul(a, _qconj(b))
    return e / np.linalg.norm(e, axis=1, keepdims=True)


def errors_rad(q_imu: np.ndarray, q_opt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sample, BROAD's total, heading and inclination errors, rad ``(N,)`` each."""
    e = error_quaternion(q_imu, q_opt)
    w, z = e[:, 0], e[:, 3]
    total = 2.0 * np.arccos(np.clip(np.abs(w), 0.0, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        heading = 2.0 * np.arctan(np.abs(z / w))
    inclination = 2.0 * np.arccos(np.clip(np.sqrt(w**2 + z**2), 0.0, 1.0))
    return total, heading, inclination


@dataclass(frozen=True)
class Scores:
    """RMSE over the scored samples (``movement`` and a finite reference and estimate), deg;
    ``scored``, ``nan_reference`` (movement samples with no optical reference, left out),
    ``no_estimate`` (movement samples the filter gave nothing for, left out)."""

    heading_deg: float
    inclination_deg: float
    total_deg: float
    scored: int
    nan_reference: int
    no_estimate: int


def scores(q_imu: np.ndarray, q_opt: np.ndarray,
           movement: np.ndarray) -> tuple[Scores, np.ndarray, np.ndarray]:
    """The benchmark's RMSEs of ``q_imu`` against ``q_opt`` over ``movement``; also the scored
    mask and the heading error (rad) per sample."""
    mv = np.asarray(movement, bool)
    ref_ok = np.all(np.isfinite(q_opt), axis=1)
    est_ok = np.all(np.isfinite(q_imu), axis=1)
    ok = mv & ref_ok & est_ok
    safe_imu = np.where(est_ok[:, None], q_imu, [1.0, 0.0, 0.0, 0.0])
    safe_opt = np.where(ref_ok[:, None], q_opt, [1.0, 0.0, 0.0, 0.0])
    total, heading, inclination = errors_rad(safe_imu, safe_opt)

    def rmse(x: np.ndarray) -> float:
        return float(np.degrees(np.sqrt(np.mean(x[ok] ** 2)))) if ok.any() else float("nan")

    return (Scores(rmse(heading), rmse(inclination), rmse(total), int(ok.sum()), int((mv & ~ref_ok).sum()),
                   int((mv & ref_ok & ~est_ok).sum())), ok, heading)


def still_heading_offset_deg(q_imu: np.ndarray, q_opt: np.ndarray, movement: np.ndarray) -> float:
    """The median signed heading offset (deg) of the estimate to the reference over the
    samples before the first movement sample (the trial's still start): a check of the
    alignment, not used to align."""
    mv = np.asarray(movement, bool)
    first = int(np.argmax(mv)) if mv.any() else len(mv)
    ok = np.zeros(len(mv), bool)
    ok[:first] = True
    ok &= np.all(np.isfinite(q_opt), axis=1) & np.all(np.isfinite(q_imu), axis=1)
    if not ok.any():
        return float("nan")
    e = error_quaternion(q_imu[ok], q_opt[ok])
    return float(np.degrees(np.median(np.angle(np.exp(2j * np.arctan2(e[:, 3], e[:, 0]))))))


# ------------------------------------------------------------------------------------ frames
def enu_from_nwu(q_nwu: np.ndarray) -> np.ndarray:
    """A sensor's orientation in an x north, y west, z up world turned into ENU, ``(N, 4)``."""
    q = np.asarray(q_nwu, float)
    return _qmul(np.broadcast_to(Q_ENU_FROM_NWU, q.shape), q)


def quat_from_rpy(rpy_rad: np.ndarray) -> np.ndarray:
    """``R_WB = Rz(yaw) Ry(pitch) Rx(roll)`` (the recording spec's base attitude) as unit
    quaternions w x y z ``(N, 4)`` from ``(N, 3)`` roll, pitch, yaw; NaN rows stay NaN."""
    r, p, y = (np.asarray(rpy_rad, float)[:, k] / 2.0 for k in range(3))
    z0 = np.zeros_like(r)
    qz = np.column_stack([np.cos(y), z0, z0, np.sin(y)])
    qy = np.column_stack([np.cos(p), z0, np.sin(p), z0])
    qx = np.column_stack([np.cos(r), np.sin(r), z0, z0])
    return _qmul(_qmul(qz, qy), qx)


# ------------------------------------------------------------------------------------ armfusion
@dataclass(frozen=True)
class ArmfusionTrack:
    """armfusion on one trial: ``q_enu (N, 4)`` (NaN before the tracker's start),
    ``heading_sigma_rad (N,)``, the still window the startup used and the run's counters."""

    q_enu: np.ndarray
    heading_sigma_rad: np.ndarray
    start_window_s: tuple[float, float]
    seconds: float
    summary: dict


def run_armfusion(trial: Trial, config: str = CONFIG) -> ArmfusionTrack:
    """The trial through ``armfusion import`` and ``armfusion track``'s own path: the shipped
    BROAD map onto ``config``, the startup on the first still stretch, the tracker after it.
    Each tracked instant is put back on the trial's sample at that time."""
    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.importing.column_map import load_column_map
    from armfusion.fusion.importing.run import import_recording
    from armfusion.fusion.tracking.tracker import start_from_recording

    arm = load_arm(config)
    rec = import_recording(trial.path, load_column_map("broad"), arm, config).recording
    t_wall = time.perf_counter()
    tr, start = start_from_recording(arm, rec)
    run = tr.run(rec)
    seconds = time.perf_counter() - t_wall
    t_samples = rec.get("imu_gyro").t_s
    k = np.searchsorted(t_samples, run.t_s - 1e-9)
    n = len(trial.movement)
    rpy = np.full((n, 3), np.nan)
    sigma = np.full(n, np.nan)
    rpy[k] = run.rpy_rad
    sigma[k] = run.rpy_sigma_rad[:, 2]
    return ArmfusionTrack(enu_from_nwu(quat_from_rpy(rpy)), sigma, (start.t_start_s, start.t_end_s),
                          seconds, run.summary())


# ------------------------------------------------------------------------------------ the peers
# Each peer: (gyroscope rad/s, accelerometer m/s², magnetometer µT, all (N, 3); period s) ->
# the sensor's orientation in ENU, unit quaternions w x y z (N, 4).
PeerFilter = Callable[[np.ndarray, np.ndarray, np.ndarray, float], np.ndarray]


def _vqf(gyr, acc, mag, period_s):
    from vqf import VQF

    out = VQF(period_s).updateBatch(*(np.ascontiguousarray(v, dtype=float) for v in (gyr, acc, mag)))
    return out["quat9D"]  # VQF's world is ENU


def _imufusion(gyr, acc, mag, period_s):
    import imufusion

    ahrs = imufusion.Ahrs()
    ahrs.set_sample_period(period_s)
    gyr_dps, acc_g = np.degrees(gyr), acc / GRAVITY_MPS2
    q = np.empty((len(gyr), 4))
    for i in range(len(q)):
        ahrs.update(gyr_dps[i], acc_g[i], mag[i])
        q[i] = ahrs.get_quaternion()
    return enu_from_nwu(q)  # Fusion's default convention is NWU


def _madgwick(gyr, acc, mag, period_s):
    from ahrs.filters import Madgwick

    q = Madgwick(gyr=np.asarray(gyr, float), acc=np.asarray(acc, float), mag=np.asarray(mag, float),
                 frequency=1.0 / period_s).Q
    return enu_from_nwu(q)  # its earth frame: x magnetic north, z up


PEERS: dict[str, tuple[str, PeerFilter]] = {
    "vqf": ("vqf", _vqf),
    "imufusion": ("imufusion", _imufusion),
    "ahrs Madgwick": ("ahrs", _madgwick),
}
"""The 9-axis peers, by the name they are reported under: (their package, how each runs)."""


# ------------------------------------------------------------------------------------ one trial
@dataclass(frozen=True)
class FilterResult:
    name: str
    library: str
    scores: Scores
    still_offset_deg: float
    seconds: float


@dataclass(frozen=True)
class TrialResult:
    trial: str
    samples: int
    movement: int
    results: dict[str, FilterResult]
    within_3sigma: float
    """armfusion's share of scored samples whose heading error is within 3 of its sigma."""
    heading_sigma_median_deg: float
    start_window_s: tuple[float, float]
    af_summary: dict


def run_trial(trial: Trial, peers: tuple[str, ...] = tuple(PEERS), config: str = CONFIG) -> TrialResult:
    """armfusion and every peer on ``trial``, scored alike."""
    af = run_armfusion(trial, config)
    out: dict[str, FilterResult] = {}
    sc, ok, heading = scores(af.q_enu, trial.opt_quat, trial.movement)
    out["armfusion"] = FilterResult("armfusion", f"armfusion ({config})", sc,
                                    still_heading_offset_deg(af.q_enu, trial.opt_quat, trial.movement),
                                    af.seconds)
    inside = heading[ok] <= 3.0 * af.heading_sigma_rad[ok]
    period_s = 1.0 / trial.rate_hz
    for name in peers:
        package, run = PEERS[name]
        t_wall = time.perf_counter()
        q = run(trial.gyr_rad_s, trial.acc_mps2, trial.mag_ut, period_s)
        seconds = time.perf_counter() - t_wall
        psc, _, _ = scores(q, trial.opt_quat, trial.movement)
        out[name] = FilterResult(name, f"{package} {version(package)}", psc,
                                 still_heading_offset_deg(q, trial.opt_quat, trial.movement), seconds)
    return TrialResult(trial.name, len(trial.movement), int(trial.movement.sum()), out,
                       float(inside.mean()) if inside.size else float("nan"),
                       float(np.degrees(np.median(af.heading_sigma_rad[ok]))) if ok.any() else float("nan"),
                       af.start_window_s, af.summary)


# ------------------------------------------------------------------------------------ the report
def _mean(rows: list[TrialResult], name: str, metric: str) -> float:
    return float(np.mean([getattr(r.results[name].scores, metric) for r in rows]))


def targets_line(rows: list[TrialResult], ours: str = "armfusion", reference: str = "vqf") -> str:
    """The issue's BROAD targets, judged on these trials: the mean heading below every peer's,
    the mean inclination no worse than ``reference``'s, the heading within 3 of its sigma on
    at least 95 % of each magnetic-disturbance trial; with the means to three decimals and
    their ratios (the table's two decimals can hide which is lower)."""
    names = list(rows[0].results)
    peers = [n for n in names if n != ours]
    head = {n: _mean(rows, n, "heading_deg") for n in names}
    inc = {n: _mean(rows, n, "inclination_deg") for n in names}
    magnetic = [r.within_3sigma for r in rows if MAGNETIC in r.trial]
    if reference not in names:
        return f"{ours} ran without {reference}: its targets are not judged."
    verdict = {True: "met", False: "**not met**"}
    parts = [f"{ours}'s means against {reference}'s: heading {head[ours]:.3f} against "
             f"{head[reference]:.3f} deg ({head[ours] / head[reference]:.2f} times), inclination "
             f"{inc[ours]:.3f} against {inc[reference]:.3f} deg ({inc[ours] / inc[reference]:.3f} times).",
             f"Targets: mean heading below every peer's: "
             f"{verdict[all(head[ours] < head[n] for n in peers)]}; mean inclination no worse "
             f"than {reference}'s: {verdict[inc[ours] <= inc[reference]]}; heading within 3 sigma "
             f"on at least 95 % of each magnetic-disturbance trial: "
             + (verdict[min(magnetic) >= 0.95] if magnetic else "no such trial here") + "."]
    return " ".join(parts)


def headline_rows(rows: list[TrialResult], ours: str = "armfusion", reference: str = "vqf") -> list[dict]:
    """The README's rows: the mean heading and inclination over the trials, against
    ``reference`` in the same run."""
    out = []
    for metric, words in (("heading_deg", "heading"), ("inclination_deg", "inclination")):
        mine = _mean(rows, ours, metric)
        theirs = f"{reference} {_mean(rows, reference, metric):.2f}°" if reference in rows[0].results else ""
        out.append({"what": f"BROAD, a real hand-held IMU ({len(rows)} trials, one parameter set, "
                            f"in sample): mean {words} RMSE",
                    "armfusion": f"{mine:.2f}°", "baseline": theirs})
    return out


def report_md(rows: list[TrialResult], data: Path) -> str:
    """The docs/benchmarks.md section: per trial and filter, the three RMSEs; the means."""
    from tools.benchdoc import machine_line

    names = list(rows[0].results)
    libs = ", ".join(rows[0].results[n].library for n in names)
    lines = [
        "## BROAD: heading and inclination on a real hand-held IMU (`tools/bench_heading_broad.py`)",
        "",
        f"{len(rows)} trials of BROAD (Laidig, Caruso, Cereatti, Seel 2021, CC BY 4.0) from "
        f"`{data.name}/`; armfusion is the IMU-only config `{CONFIG}` through `import` and `track` "
        "(the chair's own tilt and heading code), beside the peers with their defaults, in the same "
        f"process on the same samples ({libs}). One parameter set for every trial. Errors as the "
        "benchmark defines them (RMSE over `movement`, NaN reference samples left out); every "
        "filter's world turned into the reference's ENU by a fixed turn only (the benchmark's own "
        "alignment: the tool's docstring).",
        "",
        "| trial | scored (NaN ref.) | "
        + " | ".join(f"{n} heading / incl. / total [deg]" for n in names) + " |",
        "| --- | --- | " + " | ".join("---" for _ in names) + " |",
    ]
    for r in rows:
        sc = r.results[names[0]].scores
        cells = [f"{r.results[n].scores.heading_deg:.2f} / {r.results[n].scores.inclination_deg:.2f} / "
                 f"{r.results[n].scores.total_deg:.2f}" for n in names]
        lines.append(f"| {r.trial} | {sc.scored:,} ({sc.nan_reference:,}) | " + " | ".join(cells) + " |")
    cells = [f"**{_mean(rows, n, 'heading_deg'):.2f} / {_mean(rows, n, 'inclination_deg'):.2f} / "
             f"{_mean(rows, n, 'total_deg'):.2f}**" for n in names]
    lines.append("| mean | | " + " | ".join(cells) + " |")
    lines += ["", targets_line(rows)]
    lines += ["", "Alignment check: each filter's median heading offset to the reference on the still "
              "start before the motion, deg (not used to align): "
              + "; ".join(f"{r.trial[:2]}: " + ", ".join(f"{n} {r.results[n].still_offset_deg:+.1f}"
                                                          for n in names) for r in rows) + ".", ""]
    lines.append("armfusion's heading within 3 of its own sigma (share of scored samples; median sigma):")
    lines.append("")
    for r in rows:
        tag = " (magnetic disturbance)" if MAGNETIC in r.trial else ""
        lines.append(f"- {r.trial}{tag}: {100 * r.within_3sigma:.1f} % "
                     f"(sigma {r.heading_sigma_median_deg:.2f} deg)")
    lines += ["", f"Machine: {machine_line()}."]
    return "\n".join(lines)


def _run_path(path: Path) -> TrialResult:
    """One trial read and run (a worker's task: :func:`main`'s ``--jobs``)."""
    return run_trial(read_trial(path))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of BROAD .hdf5 trials")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    ap.add_argument("--jobs", type=int, default=1,
                    help="trials run at once, each in its own process (its timings then share the cores)")
    a = ap.parse_args(argv)
    if a.jobs < 1:
        print(f"error: --jobs {a.jobs}: must be 1 or more", file=sys.stderr)
        return 2
    if not a.data.is_dir():
        print(f"error: --data {str(a.data)[:80]}: no such folder", file=sys.stderr)
        return 2
    paths = sorted(a.data.glob("*.hdf5"))
    if not paths:
        print(f"error: --data {str(a.data)[:80]}: no .hdf5 trial in it", file=sys.stderr)
        return 2
    for path in paths:  # every trial checked before any runs
        try:
            read_trial(path)
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    rows = []
    if a.jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(max_workers=min(a.jobs, len(paths)))
        results = pool.map(_run_path, paths)
    else:
        pool, results = None, map(_run_path, paths)
    for r in results:
        rows.append(r)
        print(f"{r.trial}: {r.samples:,} samples, {r.movement:,} in movement; armfusion started on "
              f"{r.start_window_s[0]:.1f}..{r.start_window_s[1]:.1f} s", flush=True)
        for f in r.results.values():
            s = f.scores
            print(f"  {f.name:14s} heading {s.heading_deg:6.2f}  incl. {s.inclination_deg:6.2f}  total "
                  f"{s.total_deg:6.2f} deg  ({s.scored:,} scored, {s.nan_reference:,} NaN ref., "
                  f"{s.no_estimate} no estimate; still offset {f.still_offset_deg:+.1f} deg; "
                  f"{f.seconds:.1f} s)",
                  flush=True)
        print(f"  armfusion heading within 3 sigma: {100 * r.within_3sigma:.1f} % "
              f"(median sigma {r.heading_sigma_median_deg:.2f} deg)", flush=True)
    if pool is not None:
        pool.shutdown()
    for n in rows[0].results:
        print(f"mean {n:14s} heading {_mean(rows, n, 'heading_deg'):6.2f}  incl. "
              f"{_mean(rows, n, 'inclination_deg'):6.2f}  total {_mean(rows, n, 'total_deg'):6.2f} deg")
    print(targets_line(rows))
    md = report_md(rows, a.data)
    if a.json is not None:
        a.json.write_text(json.dumps({r.trial: {
            "samples": r.samples, "movement": r.movement, "within_3sigma": r.within_3sigma,
            "heading_sigma_median_deg": r.heading_sigma_median_deg,
            "filters": {f.name: {"library": f.library, **f.scores.__dict__,
                                 "still_offset_deg": f.still_offset_deg, "seconds": f.seconds}
                        for f in r.results.values()}} for r in rows}, indent=1) + "\n")
    if a.no_write:
        print(md)
    else:
        from tools.benchdoc import record_headline, write_section

        print(f"wrote {write_section('bench_heading_broad', md)}")
        record_headline("bench_heading_broad", headline_rows(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
