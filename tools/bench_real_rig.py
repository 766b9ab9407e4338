"""Real recordings: the one-joint IMU rig of Song, Pei and Hsiao-Wecksler (2022) through
armfusion's import, workbench and tracker, trial by trial.

Every ``*.mat`` trial of the data folder (default ``../shared/data/imu-rig``) is treated as
a user's recording never seen before (nothing here knows a file by its name):

1. **Import** with the shipped column map ``imu-rig`` (values in g and °/s, encoder in deg).
2. **Which set-up**: the three rig configs (shaft horizontal along the frame IMU's x or y,
   or vertical) are each fitted to the trial's first minute; the one whose model fits best
   (the lowest ratio of residual to noise) is the trial's. (The file's name is printed
   beside it as a check only.)
3. **The error ladder** on the calibration stretch (the first ``--calibrate-s``): the
   workbench's fit and ranking (`armfusion diagnose`), the most significant missing effect
   added and the model refitted, again and again until nothing significant is left (or
   ``--rungs``); each rung with what it added, its estimate ± σ and the fit's RMS over the
   noise. The floor the target refers to is the noise model's: the MPU-6050's datasheet
   density over half the rate and the 0.01 rounding of the stored values.
4. **Tracking** the rest of the trial (never seen by the calibration) with the calibrated
   config, the encoder as the joint's relative encoder (its zero unknown to the tracker,
   which starts afresh, on a moving shaft): the angle's error against the encoder and the
   calibration's zero (what the ladder's fit made of the encoder's zero on this power-up,
   with its σ) over time, within 3σ, and the joint's flags.

5. **The encoder withheld**: the scored stretch again, the joint's relative angle from the
   integral of the shaft's gyro less the frame's about the shaft's axis, each read when its
   samples were true (:mod:`armfusion.fusion.tracking.gyro_encoder`, as ``track --encoder-withheld``
   does: its scale, taps, bias and drift calibrated on the calibration stretch, the drift the
   joint's random walk in the tracker), beside the peer filters of the package index
   (`tools/rig_peers.py`: vqf, imufusion, ahrs) on the same samples, their zero aligned on
   the same calibration stretch.

Each trial's stages are guarded: a stage that fails (an unreadable file, a start with no
usable instant, …) is reported in the trial's row and section, the stages that needed it
are marked not run, and the bench goes on to the next trial, so that ``--data DIR`` runs
every trial of any folder to the end.

Writes its section of docs/benchmarks.md and docs/real-data.md.

    python tools/bench_real_rig.py [--data DIR] [--calibrate-s 300] [--rungs 10] [--jobs 2] [--no-write]
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.fusion.configfile import load_arm, resolve_config_path  # noqa: E402
from armfusion.fusion.identification.calibrated_config import config_with_estimates  # noqa: E402
from armfusion.fusion.identification.identify import data_from_recording  # noqa: E402
from armfusion.fusion.importing.column_map import load_column_map  # noqa: E402
from armfusion.fusion.importing.run import import_recording  # noqa: E402
from armfusion.fusion.tracking.calibrated import config_model, device_time_offsets  # noqa: E402
from armfusion.fusion.tracking.gyro_encoder import (  # noqa: E402
    RESPONSE_SPAN_S,
    calibrate_gyro_encoder,
    settings_with_gyro_encoder,
    with_gyro_encoder,
)
from armfusion.fusion.tracking.settings import JOINT_FLAGS, TrackerSettings  # noqa: E402
from armfusion.fusion.tracking.start import StartOptions, start_from_recording  # noqa: E402
from armfusion.fusion.workbench.discover import DiscoverSettings, Discovery, Rung, discover  # noqa: E402
from armfusion.models.effects import model_from_arm  # noqa: E402
from armfusion.models.rotations import wrap_angle  # noqa: E402
from armfusion.sensors.samples import Recording  # noqa: E402

from tools.benchdoc import machine_line, record_headline, write_section  # noqa: E402
from tools.rig_configs import RIG_CONFIGS, WINDOW, choose_config  # noqa: E402
from tools.rig_peers import peer_joint_angles  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "imu-rig"
REAL_DATA_DOC = ROOT / "docs" / "real-data.md"
CITATION = ("S. Y. Song, Y. Pei, E. T. Hsiao-Wecksler, \"Estimating Relative Angles Using Two Inertial "
            "Measurement Units Without Magnetometers\", IEEE Sensors Journal, 2022; data and code "
            "github.com/ssong47/compute_relative_angle_between_two_IMUs (MIT licence)")
ZERO_TARGET_DEG = 0.2
ZERO_WITHIN_S = 30.0
ROUGH_SAMPLES = 9
"""The span of the smooth local fit the encoder's roughness is measured about (9 samples,
0.09 s at 100 Hz: about the shortest a gravity correction through the shaking shaft's
accelerometer can average over)."""


@dataclass
class TrialResult:
    """One trial's figures; a stage that failed leaves its fields None and says why in
    ``failures`` (stage -> the error), and the stages after it that needed it are not run."""

    name: str
    rows: int | None = None
    import_changes: list[str] | None = None
    config: str | None = None
    fits: dict[str, float] | None = None
    rungs: tuple[Rung, ...] | None = None
    follows: tuple[str, ...] = ()
    zero_deg: float = float("nan")
    zero_sigma_deg: float = float("nan")
    track: dict | None = None
    withheld: dict | None = None
    peers: dict[str, dict] | None = None
    seconds: dict[str, float] | None = None
    time_offset_s: float | None = None
    """The shaft IMU's calibrated time offset (s), when the ladder added one."""
    encoder_rough_deg: float = float("nan")
    """The encoder's roughness on the scored stretch (:func:`encoder_roughness_deg`)."""
    failures: dict[str, str] | None = None

    @property
    def horizontal(self) -> bool:
        return self.config is not None and self.config != "imu_rig_yaw"

    def failed(self, stage: str) -> str | None:
        return (self.failures or {}).get(stage)


