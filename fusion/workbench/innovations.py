"""The workbench on moving data (the chair driving): the tracker run over the recording,
and the same whiteness and input-correlation analysis (:mod:`armfusion.fusion.workbench.whiteness`) on
its normalised innovations, with each sensor's mean NIS. :func:`chair_moves` says whether a
recording is one for this analysis (the fit of :func:`armfusion.fusion.workbench.diagnose.diagnose`
takes the chair as parked)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from armfusion.fusion.workbench.whiteness import (
    MAX_LAG,
    InputCorrelation,
    ResidualAnalysis,
    residual_analysis,
)
from armfusion.models.rotations import DEG, up_from_tilt
from armfusion.models.sensor_models import stream_models

INNOVATIONS_WHITE = "innovations white: the model fits the moving recording"


@dataclass(frozen=True)
class InnovationDiagnosis:
    """Whiteness and cross-correlation of the tracker's normalised innovations
    (``L⁻¹ν`` with ``S = LLᵀ``: white, unit variance and following no input when the
    model and its noise are right), and each sensor's mean NIS."""

    analyses: tuple[ResidualAnalysis, ...]
    """One per group of sensors fused at the same instants (the accelerometers), in the verdict."""
    nis: dict[str, tuple[float, int, int]]
    """Per sensor: mean NIS, count, degrees of freedom."""
    steps: int
    seconds: float
    compass: ResidualAnalysis | None = None
    """The compass's heading innovations, analysed alike but not in the verdict: the tracker
    takes its iron's and the arm's steel's errors as biases that last a heading visit
    (docs/tracking-heading.md, "The compass calibrated by driving"), so they are coloured by design;
    their mean NIS (in ``nis``) says whether their size is right."""

    @property
    def white(self) -> bool:
        return all(a.white for a in self.analyses)

    def not_white(self) -> list[tuple[str, str, float]]:
        return sorted((x for a in self.analyses for x in a.not_white()), key=lambda x: -x[2])

    def flagged(self) -> list[InputCorrelation]:
        return sorted((c for a in self.analyses for c in a.flagged()), key=lambda c: -abs(c.r))

    @property
    def verdict(self) -> str:
        if self.white:
            return INNOVATIONS_WHITE
        nw, fl = self.not_white(), self.flagged()
        where = nw[0][1] if nw else fl[0].axis
        return f"innovations not white: the model misses something while moving (worst: {where})"

    def as_dict(self) -> dict[str, Any]:
        return {"verdict": self.verdict, "white": self.white, "steps": self.steps,
                "seconds": round(self.seconds, 3),
                "nis": {s: {"mean": round(float(m), 4), "count": int(c), "dof": int(k)}
                        for s, (m, c, k) in self.nis.items()},
                "analyses": [a.as_dict() for a in self.analyses],
                "compass_not_in_verdict": None if self.compass is None else {
                    "white": self.compass.white, **self.compass.as_dict(),
                    "why": "the compass's iron and the arm's steel are biases that last a heading visit"}}


def chair_moves(arm, rec, rate_rad_s: float = 5 * DEG, share: float = 0.01) -> bool:
    """Whether the chair turns in ``rec``: the IMU gyro reads more than ``rate_rad_s`` (beyond
    its median, the bias) on more than ``share`` of the samples. The fit of :func:`diagnose`
    takes the chair as parked; a moving recording is for :func:`innovation_diagnosis`."""
    g = rec.get("imu_gyro")
    if g is None or not len(g):
        return False
    w = stream_models(arm)["imu_gyro"].from_counts(np.asarray(g.values, float))
    w = w - np.median(w, 0)
    return bool(np.mean(np.linalg.norm(w, axis=1) > rate_rad_s) > share)


