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

Leave one trial out: one constant of ``broad_imu`` is chosen from the recordings, the
magnetometer's ``delay_s`` (the gyroscope's plus the median of the trials' compass lags,
:func:`compass_lag_s`, found from the IMU's own readings without the reference). With three
trials or more the tool chooses it again on all trials but one, scores armfusion on that
one with it, for each trial, and prints that table and its targets beside the in-sample
one (a fold that chooses the shipped value reuses the in-sample run).

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


# ------------------------------------------------------------------------------------ the compass's lag
LAG_GRID_S = np.arange(0.0, 0.030 + 1e-9, 0.00025)
"""The compass's lag behind the gyro tried by :func:`compass_lag_s`: 0-30 ms in 0.25 ms."""
SMOOTH_S = 0.05
"""The derivative's window (Savitzky-Golay, quadratic): 50 ms, shorter than a hand's turn."""


def compass_lag_s(trial: Trial) -> float:
    """How far the magnetometer's readings lag the gyro's, s, from the IMU's own readings (no
    reference): while the sensor turns, a field fixed in the world changes in its axes as
    ``dm/dt = -ω × m``, so a compass ``d`` late changes as ``-ω(t - d) × m(t)``; the lag is
    the ``d``, on :data:`LAG_GRID_S`, at which that prediction (both sides smoothed alike
    over :data:`SMOOTH_S`) best matches the compass's change over the ``movement`` samples."""
    from scipy.signal import savgol_filter

    r = trial.rate_hz
    win = max(5, int(round(SMOOTH_S * r)) | 1)
    m = np.asarray(trial.mag_ut, float)
    dm = savgol_filter(m, win, 2, deriv=1, axis=0) * r
    mv = np.asarray(trial.movement, bool)
    if not mv.any():
        return 0.0
    i = np.arange(len(m), dtype=float)
    cost = []
    for d in LAG_GRID_S:
        w = np.column_stack([np.interp(i - d * r, i, trial.gyr_rad_s[:, k]) for k in range(3)])
        pred = savgol_filter(-np.cross(w, m), win, 2, axis=0)
        cost.append(float(np.mean((dm[mv] - pred[mv]) ** 2)))
    return float(LAG_GRID_S[int(np.argmin(cost))])


def chosen_lag_s(lags: list[float]) -> float:
    """The compass's lag one parameter set takes from trials' lags: their median, on the grid."""
    m = float(np.median(lags))
    return float(LAG_GRID_S[int(np.argmin(np.abs(LAG_GRID_S - m)))])


def sensor_delays_s(config: str) -> tuple[float, float]:
    """``config``'s gyroscope and magnetometer ``delay_s`` (its IMU's description)."""
    from armfusion.fusion.configfile import read_yaml, resolve_config_path

    data = read_yaml(resolve_config_path(config))
    out = next(s for s in data["sensors"] if s.get("kind") == "imu")["outputs"]
    return float(out["gyroscope"].get("delay_s", 0.0)), float(out["magnetometer"].get("delay_s", 0.0))


def config_with_compass_delay(config: str, delay_s: float, folder: Path) -> Path:
    """``config`` with its magnetometer's ``delay_s`` set to ``delay_s``, written into ``folder``."""
    import yaml
    from armfusion.fusion.configfile import read_yaml, resolve_config_path

    data = read_yaml(resolve_config_path(config))
    next(s for s in data["sensors"] if s.get("kind") == "imu")["outputs"]["magnetometer"]["delay_s"] = \
        float(delay_s)
    path = folder / f"{Path(config).stem}_compass_{delay_s * 1e6:.0f}us.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


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


@dataclass(frozen=True)
class LooResult:
    """armfusion on one trial with the compass's delay chosen on the other trials."""

    trial: str
    compass_delay_s: float
    scores: Scores
    within_3sigma: float


def _loo_of(row: TrialResult, delay_s: float) -> LooResult:
    """An in-sample row taken as the leave-one-out one (its fold chose the shipped delay)."""
    return LooResult(row.trial, delay_s, row.results["armfusion"].scores, row.within_3sigma)


def _run_loo(job: tuple[Path, str, float]) -> LooResult:
    """armfusion alone on a trial with ``config`` (its fold's compass delay ``delay_s``)."""
    path, config, delay_s = job
    trial = read_trial(path)
    af = run_armfusion(trial, config)
    sc, ok, heading = scores(af.q_enu, trial.opt_quat, trial.movement)
    inside = heading[ok] <= 3.0 * af.heading_sigma_rad[ok]
    return LooResult(trial.name, delay_s, sc, float(inside.mean()) if inside.size else float("nan"))