def ladder(arm, rec: Recording, rungs: int) -> Discovery:
    """Walk the error ladder (:func:`armfusion.fusion.workbench.discover.discover`): rung 0 the config as
    it is, then the most significant missing effect added each time, until nothing significant
    is left or ``rungs`` were added."""
    data = data_from_recording(arm, rec, window=WINDOW, q_ref_rad=np.zeros(arm.n_joints))
    return discover(model_from_arm(arm), data, DiscoverSettings(max_rungs=rungs))


def encoder_zero(d) -> tuple[float, float]:
    """The fit's joint zero (the encoder's, on this power-up: geometric = encoder + zero)
    and its σ, rad."""
    fit = d.fit
    for i, nm in enumerate(fit.names):
        if nm.endswith(".joint_offset") or ".joint_offset[" in nm:
            return float(fit.x[i]), float(fit.sigma[i])
    return 0.0, float("nan")


def encoder_roughness_deg(arm, rec: Recording, joint: int = 0) -> float:
    """RMS of the encoder's angle (deg) about a local quadratic fitted over
    :data:`ROUGH_SAMPLES` samples centred on each: the shaft's motion from one sample to the
    next (a stepper's steps, the ringing after them) that the encoder follows and an estimate
    without it, from gravity and the integral of sampled gyros, cannot. A floor on the error
    of any encoder-free estimate scored against the encoder."""
    q = np.degrees(rec.get("enc").values[:, joint].astype(float) / arm.counts_per_rad[joint])
    k = ROUGH_SAMPLES
    if len(q) < k:
        return float("nan")
    x = np.arange(k) - k // 2
    V = np.vander(x, 3)
    centre = (V @ np.linalg.pinv(V))[k // 2]
    smooth = np.lib.stride_tricks.sliding_window_view(q, k) @ centre
    return float(np.sqrt(np.mean((q[k // 2: len(q) - k // 2] - smooth) ** 2)))


def _run_errors(arm, rec: Recording, zero_rad: float, settings: TrackerSettings | None,
                given_conventions: bool):
    """One tracker run from scratch (moving start): the run, its start, its error against the
    encoder plus the calibration's zero (deg) and its reported σ (deg), per fused instant."""
    tr, start = start_from_recording(arm, rec, settings,
                                     options=StartOptions(moving_start=True, propose_unlock=False,
                                                          sigma_given_conventions=given_conventions))
    run = tr.run(rec, truth=False)
    tq = rec.get("true_q")
    ref = np.interp(run.t_s, tq.t_s, tq.values[:, 0]) + zero_rad
    err = np.degrees(wrap_angle(run.q_rad[:, 0] - ref))
    return run, start, err, np.degrees(run.sigma_rad[:, 0])


def track_scored(cal_config: Path, rec: Recording, zero_rad: float,
                 settings: TrackerSettings | None = None, relative_sigma: bool = False) -> dict:
    """Track ``rec`` from scratch (moving start, encoder zero unknown to the tracker) with the
    calibrated config; errors against the encoder plus the calibration's zero.

    The reference is aligned by the calibration's own zero, so the error is the angle's
    against that calibration; the σ the tracker reports (what a controller needs) also holds
    the absolute zero's doubt (the calibration's joint-zero convention, ``zero_sigma_deg``),
    which this error shares and so cannot show. ``relative_sigma``: the same stretch tracked
    again with the σ taken relative to the calibration's conventions
    (``StartOptions(sigma_given_conventions=True)``), the σ this error is to be
    judged by, reported beside the absolute one (``sigma_rel_*``; ``rmse_rel_run_deg`` that
    run's own error, the same estimate up to the gating the σ touches)."""
    arm = load_arm(cal_config)
    t_wall = time.perf_counter()
    run, start, err, sig = _run_errors(arm, rec, zero_rad, settings, False)
    elapsed = time.perf_counter() - t_wall
    t = run.t_s
    rel = t - t[0]
    flags = run.flags[:, 0]
    share = {JOINT_FLAGS[f]: float(np.mean(flags == f)) for f in np.unique(flags)}
    late = rel >= ZERO_WITHIN_S
    at30 = (rel >= ZERO_WITHIN_S - 5) & (rel < ZERO_WITHIN_S)
    within = np.abs(err) <= 3 * sig
    found = np.flatnonzero(np.abs(err) <= ZERO_TARGET_DEG)
    return {
        "start_note": start.notes[0] if start.notes else "",
        "startup_deg": None if start.startup.joints[0].angle_rad is None
        else float(np.degrees(start.startup.joints[0].angle_rad)),
        "startup_flag": start.startup.joints[0].flag,
        "err_at_30s_deg": float(np.sqrt(np.mean(err[at30] ** 2))) if at30.any() else float("nan"),
        "rmse_after_30s_deg": float(np.sqrt(np.mean(err[late] ** 2))) if late.any() else float("nan"),
        "max_after_30s_deg": float(np.max(np.abs(err[late]))) if late.any() else float("nan"),
        "sigma_median_deg": float(np.median(sig[late])) if late.any() else float("nan"),
        "within_3sigma": float(np.mean(within[late])) if late.any() else float("nan"),
        "first_within_target_s": float(rel[found[0]]) if len(found) else None,
        "flags": share,
        "duration_s": float(rel[-1]),
        "seconds": elapsed,
        "pitch_end_deg": float(np.degrees(run.rpy_rad[-1, 1])),
        **(_relative_sigma(arm, rec, zero_rad, settings) if relative_sigma and late.any() else {}),
    }


def _relative_sigma(arm, rec: Recording, zero_rad: float, settings: TrackerSettings | None) -> dict:
    """The σ relative to the calibration's conventions, scored after 30 s (see
    :func:`track_scored`)."""
    run, _start, err, sig = _run_errors(arm, rec, zero_rad, settings, True)
    late = run.t_s - run.t_s[0] >= ZERO_WITHIN_S
    return {"sigma_rel_median_deg": float(np.median(sig[late])),
            "within_3sigma_rel": float(np.mean(np.abs(err[late]) <= 3 * sig[late])),
            "rmse_rel_run_deg": float(np.sqrt(np.mean(err[late] ** 2)))}


def track_encoder_withheld(cal_config: Path, cal: Recording, rec: Recording, zero_rad: float) -> dict:
    """The scored stretch tracked with the encoder withheld: the joint's relative angle from
    the gyros on either side of it (:mod:`armfusion.fusion.tracking.gyro_encoder`: its scale, bias and
    drift measured against the encoder on the calibration stretch, the drift the tracker's
    random walk for the joint), scored against the encoder and the calibration's zero as
    :func:`track_scored` is."""
    arm = load_arm(cal_config)
    gcal = calibrate_gyro_encoder(arm, cal, 0)
    settings = settings_with_gyro_encoder(None, gcal)
    out = track_scored(cal_config, with_gyro_encoder(arm, rec, 0, gcal), zero_rad, settings)
    out["gyro_scale"] = gcal.scale
    out["gyro_bias_deg_s"] = float(np.degrees(gcal.bias_rad_s))
    out["gyro_delay_ms"] = 1e3 * gcal.delay_s
    out["gyro_taps"] = len(gcal.rate_taps)
    out["drift_span_s"] = gcal.drift_span_s
    out["random_walk_deg_sqrt_s"] = gcal.drift_deg_per_sqrt_s
    out["gyro_residual_deg"] = gcal.residual_deg
    out["gyro_bounded_deg"] = gcal.bounded_deg
    return out


STAGES = ("import", "choose", "ladder", "track", "withheld", "peers")


def _stage(r: TrialResult, stage: str, fn):
    """Run one stage of a trial: its result, or None with the error kept in ``r.failures``
    (a trial's failure is a row of the table, never the end of the bench)."""
    t0 = time.perf_counter()
    try:
        return fn()
    except Exception as e:  # noqa: BLE001 - any failure of a stage is reported, not raised
        r.failures[stage] = f"{type(e).__name__}: {e}"
        return None
    finally:
        r.seconds[stage] = time.perf_counter() - t0


def run_trial(path: Path, calibrate_s: float, rungs: int, work: Path) -> TrialResult:
    """One trial through every stage (:data:`STAGES`); a stage that fails is reported in the
    result and the stages that needed it are skipped, each saying so."""
    r = TrialResult(path.stem, seconds={}, failures={})

    def do_import():
        cmap = load_column_map("imu-rig")
        first = load_arm(RIG_CONFIGS[0])
        return import_recording(path, cmap, first, RIG_CONFIGS[0])

    imported = _stage(r, "import", do_import)
    if imported is None:
        return _skip(r, "import")
    rec = imported.recording
    r.rows, r.import_changes = len(rec.get("enc")), list(imported.changes)
    chosen = _stage(r, "choose", lambda: choose_config(rec, 60.0))
    if chosen is None:
        return _skip(r, "choose")
    r.config, r.fits = chosen
    arm = load_arm(r.config)
    t_start = rec.t_start_s
    cal = rec.between(t_start, t_start + calibrate_s)
    scored = rec.between(t_start + calibrate_s, np.inf)
    r.encoder_rough_deg = encoder_roughness_deg(arm, scored)
    disc = _stage(r, "ladder", lambda: ladder(arm, cal, rungs))
    if disc is None:
        return _skip(r, "ladder")
    r.rungs, r.follows = disc.rungs, disc.remaining
    zero, zero_sig = encoder_zero(disc.final)
    r.zero_deg, r.zero_sigma_deg = float(np.degrees(zero)), float(np.degrees(zero_sig))
    cfg = yaml.safe_load(resolve_config_path(r.config).read_text(encoding="utf-8"))
    out = work / f"{path.stem}.calibrated.yaml"
    out.write_text(yaml.safe_dump(config_with_estimates(cfg, disc.final.fit), sort_keys=False, width=110),
                   encoding="utf-8")
    shaft = arm.link_accelerometers[0].name
    r.time_offset_s = device_time_offsets(config_model(load_arm(out))).get(shaft, (None, None))[0]
    r.track = _stage(r, "track", lambda: track_scored(out, scored, zero, relative_sigma=r.horizontal))
    r.withheld = _stage(r, "withheld", lambda: track_encoder_withheld(out, cal, scored, zero))

    def do_peers():
        _grid, peer_runs = peer_joint_angles(rec, arm, calibrate_s)
        return {n: {"library": p.library, "rmse_deg": p.rmse_deg, "max_deg": p.max_deg, "seconds": p.seconds,
                    "heading_shared": p.heading_shared} for n, p in peer_runs.items()}

    r.peers = _stage(r, "peers", do_peers)
    return r


def _skip(r: TrialResult, failed: str) -> TrialResult:
    """The stages after ``failed`` marked not run."""
    for stage in STAGES[STAGES.index(failed) + 1:]:
        r.failures.setdefault(stage, f"not run ({failed} failed)")
    return r


# ------------------------------------------------------------------------------------ reporting
def _fmt(x, spec=".2f", none="–") -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return none
    return format(x, spec)


def _failure(r: TrialResult, stage: str) -> str:
    return f"**{stage} failed**: {r.failed(stage)}"


def _best_peer(r: TrialResult) -> str:
    if not r.peers:
        return _failure(r, "peers") if r.failed("peers") else "–"
    name, p = min(r.peers.items(), key=lambda kv: kv[1]["rmse_deg"])
    return f"{name} {_fmt(p['rmse_deg'])}°"


def _best_peer_rmse(r: TrialResult) -> float:
    return min((p["rmse_deg"] for p in r.peers.values()), default=float("nan")) if r.peers else float("nan")


def _flag_words(flags: dict) -> str:
    return ", ".join(f"{k} {100 * v:.0f} %" for k, v in sorted(flags.items(), key=lambda kv: -kv[1]))


def _blind_share(tk: dict) -> float:
    """The share of the time the joint was flagged gravity-blind (``gimbal_lock`` or
    ``unobserved``)."""
    return tk["flags"].get("gimbal_lock", 0.0) + tk["flags"].get("unobserved", 0.0)


def _row(r: TrialResult) -> str:
    if r.rungs is None:
        first = next(st for st in STAGES if r.failed(st))
        return f"| {r.name} | {_failure(r, first)} |" + " |" * 11
    tk, wh = r.track, r.withheld
    if tk is None:
        track_cells = f"{_failure(r, 'track')} | | | | | | "
    else:
        track_cells = (f"{_fmt(tk['err_at_30s_deg'])}° | {_fmt(tk['rmse_after_30s_deg'])}° | "
                       f"{100 * tk['within_3sigma']:.1f} % | {_fmt(tk['sigma_median_deg'])}° | "
                       f"{_rel_cell(tk)} | "
                       f"{_flag_words(tk['flags'])} | ")
    withheld = (_failure(r, "withheld") if wh is None else
                f"{_fmt(wh['rmse_after_30s_deg'])}° ({100 * wh['within_3sigma']:.1f} %)")
    return (f"| {r.name} | {r.config} ({r.fits[r.config]:.1f}) | {r.rungs[0].rms_ratio:.1f} → "
            f"{r.rungs[-1].rms_ratio:.2f} | {len(r.rungs) - 1} | " + track_cells
            + f"{r.zero_deg:+.2f}° ± {r.zero_sigma_deg:.2f}° | {withheld} | {_best_peer(r)} |")


def _listing(rs: list[TrialResult], ok, words) -> str:
    """Each trial's figure (``words(r)``) and whether every one meets the target (``ok(r)``)."""
    if not rs:
        return "no such trial here."
    bad = [r.name for r in rs if not ok(r)]
    body = ", ".join(f"{r.name} {words(r)}" for r in rs)
    return body + (" (met)." if not bad else f" (**not met**: {', '.join(bad)}).")


def _vertical_ok(r: TrialResult) -> bool:
    return r.track is not None and _blind_share(r.track) >= 0.99 and r.track["within_3sigma"] >= 0.99


def _vertical_words(r: TrialResult) -> str:
    tk = r.track
    if tk is None:
        return "–"
    return (f"{100 * _blind_share(tk):.1f} % flagged, within 3σ {100 * tk['within_3sigma']:.1f} % "
            f"(σ {_fmt(tk['sigma_median_deg'], '.0f')}°: the joint may be anywhere in its limits)")


def _rel_cell(tk: dict) -> str:
    """The σ relative to the calibration (median, within 3σ of it), or – where not measured."""
    if "sigma_rel_median_deg" not in tk:
        return "–"
    return f"{_fmt(tk['sigma_rel_median_deg'])}° ({100 * tk['within_3sigma_rel']:.1f} %)"


def _tight_ok(r: TrialResult) -> bool:
    """Median σ ≤ 3 × RMSE and within 3σ ≥ 95 %, judged with the σ the error can show: the σ
    relative to the calibration (the error is measured against the calibration's own zero)."""
    tk = r.track
    return (tk is not None and "sigma_rel_median_deg" in tk
            and tk["sigma_rel_median_deg"] <= 3 * tk["rmse_after_30s_deg"]
            and tk["within_3sigma_rel"] >= 0.95)


def _tight_words(r: TrialResult) -> str:
    tk = r.track
    if tk is None:
        return "–"
    rmse = tk["rmse_after_30s_deg"]
    words = (f"absolute σ {_fmt(tk['sigma_median_deg'])}° = {tk['sigma_median_deg'] / rmse:.0f} × RMSE "
             f"(within 3σ {100 * tk['within_3sigma']:.1f} %)")
    if "sigma_rel_median_deg" in tk:
        rel = tk["sigma_rel_median_deg"]
        words = (f"relative σ {_fmt(rel)}° = {rel / rmse:.1f} × RMSE "
                 f"(within 3σ {100 * tk['within_3sigma_rel']:.1f} %), " + words)
    return words


def _withheld_ok(r: TrialResult) -> bool:
    wh = r.withheld
    return (wh is not None and wh["rmse_after_30s_deg"] <= 0.5
            and wh["rmse_after_30s_deg"] < _best_peer_rmse(r))


def _track_figure(key: str):
    def words(r: TrialResult) -> str:
        return "–" if r.track is None else f"{_fmt(r.track[key])}°"
    return words


def targets(results: list[TrialResult]) -> list[str]:
    """The targets, each with where it stands on these trials (a trial whose stage failed
    misses it)."""
    horiz = [r for r in results if r.horizontal]
    vert = [r for r in results if r.config == "imu_rig_yaw"]
    failed = [r.name for r in results if r.config is None]
    lines = [
        "- Vertical shaft, every speed: flagged gravity-blind (`gimbal_lock` or `unobserved`) ≥ 99 % of "
        "the time, within 3σ ≥ 99 %: " + _listing(vert, _vertical_ok, _vertical_words),
        f"- Horizontal shaft, zero found to ≤ {ZERO_TARGET_DEG}° within {ZERO_WITHIN_S:g} s "
        "(error at 25-30 s): "
        + _listing(horiz, lambda r: r.track is not None and r.track["err_at_30s_deg"] <= ZERO_TARGET_DEG,
                   _track_figure("err_at_30s_deg")),
        "- Horizontal shaft, tracked RMSE after 30 s ≤ 0.2°: "
        + _listing(horiz, lambda r: r.track is not None and r.track["rmse_after_30s_deg"] <= 0.2,
                   _track_figure("rmse_after_30s_deg")),
        "- Horizontal shaft, σ honest and tight: median σ ≤ 3 × RMSE and within 3σ ≥ 95 %, judged with "
        "the σ relative to the calibration (the error is measured against the calibration's own zero, "
        "so the absolute zero's doubt, which the tracker's σ carries for a controller, is shared by "
        "reference and estimate and cannot show in it; the absolute σ beside it): "
        + _listing(horiz, _tight_ok, _tight_words),
        "- Horizontal shaft, encoder withheld: RMSE ≤ 0.5° and better than every peer in the same run "
        "(the joint's relative angle from the integral of the shaft's gyro less the frame's about the "
        "shaft's axis, each read when its samples were true, its scale, taps (their delay), bias and drift "
        "measured on the calibration stretch, tracked as a drifting relative encoder; the peers, "
        "tools/rig_peers.py, the twist of the two IMUs' relative orientation about the shaft, zero "
        "aligned on the same stretch): "
        + _listing(horiz, _withheld_ok,
                   lambda r: ("–" if r.withheld is None else f"{_fmt(r.withheld['rmse_after_30s_deg'])}°")
                   + f" against {_best_peer(r)} (the encoder's own roughness {_fmt(r.encoder_rough_deg)}°, "
                   + ("–" if r.withheld is None else
                      f"the stand-in's bounded error {_fmt(r.withheld['gyro_bounded_deg'])}°") + ")"),
        "- The bench runs every trial to the end: "
        + ("met (a failed stage would be a row's entry)." if not any(r.failures for r in results) else
           "every trial ran; stages failed on " + ", ".join(
               f"{r.name} ({', '.join(k for k, v in r.failures.items() if not v.startswith('not run'))})"
               for r in results if r.failures) + "."),
    ]
    if failed:
        lines.append(f"- Trials that did not reach a set-up (every target missed): {', '.join(failed)}.")
    return lines


def headline_rows(results: list[TrialResult]) -> list[dict]:
    """The README's rows: the horizontal shafts' tracked error and withheld-encoder error
    against the best peer (worst trial each), the vertical shafts' flag and honesty."""
    horiz = [r for r in results if r.horizontal and r.track is not None]
    vert = [r for r in results if r.config == "imu_rig_yaw" and r.track is not None]
    rows = []
    if horiz:
        worst = max(horiz, key=lambda r: r.track["rmse_after_30s_deg"])
        rows.append({"what": f"A real one-joint rig (Song et al. 2022), horizontal shaft, {len(horiz)} "
                             "trials: tracked RMSE after 30 s, worst trial (its median σ), relative "
                             "encoder's zero unknown",
                     "armfusion": f"{_fmt(worst.track['rmse_after_30s_deg'])}° "
                                  f"(σ {_fmt(worst.track['sigma_median_deg'])}°)", "baseline": ""})
        withheld = [r for r in horiz if r.withheld is not None]
        if withheld:
            w = max(withheld, key=lambda r: r.withheld["rmse_after_30s_deg"])
            rows.append({"what": "The same, encoder withheld (the gyros stand in), worst trial",
                         "armfusion": f"{_fmt(w.withheld['rmse_after_30s_deg'])}°",
                         "baseline": f"best peer {_best_peer(w)}"})
    if vert:
        rows.append({"what": f"The same rig, vertical shaft (gravity cannot see it), {len(vert)} trials: "
                             "share of time flagged gravity-blind, and within 3σ, worst trial",
                     "armfusion": f"{100 * min(_blind_share(r.track) for r in vert):.1f} %, "
                                  f"{100 * min(r.track['within_3sigma'] for r in vert):.1f} %",
                     "baseline": ""})
    return rows


def benchmarks_section(results: list[TrialResult], calibrate_s: float) -> str:
    lines = [
        "## Real recordings: the one-joint IMU rig (`tools/bench_real_rig.py`)",
        "",
        f"Data: {CITATION}. Each trial treated as never seen: imported with the shipped column map, its "
        f"set-up chosen by which rig config fits its first minute best, calibrated (the workbench's error "
        f"ladder) on its first {calibrate_s:g} s, tracked over the rest with the encoder as the joint's "
        "relative encoder whose zero the tracker does not know (it starts afresh on the moving shaft). "
        "Errors against the encoder and the zero the calibration found (its σ below). The σ the tracker "
        "reports is absolute: it holds the doubt of that zero (the calibration's joint-zero convention), "
        "which reference and estimate share, so the error cannot show it; the σ relative to the "
        "calibration is the same stretch tracked with that doubt left out (the calibration's spreads "
        "given its conventions), the σ this error is judged by. "
        "docs/real-data.md has each trial's ladder. A stage that fails is reported in its row; the "
        "bench goes on to the next trial.",
        "",
        f"Machine: {machine_line()}.",
        "",
        "| trial | set-up (fit ratio) | ladder: start → end (× noise) | rungs | "
        "zero found: error at 25-30 s | "
        "RMSE after 30 s | within 3σ | σ (median) | σ relative to the calibration (within 3σ) | "
        "joint flags | calibration's zero | "
        "encoder withheld: RMSE after 30 s (within 3σ) | best peer, same stretch (RMSE) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *[_row(r) for r in results],
        "",
        "Targets and where they stand:",
        "",
        *targets(results),
    ]
    done = [r for r in results if r.rungs is not None]
    lines.append(
        "- The ladder ends at ≤ 1.5× the noise floor on every trial (the floor: the MPU-6050's datasheet "
        "noise and the 0.01 rounding): "
        + ("met." if all(r.rungs[-1].rms_ratio <= 1.5 for r in done) else
           "**not met** (column 'ladder'). Against the noise each recording shows (the datasheet's with the "
           "single-sample excess the fit measures, the stepper's vibration, averaged over a fit point as "
           "white noise is) the ladders end at "
           + ", ".join(f"{r.name} {r.rungs[-1].measured_ratio:.2f}×" for r in done)
           + ": what is left above the datasheet's floor is that vibration, which no effect of the library "
           "(or any model of the joint's motion) explains (docs/real-data.md)."))
    return "\n".join(lines) + "\n"


def real_data_doc(results: list[TrialResult], calibrate_s: float) -> str:
    out = [
        "# Real data: a one-joint rig through armfusion",
        "",
        "<!-- written by tools/bench_real_rig.py; edit the tool, not this file -->",
        "",
        f"Data: {CITATION}. A stepper motor turns a shaft back and forth between about 0 and 180° for 25 "
        "minutes; an MPU-6050 on the shaft, another on the frame, an encoder on the shaft as the reference. "
        "Three set-ups: the shaft horizontal (`roll`, `pitch`: gravity sees the angle) and vertical (`yaw`: "
        "it cannot). Values were stored in g and °/s rounded to 0.01.",
        "",
        "armfusion reads the rig as a one-joint arm (`config/imu_rig_{roll,pitch,yaw}.yaml`): the frame "
        "IMU is the base IMU, the shaft IMU a link accelerometer with a link gyroscope, the encoder the "
        "joint's relative encoder. A trial comes in with",
        "",
        "```sh",
        "armfusion import raw_roll_slow.mat --map imu-rig --config imu_rig_roll --out roll.mcap",
        "armfusion diagnose roll.mcap --config imu_rig_roll --report roll.html",
        "armfusion diagnose roll.mcap --config imu_rig_roll --add gyro_bias:frame --write roll-1.yaml",
        "armfusion track roll.mcap --config roll-1.yaml --moving-start",
        "armfusion track roll.mcap --config roll-1.yaml --moving-start --encoder-withheld shaft@300",
        "```",
        "",
        "and `tools/bench_real_rig.py` does for every trial what a calibration engineer would: import; "
        "choose the set-up by which config fits (not by the file's name); walk the error ladder on the "
        f"first {calibrate_s:g} s (add the most significant missing effect, refit, until nothing "
        "significant is left); track the rest, never seen by the calibration, with the calibrated config, "
        "the tracker starting afresh on the moving shaft with the encoder's zero unknown to it."
        " Then the same stretch with the encoder withheld, as `track --encoder-withheld` does it (the "
        "two gyros' relative rate about the shaft, each read when its samples were true by the "
        "calibrated time offset, integrated into a drifting relative encoder whose scale, bias and "
        "drift are calibrated where the encoder was known; the drift is the joint's random walk in the "
        "tracker, so gravity corrects it), beside the peer filters of the package index "
        "(`tools/rig_peers.py`: vqf, imufusion, ahrs) on the same samples.",
        "",
        "The noise floor each ratio is measured against is the noise model's: the MPU-6050's datasheet "
        "density (400 µg/√Hz, 0.005 °/s/√Hz) over half the 100 Hz rate, with the 0.01 rounding "
        "(step/√12), per fit point of 10 samples.",
        "",
    ]
    for r in results:
        tk = r.track
        if r.rungs is None:  # failed before the calibration: what failed, and nothing more
            out += [f"## {r.name}", "",
                    *[f"- {stage}: {r.failed(stage)}" for stage in STAGES if r.failed(stage)], ""]
            continue
        out += [
            f"## {r.name}",
            "",
            f"{r.rows:,} samples imported"
            + (f"; {'; '.join(r.import_changes)}" if r.import_changes else "") + ".",
            "",
            "Set-up chosen by fit (ratio of residual to noise, the config as shipped, first minute): "
            + ", ".join(f"`{k}` {v:.1f}" for k, v in r.fits.items()) + f" → **`{r.config}`**.",
            "",
            f"Error ladder on the first {calibrate_s:g} s ({r.seconds['ladder']:.0f} s of one core):",
            "",
            "| rung | added | its estimate ± σ | RMS / noise | per stream | RMS / measured noise |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for i, g in enumerate(r.rungs):
            per = ", ".join(f"{s} {v:.2f}" for s, v in g.per_stream.items())
            out.append(f"| {i} | {g.label} | {g.estimate_words() or '–'} | {g.rms_ratio:.2f} | {per} | "
                       f"{g.measured_ratio:.2f} |")
        out += ["", f"Verdict at the last rung: {r.rungs[-1].verdict}."]
        if r.follows:
            out += ["", "What the remaining residual follows (no effect of the library explains it):", ""]
            out += [f"- {f}" for f in r.follows]
        out += [
            "",
            f"The calibration's joint zero (the encoder's zero on this power-up, geometric = encoder + "
            f"zero): {r.zero_deg:+.3f}° ± {r.zero_sigma_deg:.3f}°.",
            "",
            "",
        ]
        wh = r.withheld
        out += [(_failure(r, "track") if tk is None else
                 f"Tracking the remaining {tk['duration_s']:.0f} s with the calibrated config "
                 f"({tk['seconds']:.0f} s): "
                 f"{tk['start_note']}; startup "
                 + (f"{tk['startup_deg']:.1f}° ({tk['startup_flag']})" if tk["startup_deg"] is not None
                    else f"none ({tk['startup_flag']})")
                 + ". Error against the encoder and the calibration's zero: "
                 f"{_fmt(tk['err_at_30s_deg'])}° "
                 f"(RMS over 25-30 s), {_fmt(tk['rmse_after_30s_deg'])}° RMS after 30 s (worst "
                 f"{_fmt(tk['max_after_30s_deg'])}°), within 3σ {100 * tk['within_3sigma']:.1f} % "
                 "of the time "
                 "at a "
                 f"median σ of {_fmt(tk['sigma_median_deg'])}° (absolute: it holds the calibration's zero "
                 "doubt, which this error shares)"
                 + ("" if "sigma_rel_median_deg" not in tk else
                    f"; relative to the calibration (the same stretch tracked again with that doubt left "
                    f"out; its error {_fmt(tk['rmse_rel_run_deg'])}° RMS) a median σ of "
                    f"{_fmt(tk['sigma_rel_median_deg'])}°, within 3σ {100 * tk['within_3sigma_rel']:.1f} %")
                 + f"; first within {ZERO_TARGET_DEG}° at "
                 f"{_fmt(tk['first_within_target_s'], '.1f', 'never')} s. Joint flags: "
                 + ", ".join(f"{k} {100 * v:.0f} %" for k, v in tk["flags"].items()) + "."),
                "",
                ("The same stretch with the encoder withheld: " + _failure(r, "withheld") if wh is None else
                 f"The same stretch with the encoder withheld (the gyros' relative rate about the shaft, "
                 f"integrated: its scale, delay and bias against the encoder on the calibration stretch "
                 f"{wh['gyro_scale']:.4f}, {wh.get('gyro_delay_ms', 0.0):+.1f} ms and "
                 f"{wh['gyro_bias_deg_s']:+.4f} °/s, and {wh.get('gyro_taps', 0)} taps over the last "
                 f"{RESPONSE_SPAN_S:.1f} s for what the encoder reads otherwise than the link, applied; what "
                 f"that left there {wh['gyro_residual_deg']:.2f}° RMS, drifting "
                 f"{wh['random_walk_deg_sqrt_s']:.3f} °/√s over {wh.get('drift_span_s', 10.0):.2f} s, the "
                 f"time gravity takes to correct it, the joint's random walk in the "
                 f"tracker, of which a bounded {wh['gyro_bounded_deg']:.2f}° that no span makes larger): "
                 f"{_fmt(wh['err_at_30s_deg'])}° at 25-30 s, "
                 f"{_fmt(wh['rmse_after_30s_deg'])}° RMS "
                 f"after 30 s (worst {_fmt(wh['max_after_30s_deg'])}°), within 3σ "
                 f"{100 * wh['within_3sigma']:.1f} % at a median σ of "
                 f"{_fmt(wh['sigma_median_deg'])}°. The encoder itself departs from a smooth "
                 f"curve through {ROUGH_SAMPLES} samples by {_fmt(r.encoder_rough_deg)}° RMS on this "
                 "stretch (the shaft's motion from one sample to the next, which an estimate "
                 "without the encoder cannot follow)."),
                ""]
        if r.peers is None:
            out += ["The peer filters: " + _failure(r, "peers"), ""]
            continue
        out += [
            "The peer filters on the same trial (`tools/rig_peers.py`, each with its documented defaults, "
            "on both IMUs; the shaft angle the twist of their relative orientation about the config's "
            "shaft axis, the two filters' headings reconciled through that axis where the shaft is not "
            f"vertical; the zero aligned to the encoder on the first {calibrate_s:g} s; scored on the rest):",
            "",
            "| peer | library | RMSE | max | its time (both IMUs) |",
            "| --- | --- | ---: | ---: | ---: |",
            *[f"| {n} | {p['library']} | {_fmt(p['rmse_deg'])}° | {_fmt(p['max_deg'])}° | "
              f"{p['seconds']:.1f} s"
              + ("" if p["heading_shared"] else " (gyroscopes only: no direction both IMUs see)") + " |"
              for n, p in sorted(r.peers.items(), key=lambda kv: kv[1]["rmse_deg"])],
            "",
        ]
    out += [
        "## What the rig teaches",
        "",
        "- **Vibration is noise the datasheet does not know.** The stepper motor shakes both IMUs: the "
        "shaft's accelerometer scatters sample to sample by about 0.01-0.07 g beyond its datasheet noise "
        "and the frame's gyroscope by about 1 °/s. Window means (the fit's points) hide it; a filter that "
        "reads every sample meets it. The fit now measures it on single samples (second differences) "
        "and the calibrated config's floor carries it, so the tracker's σ stays honest.",
        "- **One horizontal joint and a still base are one angle to gravity.** The shaft's accelerometer "
        "sees the base's tilt about the shaft plus the joint; the frame's accelerometer sees that tilt "
        "plus its own bias, which a base that never moves cannot separate from it. The calibration "
        "holds that bias as a convention (`joint_zero_conventions`) and fits the joint's zero in it; "
        "the convention's σ is the absolute zero's, and the tracker reports it with the angle. The "
        "tracker keeps the convention ([A calibrated config's own uncertainty]"
        "(tracking-health.md#a-calibrated-configs-own-uncertainty)): when it took the convention's σ "
        "as freedom "
        "for its frame-bias state instead, the base's tilt wandered within it, pulled by the shaft's "
        "vibration, and the joint with it (2.3° and 4.7° RMS on the horizontal trials).",
        "- **Stamps are not instants.** The shaft IMU's samples are stamped about 10 ms late against "
        "the encoder (the ladder's `time_offset`, "
        + ", ".join(f"{r.name} {1e3 * r.time_offset_s:+.1f} ms" for r in results
                    if r.time_offset_s is not None)
        + "). A gyro integral read at its stamps seemed to drift by degrees per √s against the "
        "encoder at the rig's speeds; read when its samples were true, most of that drift is gone.",
        "- **The stepper's steps shake the shaft.** The stepper turns the shaft in steps: the shaft "
        "oscillates about its mean motion at a frequency that rises with its speed (tens of hertz), "
        "tens of °/s in the gyro's samples. The encoder follows that oscillation, and the gyros' "
        "integral follows it differently (within a sample's timing, or the shaft's twist between "
        "them): an error of the stand-in that swings about the encoder without drifting away (its "
        "bounded part, measured over spans of 1 to 10 s, beside its drift), faster than gravity "
        "through the shaking shaft's accelerometer can correct. The encoder's roughness about a "
        f"smooth curve through {ROUGH_SAMPLES} samples ("
        + ", ".join(f"{r.name} {_fmt(r.encoder_rough_deg)}°" for r in results if r.horizontal)
        + ") is a floor on the error of any estimate without the encoder, scored against it.",
        "- **With the encoder withheld**, where gravity sees the shaft: "
        + "; ".join(f"{r.name} armfusion {_fmt(r.withheld['rmse_after_30s_deg'])}°, best peer "
                    f"{_best_peer(r)}" for r in results
                    if r.horizontal and r.withheld is not None)
        + " (RMSE after 30 s).",
        "",
    ]
    return "\n".join(out)


def _run_trials(trials: list[Path], calibrate_s: float, rungs: int, work: Path, jobs: int):
    """Each trial's result, in the trials' order; ``jobs`` > 1 runs them in that many
    processes (each trial is independent of the others)."""
    if jobs <= 1:
        for p in trials:
            yield run_trial(p, calibrate_s, rungs, work)
        return
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs) as pool:
        yield from pool.map(run_trial, trials, [calibrate_s] * len(trials), [rungs] * len(trials),
                            [work] * len(trials))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA, help="folder of the rig's .mat trials")
    ap.add_argument("--calibrate-s", type=float, default=300.0)
    ap.add_argument("--rungs", type=int, default=10)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--jobs", type=int, default=1, help="trials run side by side (processes)")
    a = ap.parse_args(argv)
    trials = sorted(a.data.glob("*.mat"))
    if not trials:
        print(f"no .mat trials in {a.data}", file=sys.stderr)
        return 1
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in _run_trials(trials, a.calibrate_s, a.rungs, Path(tmp), a.jobs):
            tk = r.track
            ladder_words = ("" if r.rungs is None else
                            f"ladder {r.rungs[0].rms_ratio:.1f} -> {r.rungs[-1].rms_ratio:.2f} "
                            f"({len(r.rungs) - 1} rungs); "
                            f"zero {r.zero_deg:+.2f} ± {r.zero_sigma_deg:.2f} deg; ")
            track_words = ("" if tk is None else
                           f"tracked: {_fmt(tk['err_at_30s_deg'])} deg at 30 s, "
                           f"RMSE {_fmt(tk['rmse_after_30s_deg'])}, within 3 sigma "
                           f"{100 * tk['within_3sigma']:.1f} %, flags {tk['flags']}")
            print(f"{r.name}: {r.config}; {ladder_words}{track_words}"
                  + (f"; FAILED {r.failures}" if r.failures else ""), flush=True)
            results.append(r)
    body = benchmarks_section(results, a.calibrate_s)
    doc = real_data_doc(results, a.calibrate_s)
    if a.no_write:
        print(body)
        return 0
    print(f"wrote {write_section('bench_real_rig', body)}")
    record_headline("bench_real_rig", headline_rows(results))
    REAL_DATA_DOC.write_text(doc, encoding="utf-8")
    print(f"wrote {REAL_DATA_DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