def _moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or len(x) < n:
        return x
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), 0)
    m = (c[n:] - c[:-n]) / n
    pad = n - 1
    return np.concatenate([np.repeat(m[:1], pad // 2, 0), m, np.repeat(m[-1:], pad - pad // 2, 0)])


CHAIR_ACCEL_MEAN_S = 0.5
"""The chair's acceleration input is the IMU's reading averaged over this long (centred)."""


def _shares_noise(stream: str, label: str) -> bool:
    """The chair's acceleration is read off the IMU's accelerometer: not evidence against it."""
    return stream == "imu_acc" and label.startswith("chair accel")


def _first_lag(block_s: float) -> Callable[[str], int]:
    """The smallest lag (in blocks of ``block_s``) at which each input is tested. The chair's
    acceleration is the IMU's own reading, which the tracker fuses: an innovation is
    orthogonal to the readings before it, not to those at or after it (they carry the same
    state error: a correct filter's link innovations follow the IMU's later readings), so it
    is tested only where its whole averaging window ends before the innovation's block starts.
    The joints' angles, rates and accelerations come from the encoders (the tracker's
    corrections to them are hundredths of a degree): every lag."""
    first = math.ceil((CHAIR_ACCEL_MEAN_S / 2) / block_s + 0.5 - 1e-9)
    return lambda label: first if label.startswith("chair accel") else -MAX_LAG


def workbench_arm(arm):
    """The arm as the workbench tracks a moving recording: its link accelerometers' noise
    their datasheet's, without the config's unmodelled floor (the IMU's is kept: the tracker
    carries it as a bias state). That floor is the config's doubt about a calibration (a
    bias, a board's mount: errors that last), which the tracker takes as white noise so that
    its sigmas stay honest; taken so on a moving recording it weighs each link accelerometer
    ``(floor / noise)²`` times less than its noise allows (about 200 times for the shipped
    45 mg), and a filter whose gain is not the optimal one leaves coloured innovations even
    when its model is exact (the gimbal-locked joints read at the first reach settle over
    seconds). The workbench asks whether the model explains the readings to their noise: a
    calibration error is then a missing effect it shows."""
    cal = arm.calibration
    exact_links = replace(cal, accel_unmodelled_g=0.0, accel_unmodelled_g_per_sensor={},
                          imu_accel_unmodelled_g=cal.imu_accel_floor_g)
    return replace(arm, calibration=exact_links)


def innovation_inputs(arm, rec, run, t_s: np.ndarray) -> dict[str, np.ndarray]:
    """The inputs at the innovations' instants: each joint's angle, its rate and acceleration
    (from the encoders' angle, smoothed over 0.2 s: the joint's own motion, not the tracker's
    corrections to it, which follow its innovations; the angle anchored to the tracked one at
    the start), the chair's acceleration (the IMU's specific force less gravity at the tracked
    tilt, base axes, averaged over 0.5 s so that the IMU's own noise does not correlate with
    its innovations: :data:`CHAIR_ACCEL_MEAN_S`) and the temperature."""
    sm = stream_models(arm)
    tt = np.asarray(run.t_s, float)
    ok = np.all(np.isfinite(run.q_rad), 1)
    tt, q_tracked = tt[ok], run.q_rad[ok]
    enc = rec.get("enc")
    if enc is not None and len(enc) > 1 and len(tt):
        q_enc = sm["enc"].from_counts(np.asarray(enc.values, float))
        q = np.stack([np.interp(tt, enc.t_s, q_enc[:, j]) for j in range(q_enc.shape[1])], 1)
        q = q + (q_tracked[0] - q[0])
    else:
        q = q_tracked
    dt = float(np.median(np.diff(tt))) if len(tt) > 1 else 0.01
    qs = _moving_mean(q, max(1, int(round(0.2 / dt))))
    qd = np.gradient(qs, tt, axis=0)
    qdd = np.gradient(_moving_mean(qd, max(1, int(round(0.2 / dt)))), tt, axis=0)
    out: dict[str, np.ndarray] = {}
    for j, jn in enumerate(arm.joint_names):
        k = jn[1:] if jn.startswith("j") else jn
        out[f"q{k}"] = np.interp(t_s, tt, q[:, j])
        out[f"rate q{k}"] = np.interp(t_s, tt, qd[:, j])
        out[f"accel q{k}"] = np.interp(t_s, tt, qdd[:, j])
    ia = rec.get("imu_acc")
    if ia is not None and len(ia) and arm.imu is not None:
        f = sm["imu_acc"].from_counts(np.asarray(ia.values, float)) @ arm.imu.R_LS.T
        rpy = run.rpy_rad[ok]
        up = up_from_tilt(np.interp(ia.t_s, tt, rpy[:, 0]), np.interp(ia.t_s, tt, rpy[:, 1]))
        da = np.asarray(ia.t_s, float)
        step_s = max(float(np.median(np.diff(da))), 1e-3)
        a = _moving_mean(f - up, max(1, int(round(CHAIR_ACCEL_MEAN_S / step_s))))
        for c, lab in enumerate("xyz"):
            out[f"chair accel {lab}"] = np.interp(t_s, da, a[:, c])
    tp = rec.get("imu_temp")
    if tp is not None and len(tp):
        temp_c = sm["imu_temp"].from_counts(np.asarray(tp.values, float))[:, 0]
        out["temperature"] = np.interp(t_s, tp.t_s, temp_c)
    return out


def _block_means(t: np.ndarray, x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    m = len(t) // n
    if n <= 1 or m < 2:
        return t, x
    return (t[: m * n].reshape(m, n).mean(1),
            x[: m * n].reshape(m, n, *x.shape[1:]).mean(1))


def innovation_diagnosis(arm, rec, settings=None, max_lag: int = MAX_LAG, block_s: float = 0.5,
                         progress: Callable[[str, float], None] | None = None) -> InnovationDiagnosis:
    """Run the tracker (``armfusion.fusion.tracking.tracker``, started on the recording's first still stretch)
    over ``rec`` and analyse its normalised innovations: whiteness per axis and
    cross-correlation with the inputs (:func:`residual_analysis`).

    The innovations are averaged over blocks of ``block_s`` first ("batch means"): a filter's
    innovations carry short-lived colour even when its model is right (the differentiators'
    lag in the motion terms, the encoders' rounding, a gain below the optimum where the
    noise is taken larger than it is), which the block means wash out, while a missing
    effect (a bias that follows the pose, a drift) lasts for seconds and survives."""
    from armfusion.fusion.tracking.tracker import StartOptions, start_from_recording

    t0 = time.perf_counter()
    say = progress or (lambda _m, _f: None)
    say("starting the tracker", 0.0)
    arm = workbench_arm(arm)
    tr, _start = start_from_recording(arm, rec, settings, options=StartOptions(resolve_by_motion_s=20.0))
    say("tracking the recording", 0.1)
    run = tr.run(rec, truth=False, progress=lambda f: say("tracking the recording", 0.1 + 0.8 * f))
    say("analysing the innovations", 0.9)
    sm = stream_models(arm)
    logs = []
    for s in [a.name for a in arm.link_accelerometers] + (["imu_acc", "imu_mag"] if arm.imu else []):
        try:
            lg = tr.innovations(s)
        except KeyError:
            continue
        good = np.isfinite(lg.nis) & np.all(np.isfinite(lg.innovation), 1)
        if good.sum() < 10:
            continue
        Lc = np.linalg.cholesky(lg.S[good])
        e = np.linalg.solve(Lc, lg.innovation[good][..., None])[..., 0]
        names = tuple(c.removeprefix(f"{s}_") for c in sm[s].channels) \
            if lg.innovation.shape[1] == len(sm[s].channels) else ("heading",)
        logs.append((s, np.round(lg.t_s[good], 6), e, names))
    # sensors fused at the same instants are analysed together (the accelerometers at every
    # instant; the compass at its own, slower, fusion period)
    groups: list[tuple[np.ndarray, list]] = []
    for s, t, e, names in logs:
        for gt, members in groups:
            if len(gt) == len(t) and np.array_equal(gt, t):
                members.append((s, e, names))
                break
        else:
            groups.append((t, [(s, e, names)]))
    analyses, compass = [], None
    for t, members in groups:
        E = np.concatenate([e for _, e, _ in members], 1)
        axes = [(s, f"{s}_{n}") for s, _, names in members for n in names]
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        t, E = _block_means(t, E, max(1, int(round(block_s / max(dt, 1e-9)))))
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        a = residual_analysis(E, axes, innovation_inputs(arm, rec, run, t), dt, max_lag,
                              source="tracker innovations", exclude=_shares_noise,
                              min_lag=_first_lag(dt))
        if [s for s, _, _ in members] == ["imu_mag"]:
            compass = a
        else:
            analyses.append(a)
    say("done", 1.0)
    return InnovationDiagnosis(tuple(analyses), tr.nis_stats(), run.steps, time.perf_counter() - t0, compass)