def leave_one_out(paths: list[Path], rows: list[TrialResult], jobs: int, folder: Path
                  ) -> tuple[list[float], float, list[LooResult]]:
    """The one constant chosen from these trials, the compass's delay (the gyro's delay plus
    the median of the trials' :func:`compass_lag_s`), chosen on all trials but one and
    armfusion scored on that one, for each: the trials' lags (s), the delay chosen on all of
    them (s), and the leave-one-out results (a fold that chooses the shipped delay reuses
    the in-sample run)."""
    lags = [compass_lag_s(read_trial(p)) for p in paths]
    gyro_s, shipped_s = sensor_delays_s(CONFIG)
    folds = [gyro_s + chosen_lag_s(lags[:k] + lags[k + 1:]) for k in range(len(paths))]
    out: list[LooResult | None] = [None] * len(paths)
    todo = []
    for k, d in enumerate(folds):
        if abs(d - shipped_s) < 1e-9:
            out[k] = _loo_of(rows[k], d)
        else:
            todo.append((k, (paths[k], str(config_with_compass_delay(CONFIG, d, folder)), d)))
    if jobs > 1 and len(todo) > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=min(jobs, len(todo))) as pool:
            done = list(pool.map(_run_loo, [j for _, j in todo]))
    else:
        done = [_run_loo(j) for _, j in todo]
    for (k, _), r in zip(todo, done, strict=True):
        out[k] = r
    return lags, gyro_s + chosen_lag_s(lags), [r for r in out if r is not None]


def loo_md(rows: list[TrialResult], lags: list[float], chosen_s: float, loo: list[LooResult],
           reference: str = "vqf") -> list[str]:
    """The leave-one-trial-out table (armfusion's heading and inclination with the compass's
    delay chosen on the other trials, beside ``reference``'s in the same run) and its targets."""
    shipped_s = sensor_delays_s(CONFIG)[1]
    lines = ["", "### Leave one trial out", "",
             "One constant of `broad_imu` is chosen from these recordings: the magnetometer's "
             "`delay_s`, the gyroscope's plus the median of the trials' compass lags (each "
             "found from the IMU's own readings, no reference: the lag at which the gyro's "
             "turn best predicts the compass's change, `compass_lag_s`). Lags found, ms: "
             + ", ".join(f"{r.trial[:2]} {1e3 * g:.2f}" for r, g in zip(rows, lags, strict=True))
             + f". Chosen on all {len(rows)}: {1e3 * chosen_s:.2f} ms (the config ships "
             f"{1e3 * shipped_s:.2f} ms). Below, each trial scored with the delay chosen on the "
             "other trials (its fold's value in the second column); every other constant is the "
             "config's, from datasheets and physics, chosen on no trial.", "",
             f"| trial | compass delay [ms] | armfusion heading / incl. [deg] | {reference} heading / "
             "incl. [deg] | heading ratio |",
             "| --- | --- | --- | --- | --- |"]
    for r, o in zip(rows, loo, strict=True):
        v = r.results[reference].scores
        lines.append(f"| {r.trial} | {1e3 * o.compass_delay_s:.2f} | {o.scores.heading_deg:.2f} / "
                     f"{o.scores.inclination_deg:.2f} | {v.heading_deg:.2f} / {v.inclination_deg:.2f} | "
                     f"{o.scores.heading_deg / v.heading_deg:.2f} |")
    h = float(np.mean([o.scores.heading_deg for o in loo]))
    i = float(np.mean([o.scores.inclination_deg for o in loo]))
    vh, vi = _mean(rows, reference, "heading_deg"), _mean(rows, reference, "inclination_deg")
    worst = max(o.scores.heading_deg / r.results[reference].scores.heading_deg
                for r, o in zip(rows, loo, strict=True))
    verdict = {True: "met", False: "**not met**"}
    lines += [f"| **mean** | | **{h:.2f} / {i:.2f}** | **{vh:.2f} / {vi:.2f}** | |", "",
              f"Leave one out: armfusion's mean heading {h:.3f} against {reference}'s {vh:.3f} deg "
              f"({h / vh:.2f} times), inclination {i:.3f} against {vi:.3f} deg ({i / vi:.3f} times). "
              f"Targets: mean heading below {reference}'s: {verdict[h < vh]}; mean inclination no "
              f"worse: {verdict[i <= vi]}; no trial's heading above 2 times {reference}'s: "
              f"{verdict[worst <= 2.0]} (worst {worst:.2f} times)."]
    return lines


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


def report_md(rows: list[TrialResult], data: Path, loo_lines: list[str] | None = None) -> str:
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
    lines += loo_lines or []
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
    loo_lines = None
    if len(rows) >= 3:  # a constant chosen on the others needs others
        import tempfile

        with tempfile.TemporaryDirectory() as folder:
            lags, chosen_s, loo = leave_one_out(paths, rows, a.jobs, Path(folder))
        loo_lines = loo_md(rows, lags, chosen_s, loo)
        print("\n".join(loo_lines))
    md = report_md(rows, a.data, loo_lines)
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
