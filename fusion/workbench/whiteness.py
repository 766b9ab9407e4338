"""Where the model fails: the whiteness of residuals (or a tracker's normalised
innovations), their cross-correlation with the inputs (joint angles, rates, accelerations,
the chair's acceleration, the temperature), as MATLAB's ``resid``, and the recording's
worst stretches."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import norm

MAX_LAG = 25
"""Lags (fit points, either side) of the auto- and cross-correlations (MATLAB's default)."""
BAND_Z = 2.58
"""The 99 % band of a correlation estimate of white residuals: ±2.58/√N."""


@dataclass(frozen=True)
class InputCorrelation:
    """One residual axis against one input: the largest cross-correlation within ±MAX_LAG."""

    stream: str
    axis: str
    input: str
    r: float
    lag: int
    """Fit points; positive: the residual follows the input that many points later."""
    r_lag0: float


@dataclass(frozen=True)
class ResidualAnalysis:
    """Autocorrelation (whiteness) of every residual axis and its cross-correlation with every
    input (joint angles, rates, accelerations, the chair's acceleration, the temperature).

    For white residuals each estimate is about N(0, 1/N): MATLAB's ``resid`` draws the 99 %
    band ``±2.58/√N``. Beyond that band one pair in a hundred still strays by chance, and
    there are axes × inputs × lags of them, so a correlation is **flagged** only beyond the
    band corrected for that many tests (Bonferroni at 1 %): a model that fits to noise shows
    no flag in 99 % of recordings."""

    axes: tuple[tuple[str, str], ...]
    inputs: tuple[str, ...]
    n: int
    dt_s: float
    max_lag: int
    autocorr: np.ndarray
    """``(axes, max_lag + 1)``: lags 0 (= 1) to max_lag."""
    xcorr: np.ndarray
    """``(axes, inputs, 2 max_lag + 1)``: lags -max_lag … max_lag."""
    constant_inputs: tuple[str, ...] = ()
    """Inputs that do not vary in this recording (left out: no correlation to speak of)."""
    source: str = "fit residuals"
    excluded: np.ndarray | None = None
    """``(axes, inputs)``: pairs not tested (an input measured by that same sensor shares its
    noise: the chair's acceleration from the IMU against the IMU's own innovations)."""
    min_lag: np.ndarray | None = None
    """``(inputs,)``: the smallest lag tested per input (None: every lag from -max_lag). A
    filter's innovation is orthogonal to the measurements before it, not to those at or
    after it (they carry the same state error): an input the filter itself measures (the
    chair's acceleration, read off the IMU) is tested only at lags where it comes first."""

    def tested(self) -> np.ndarray:
        """``(axes, inputs)`` bool: which axis-input pairs the test looked at (the excluded
        ones left out)."""
        ok = np.ones((len(self.axes), len(self.inputs)), bool)
        return ok if self.excluded is None else ~self.excluded

    def _lag_from(self) -> np.ndarray:
        """Per input, the index (into ``xcorr``'s last axis) of its smallest tested lag."""
        lo = np.zeros(len(self.inputs), dtype=int) if self.min_lag is None else \
            np.clip(np.asarray(self.min_lag, int) + self.max_lag, 0, 2 * self.max_lag)
        return lo

    @property
    def n_tests(self) -> int:
        """How many correlations the input test weighs (tested pairs times their lags)."""
        lags = 2 * self.max_lag + 1 - self._lag_from()
        return int(np.sum(self.tested() * lags[None, :]))

    @property
    def band(self) -> float:
        return BAND_Z / np.sqrt(max(self.n, 1))

    @property
    def band_flag(self) -> float:
        tests = max(self.n_tests, 1)
        return float(norm.isf(0.005 / tests) / np.sqrt(max(self.n, 1)))

    @property
    def band_flag_autocorr(self) -> float:
        return float(norm.isf(0.005 / max(len(self.axes) * self.max_lag, 1)) / np.sqrt(max(self.n, 1)))

    def correlations(self) -> list[InputCorrelation]:
        """Every axis-input pair's strongest correlation, strongest first."""
        out = []
        L = self.max_lag
        ok = self.tested()
        lo = self._lag_from()
        for a, (s, ax) in enumerate(self.axes):
            for i, lab in enumerate(self.inputs):
                if not ok[a, i]:
                    continue
                c = self.xcorr[a, i]
                k = int(lo[i] + np.argmax(np.abs(c[lo[i]:])))
                out.append(InputCorrelation(s, ax, lab, float(c[k]), k - L, float(c[L])))
        return sorted(out, key=lambda c: -abs(c.r))

    def flagged(self) -> list[InputCorrelation]:
        return [c for c in self.correlations() if abs(c.r) > self.band_flag]

    def not_white(self) -> list[tuple[str, str, float]]:
        """Axes whose autocorrelation strays beyond the corrected band at some lag:
        ``(stream, axis, largest |autocorrelation|)``."""
        out = []
        for a, (s, ax) in enumerate(self.axes):
            m = float(np.max(np.abs(self.autocorr[a, 1:]))) if self.max_lag else 0.0
            if m > self.band_flag_autocorr:
                out.append((s, ax, m))
        return sorted(out, key=lambda t: -t[2])

    @property
    def white(self) -> bool:
        return not self.not_white() and not self.flagged()

    def as_dict(self) -> dict[str, Any]:
        return {
            "source": self.source, "n": self.n, "dt_s": self.dt_s, "max_lag": self.max_lag,
            "band_99": round(self.band, 5), "band_flag": round(self.band_flag, 5), "tests": self.n_tests,
            "band_flag_autocorr": round(self.band_flag_autocorr, 5),
            "inputs": list(self.inputs), "constant_inputs": list(self.constant_inputs),
            "white": self.white,
            "autocorr": [{"stream": s, "axis": ax, "r": np.round(self.autocorr[a, 1:], 4).tolist()}
                         for a, (s, ax) in enumerate(self.axes)],
            "not_white": [{"stream": s, "axis": ax, "max_abs_r": round(m, 4)}
                          for s, ax, m in self.not_white()],
            "flagged": [{"stream": c.stream, "axis": c.axis, "input": c.input, "r": round(c.r, 4),
                         "lag": c.lag, "r_lag0": round(c.r_lag0, 4)} for c in self.flagged()],
            "xcorr_lag0": {f"{s}:{ax}": {lab: round(float(self.xcorr[a, i, self.max_lag]), 4)
                                         for i, lab in enumerate(self.inputs) if self.tested()[a, i]}
                           for a, (s, ax) in enumerate(self.axes)},
        }


def fit_inputs(state, joint_names: Sequence[str]) -> dict[str, np.ndarray]:
    """The inputs a residual is held against: each joint's angle, rate and acceleration, the
    chair's acceleration (base axes) and the temperature, at the fit points."""
    out: dict[str, np.ndarray] = {}
    N = state.t_s.shape[0]
    for j, jn in enumerate(joint_names):
        k = jn[1:] if jn.startswith("j") else jn
        out[f"q{k}"] = state.q_rad[:, j]
        out[f"rate q{k}"] = state.qd_rad_s[:, j]
        out[f"accel q{k}"] = state.qdd_rad_s2[:, j]
    a = np.broadcast_to(np.asarray(state.accel_B_mps2, float), (N, 3))
    for c, lab in enumerate("xyz"):
        out[f"chair accel {lab}"] = a[:, c]
    out["temperature"] = np.broadcast_to(np.asarray(state.temperature_c, float), (N,))
    return out


def residual_analysis(E: np.ndarray, axes: Sequence[tuple[str, str]], inputs: dict[str, np.ndarray],
                      dt_s: float, max_lag: int = MAX_LAG, source: str = "fit residuals",
                      exclude: Callable[[str, str], bool] | None = None,
                      min_lag: Callable[[str], int] | None = None) -> ResidualAnalysis:
    """Auto- and cross-correlations (biased, 1/N, as MATLAB's ``resid``) of the residuals
    ``E (N, axes)`` and the ``inputs`` (each ``(N,)``), lags -max_lag … max_lag;
    ``exclude(stream, input)`` names pairs not to test; ``min_lag(input)`` the smallest lag
    at which an input is tested (:attr:`ResidualAnalysis.min_lag`)."""
    E = np.asarray(E, float)
    N = E.shape[0]
    L = int(max(0, min(max_lag, N - 2)))
    # not centred: white noise has mean zero, and a constant offset is a failure too
    sd = np.sqrt(np.mean(E**2, 0))
    Ec = E / np.where(sd > 0, sd, 1.0)
    labels, cols, const = [], [], []
    for lab, u in inputs.items():
        u = np.asarray(u, float)
        s = u.std()
        if not np.isfinite(s) or s <= 1e-12 * max(np.abs(u).max(), 1e-300):
            const.append(lab)
            continue
        labels.append(lab)
        cols.append((u - u.mean()) / s)
    U = np.stack(cols, 1) if cols else np.zeros((N, 0))
    ac = np.ones((E.shape[1], L + 1))
    X = np.zeros((E.shape[1], U.shape[1], 2 * L + 1))
    for lag in range(0, L + 1):
        if lag:
            ac[:, lag] = np.sum(Ec[lag:] * Ec[:-lag], 0) / N
        X[:, :, L + lag] = Ec[lag:].T @ U[:N - lag] / N
        if lag:
            X[:, :, L - lag] = Ec[:N - lag].T @ U[lag:] / N
    excl = None
    if exclude is not None:
        excl = np.array([[bool(exclude(s, lab)) for lab in labels] for s, _ in axes], bool).reshape(
            len(axes), len(labels))
    lags = None if min_lag is None else np.array([max(-L, min(L, int(min_lag(lab)))) for lab in labels], int)
    return ResidualAnalysis(tuple(axes), tuple(labels), N, float(dt_s), L, ac, X, tuple(const), source, excl,
                            lags)



def worst_stretches(chi2_per_point: np.ndarray, t_s: np.ndarray, n: int = 3,
                    span_s: float = 5.0) -> tuple[tuple[float, float, float], ...]:
    """The ``n`` non-overlapping stretches of about ``span_s`` where the residual (mean over
    the axes of the noise-weighted r² at each fit point) is largest:
    ``(t_start, t_end, rms_ratio)``."""
    m = len(t_s)
    if m < 3:
        return ()
    ss = np.asarray(chi2_per_point, float)
    dt = float(np.median(np.diff(t_s)))
    w = int(max(1, min(m, round(span_s / max(dt, 1e-9)))))
    c = np.concatenate([[0.0], np.cumsum(ss)])
    win = (c[w:] - c[:-w]) / w
    out = []
    taken = np.zeros(len(win), bool)
    for i in np.argsort(-win):
        if len(out) == n:
            break
        if taken[max(0, i - w + 1):i + w].any():
            continue
        taken[i] = True
        out.append((float(t_s[i]), float(t_s[i + w - 1]), float(np.sqrt(win[i]))))
    return tuple(out)
