"""Scoring a tracker's run against the truth of a simulated (or instrumented) recording:
the truth at the run's instants (:func:`truth_at`), the joint and heading errors and the
NEES (:func:`errors`), and their summary (:func:`truth_summary`). The filter itself never
sees the truth: :mod:`armfusion.fusion.tracking.run` calls these after the run, when asked."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.settings import FLAG_CODE
from armfusion.models.rotations import wrap_angle
from armfusion.sensors.samples import Stream
from scipy.stats import chi2


def truth_at(truth: Stream, times: np.ndarray, angles: bool = False) -> np.ndarray:
    """The truth at each of ``times``, (T, k): linear between the truth's own samples (a
    live recording's instants fall between the simulator's grid), NaN outside its span or
    across a gap of more than two of its periods. ``angles``: interpolated unwrapped."""
    t, v = truth.t_s, truth.values
    if angles:
        v = np.unwrap(v, axis=0)
    out = np.full((len(times), v.shape[1]), np.nan)
    if len(t) < 2:
        if len(t) == 1:
            out[np.abs(times - t[0]) < 1e-9] = v[0]
        return out
    i = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
    span = t[i + 1] - t[i]
    period = float(np.median(np.diff(t)))
    ok = (times >= t[0] - 1e-9) & (times <= t[-1] + 1e-9) & (span <= 2.0 * period + 1e-9)
    w = np.clip((times - t[i]) / np.where(span > 0, span, 1.0), 0.0, 1.0)[:, None]
    val = v[i] * (1.0 - w) + v[i + 1] * w
    out[ok] = val[ok]
    return out


def errors(q_rad: np.ndarray, rpy_rad: np.ndarray, P: np.ndarray | None, truth_q: np.ndarray | None,
           truth_b: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """``(q_error_rad, yaw_error_rad, nees)`` of a run's joint angles ``q_rad (T, n)`` and
    attitude ``rpy_rad (T, 3)`` against the truth at the same instants (NaN where there is
    none); the NEES over the joints, roll, pitch and yaw with their covariances ``P (T, n+3,
    n+3)`` (None: not kept)."""
    q_err = yaw_err = nees = None
    if truth_q is not None:
        q_err = q_rad - truth_q
    if truth_b is not None:
        att_err = wrap_angle(rpy_rad - truth_b)
        yaw_err = att_err[:, 2]
        if q_err is not None and P is not None:
            e = np.concatenate([q_err, att_err], axis=1)
            good = np.all(np.isfinite(e), axis=1)
            nees = np.full(len(q_rad), np.nan)
            if good.any():
                nees[good] = np.einsum("ti,ti->t", e[good],
                                       np.linalg.solve(P[good], e[good][..., None])[..., 0])
    return q_err, yaw_err, nees


def truth_summary(run, late: np.ndarray, after_s: float) -> dict:
    """The summary's entries against the truth (see docs/reference/track-output.md): RMS errors per joint
    over the instants ``late`` (all, and those the joint was ``ok``), the worst error, the
    share within 3 of its sigmas, the heading RMS and the NEES with its 95 % chi-square
    bounds."""
    d: dict = {}
    if run.q_error_rad is not None:
        e = np.degrees(run.q_error_rad[late])
        good = np.isfinite(e)
        d["rms_error_deg"] = {nm: _rms(e[:, j][good[:, j]]) for j, nm in enumerate(run.joint_names)}
        ok = (run.flags[late] == FLAG_CODE["ok"]) & good
        d["rms_error_ok_deg"] = {nm: _rms(e[:, j][ok[:, j]]) for j, nm in enumerate(run.joint_names)}
        d["max_error_deg"] = {nm: _maxabs(e[:, j][good[:, j]]) for j, nm in enumerate(run.joint_names)}
        # the share of the instants whose error is within 3 of the reported sigmas: below
        # 99 % a joint is reported surer than it is (a confident wrong answer)
        inside = np.abs(e) <= 3.0 * np.degrees(run.sigma_rad[late])
        d["within_3_sigma"] = {nm: (float(np.mean(inside[:, j][good[:, j]])) if good[:, j].any() else None)
                               for j, nm in enumerate(run.joint_names)}
        d["rms_after_s"] = after_s
    if run.yaw_error_rad is not None:
        y = np.degrees(run.yaw_error_rad[late])
        d["heading_rms_deg"] = _rms(y[np.isfinite(y)])
    if run.nees is not None:
        v = run.nees[late & np.isfinite(run.nees)]
        if len(v):
            lo, hi = chi2.ppf([0.025, 0.975], run.nees_dof)
            d["nees"] = {"mean": float(np.mean(v)), "dof": run.nees_dof, "count": int(len(v)),
                         "bounds_95_single": [float(lo), float(hi)],
                         "bounds_95": [float(x) for x in chi2.ppf([0.025, 0.975], len(v) * run.nees_dof)
                                       / len(v)],
                         "states": [f"q[{nm}]" for nm in run.joint_names] + ["roll", "pitch", "yaw"]}
    return d


def _maxabs(v: np.ndarray) -> float | None:
    return float(np.max(np.abs(v))) if len(v) else None


def _rms(v: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(v**2))) if len(v) else None

