"""The model workbench: compare the model with the measurements, see where it fails, learn
which physical effect is missing.

``diagnose(model, data)``:

1. **Compare.** Fit the model (its effects, the recording's encoder zeros, the base
   attitude) with :func:`fusion.identification.identify.identify`; per sensor axis the residual RMS
   against the noise floor of the sensor model, and the fit in % (NRMSE, as MATLAB's
   ``compare``: ``100 (1 - |y - ŷ| / |y - mean y|)``). ``rms_ratio`` is the whole model's
   residual RMS over its noise floor (1.0: it fits to noise).
2. **Which effect is missing.** Every effect of the library the model lacks, on every
   target it could apply to, is appended at zero (the identity) to one big model; one
   Jacobian evaluation gives all their columns. For each candidate the score
   (Lagrange-multiplier) test: with the weighted residual ``r`` and the candidate's columns
   ``J_c`` with the fitted parameters' columns ``J_f`` projected out (they would re-adjust),
   ``LM = gᵀ M⁺ g``, ``g = J_cᵀ r``, ``M = J_c⊥ᵀ J_c⊥``, restricted to the directions the
   data know better than the candidate's prior. Under "nothing is missing" LM is χ² with
   that many degrees of freedom; the p-value is Bonferroni-corrected over the candidates.
   No refit is needed for this.
3. The best few by the linearised ΔBIC, among those whose score test is significant, are
   refitted (``identify`` with the candidate added, starting from the current estimates,
   on at most ``refit_points`` evenly spread fit points; the residual then evaluated over
   the whole recording), more while none reaches the noise, and the rivals of the best on
   its target: residual RMS after, ΔBIC, the estimated parameters with σ. A candidate is
   **significant** when its corrected p-value is below ``alpha`` and its ΔBIC is negative.
   Each comes with the effect's plain-language description and the evidence: which input
   its residual follows, and how much of the residual the candidate explains.
4. **Where it fails.** Each axis's residual auto- and cross-correlation with the inputs
   (:func:`residual_analysis`, as MATLAB's ``resid``) and the worst stretches.

On moving data (the chair driving) :func:`innovation_diagnosis` runs the same analysis on
the tracker's normalised innovations. See docs/workbench.md.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2 as chi2_dist

from fusion.identification.identify import (
    FIT_STREAMS_EXCLUDED,
    FitData,
    Identification,
    IdentifySettings,
    _Problem,
    identify,
    with_encoder_zeros,
)
from models.effects import EFFECTS, Effect, Model, all_effects
from models.rotations import DEG

EXCLUDED_CANDIDATES = frozenset({"enc.time_offset"})
"""The encoders are the time reference: their own delay is every other device's."""

FITS_TO_NOISE = "fits to noise"


@dataclass(frozen=True)
class DiagnoseSettings:
    alpha: float = 0.05
    """Family-wise false-alarm rate of the score tests (Bonferroni over the candidates)."""
    n_refit: int = 3
    """Candidates refitted (the best by the linearised ΔBIC whose score test is significant)."""
    max_refit: int = 8
    """Refits go on past ``n_refit`` (in the linearised order) while none has reached the noise."""
    max_rivals: int = 4
    """Besides, refit up to this many more candidates on the best refit's target."""
    refit_points: int = 1000
    """Fit points (evenly spread) a quick refit estimates on; its residual is then evaluated
    over the whole recording."""
    prefit_points: int = 2000
    """On a recording with more than twice as many fit points, the encoder zeros and the base
    attitude are first fitted on this many evenly spread points (0: never)."""
    evidence_points: int = 3000
    """Fit points (evenly spread) the evidence sentences are read off."""
    noise_tolerance: float = 1.1
    """``rms_ratio`` at or below this counts as noise (the sensor model's floor ±10 %)."""
    chunk_rows: int = 400_000
    """Residual rows per chunk of the score tests' Jacobian (bounds memory: rows × ~200
    candidate columns × 8 bytes; the evidence sentences use one chunk's worth of points)."""
    effects: tuple[str, ...] | None = None
    """Library effects to consider (None: all)."""
    identify: IdentifySettings = field(default_factory=lambda: IdentifySettings(encoder_scale=True))
    """The fits' settings. ``encoder_scale`` on: the score tests already treat an encoder's
    scale as acting on the fit's joint angles, and a refit that left it out would hold an
    ``encoder_scale`` candidate at its prior (added, it would change nothing)."""


@dataclass(frozen=True)
class AxisFit:
    """One sensor axis: residual RMS against the noise floor (physical units, window
    means) and the fit in % (NRMSE)."""

    stream: str
    axis: str
    unit: str
    rms: float
    noise: float
    fit_percent: float | None
    """None where the axis does not vary beyond 3× its noise (nothing to fit)."""
    autocorr1: float = 0.0
    """Lag-1 autocorrelation of the residual (whiteness): for white noise about ``±1/√n``;
    a missing effect makes it near 1."""

    @property
    def ratio(self) -> float:
        return self.rms / self.noise if self.noise > 0 else np.inf


@dataclass(frozen=True)
class Candidate:
    """A library effect the model lacks, at one target, and the evidence for it."""

    effect: str
    target: str
    score: float
    """The score (LM) statistic: the linearised fall of χ² if it were added."""
    dof: int
    """Directions of its parameters the data see (better than its prior)."""
    p_value: float
    """Bonferroni-corrected over all candidates."""
    explained: float
    """Share of the residual beyond the noise it explains (linearised, 0-1)."""
    delta_bic: float
    """ΔBIC of adding it (refit, or linearised when not refitted): negative is better."""
    refitted: bool
    rms_after: float | None
    """Whole-model ``rms_ratio`` after the refit (None when not refitted)."""
    params: dict[str, tuple[float, float]]
    """Element -> (estimate, σ), in the block's units (refit, else the linearised step)."""
    units: str
    significant: bool
    explanation: str
    evidence: str

    @property
    def name(self) -> str:
        return f"{self.effect}:{self.target}"

    def as_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "target": self.target, "delta_bic": round(self.delta_bic, 2),
                "rms_after": None if self.rms_after is None else round(self.rms_after, 4),
                "significant": self.significant, "score": round(self.score, 2), "dof": self.dof,
                "p_value": self.p_value, "explained": round(self.explained, 4),
                "refitted": self.refitted, "units": self.units,
                "params": {k: {"value": v, "sigma": s} for k, (v, s) in self.params.items()},
                "explanation": self.explanation, "evidence": self.evidence}


@dataclass(frozen=True)
class Diagnosis:
    """The result of :func:`diagnose`."""

    fit: Identification
    data: FitData
    axes: tuple[AxisFit, ...]
    rms_ratio: float
    candidates: tuple[Candidate, ...]
    unseen: tuple[str, ...]
    """Candidates this recording cannot see at all (no direction known beyond the prior)."""
    verdict: str
    seconds: float
    worst: tuple[tuple[float, float, float], ...] = ()
    """The worst stretches of the recording: ``(t_start_s, t_end_s, rms_ratio there)``."""
    analysis: ResidualAnalysis | None = None
    """Whiteness and cross-correlation of the residuals with the inputs."""

    @property
    def model(self) -> Model:
        """The fitted model: estimates as current values (the start of a refit)."""
        return self.fit.model.with_values(self.fit.model_x)

    @property
    def significant(self) -> tuple[Candidate, ...]:
        return tuple(c for c in self.candidates if c.significant)

    @property
    def fits_to_noise(self) -> bool:
        return self.verdict == FITS_TO_NOISE

    def effects(self) -> list[str]:
        return [e.block_name for e in self.fit.model.effects]

    def as_dict(self, top: int = 10) -> dict[str, Any]:
        return {
            "verdict": self.verdict,
            "effects": self.effects(),
            "rms_ratio": round(self.rms_ratio, 4),
            "axes": [{"stream": a.stream, "axis": a.axis, "unit": a.unit, "rms": a.rms,
                      "noise": a.noise, "ratio": round(a.ratio, 4),
                      "fit_percent": None if a.fit_percent is None else round(a.fit_percent, 3),
                      "autocorr1": round(a.autocorr1, 4)}
                     for a in self.axes],
            "candidates": [c.as_dict() for c in self.candidates[:top]],
            "n_candidates": len(self.candidates),
            "unseen": list(self.unseen),
            "worst_stretches": [{"t_start_s": a, "t_end_s": b, "rms_ratio": round(r, 3)}
                                for a, b, r in self.worst],
            "fit": {"chi2_red": self.fit.chi2_red, "n_samples": self.fit.n_samples,
                    "n_residuals": self.fit.n_residuals,
                    "held": [h.element for h in self.fit.holds], "notes": list(self.fit.notes)},
            "residual_analysis": None if self.analysis is None else self.analysis.as_dict(),
            "seconds": round(self.seconds, 3),
        }


# --------------------------------------------------------------------------------------
# where it fails: whiteness and cross-correlation with the inputs (as MATLAB's ``resid``)
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

    def _tested(self) -> np.ndarray:
        ok = np.ones((len(self.axes), len(self.inputs)), bool)
        return ok if self.excluded is None else ~self.excluded

    @property
    def band(self) -> float:
        return BAND_Z / np.sqrt(max(self.n, 1))

    @property
    def band_flag(self) -> float:
        from scipy.stats import norm

        tests = max(int(self._tested().sum()) * (2 * self.max_lag + 1), 1)
        return float(norm.isf(0.005 / tests) / np.sqrt(max(self.n, 1)))

    @property
    def band_flag_autocorr(self) -> float:
        from scipy.stats import norm

        return float(norm.isf(0.005 / max(len(self.axes) * self.max_lag, 1)) / np.sqrt(max(self.n, 1)))

    def correlations(self) -> list[InputCorrelation]:
        """Every axis-input pair's strongest correlation, strongest first."""
        out = []
        L = self.max_lag
        ok = self._tested()
        for a, (s, ax) in enumerate(self.axes):
            for i, lab in enumerate(self.inputs):
                if not ok[a, i]:
                    continue
                c = self.xcorr[a, i]
                k = int(np.argmax(np.abs(c)))
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
            "band_99": round(self.band, 5), "band_flag": round(self.band_flag, 5),
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
                                         for i, lab in enumerate(self.inputs) if self._tested()[a, i]}
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
                      exclude: Callable[[str, str], bool] | None = None) -> ResidualAnalysis:
    """Auto- and cross-correlations (biased, 1/N, as MATLAB's ``resid``) of the residuals
    ``E (N, axes)`` and the ``inputs`` (each ``(N,)``), lags -max_lag … max_lag;
    ``exclude(stream, input)`` names pairs not to test."""
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
    return ResidualAnalysis(tuple(axes), tuple(labels), N, float(dt_s), L, ac, X, tuple(const), source, excl)


# --------------------------------------------------------------------------------------
def chi2_total(res: Identification) -> float:
    """Σ r² of a fit's data residuals (noise-weighted)."""
    dof = max(res.n_residuals - int((~res.held).sum()), 1)
    return float(res.chi2_red * dof)


def rms_ratio_of(res: Identification) -> float:
    """The whole model's residual RMS over its noise floor."""
    return float(np.sqrt(chi2_total(res) / max(res.n_residuals, 1)))


def fit_model(model: Model, data: FitData, streams: Sequence[str] | None = None,
              settings: IdentifySettings | None = None,
              attitude0_rad: np.ndarray | None = None, progress=None) -> Identification:
    """``identify`` with the recording's encoder zeros added to ``model``."""
    return identify(with_encoder_zeros(model), data, streams, settings,
                    attitude0_rad=attitude0_rad, progress=progress)


def _problem(fit: Identification, data: FitData, extra: Sequence[Effect], streams: Sequence[str],
             settings: IdentifySettings) -> tuple[_Problem, np.ndarray]:
    base = fit.model.with_values(fit.model_x)
    big = base.with_effects(extra) if extra else base
    att = fit.attitude_rad if fit.attitude_rad is not None else np.zeros(3)
    pb = _Problem(big, data, streams, settings.estimate_attitude, att, encoder_scale=settings.encoder_scale)
    return pb, pb.x0.copy()


def _axes(R: np.ndarray, data: FitData, streams: Sequence[str], model: Model) -> list[AxisFit]:
    """Per sensor axis from the noise-weighted residuals ``R (N, axes)`` (streams in order)."""
    sm = model.stream_models()
    out = []
    i = 0
    for s in streams:
        y = data.counts[s]
        g = np.abs(sm[s].gain)
        sig = np.broadcast_to(data.sigma_counts[s], (y.shape[1],))
        for k in range(y.shape[1]):
            e = R[:, i] * sig[k]  # counts
            i += 1
            spread = np.linalg.norm(y[:, k] - y[:, k].mean())
            # an axis that does not vary beyond its noise has no fit % (MATLAB's would be ~0)
            varies = np.std(y[:, k]) > 3.0 * sig[k]
            fit = 100.0 * (1.0 - np.linalg.norm(e) / spread) if varies else None
            # not centred: an offset is colour too (white residuals have mean zero)
            ac = float(e[1:] @ e[:-1] / max(e @ e, 1e-300)) if len(e) > 2 else 0.0
            out.append(AxisFit(s, sm[s].channels[k], sm[s].unit, float(np.sqrt(np.mean(e**2)) / g[k]),
                               float(sig[k] / g[k]), None if fit is None else float(fit), ac))
    return out


def _features(data: FitData, names: Sequence[str]) -> tuple[list[str], np.ndarray]:
    st = data.state
    labels, cols = [], []
    for j, jn in enumerate(names):
        q = st.q_rad[:, j]
        k = jn[1:] if jn.startswith("j") else jn
        labels += [f"q{k}", f"sin(q{k})", f"cos(q{k})", f"the rate of q{k}"]
        cols += [q, np.sin(q), np.cos(q), st.qd_rad_s[:, j]]
    labels += ["the temperature", "time"]
    cols += [np.broadcast_to(np.asarray(st.temperature_c, float), st.t_s.shape), st.t_s]
    return labels, np.stack(cols, 1)


def _best_correlate(y: np.ndarray, labels: list[str], F: np.ndarray) -> tuple[str, float]:
    yc = y - y.mean()
    Fc = F - F.mean(0)
    den = np.linalg.norm(Fc, axis=0) * np.linalg.norm(yc)
    r = np.divide(Fc.T @ yc, den, out=np.zeros(F.shape[1]), where=den > 1e-12 * max(den.max(), 1e-300))
    i = int(np.argmax(np.abs(r)))
    return labels[i], float(r[i])


def _fmt_value(v: float, units: str) -> str:
    if units.startswith("rad"):
        return f"{np.degrees(v):.2g}°{units[3:]}"
    if units == "g":
        return f"{v * 1000:.3g} mg"
    if units.startswith("1 "):
        return f"{100 * v:.2g} %"
    return f"{v:.3g} {units}"


def params_words(params: dict[str, tuple[float, float]], units: str) -> str:
    """The largest (in σ) three estimates in words: ``y -1.7° ± 0.004°, …``."""
    items = sorted(params.items(), key=lambda kv: -abs(kv[1][0]) / max(kv[1][1], 1e-300))
    parts = [f"{k.split('[')[-1].rstrip(']')} {_fmt_value(v, units)} ± {_fmt_value(s, units)}"
             for k, (v, s) in items[:3]]
    return ", ".join(parts)


def _candidates(model: Model, names: Sequence[str] | None) -> list[Effect]:
    out = []
    for e in all_effects(model.arm, names):
        if e.block_name in model.index or e.block_name in EXCLUDED_CANDIDATES:
            continue
        out.append(e)
    return out


def _sums(pb: _Problem, sub: FitData, z: np.ndarray, cols: np.ndarray, G: np.ndarray, g: np.ndarray,
          res: np.ndarray) -> tuple[float, int]:
    """Add one chunk's ``JᵀJ`` (to ``G``) and ``Jᵀr`` (to ``g``) over the columns ``cols``
    (indices into z), stream by stream with only the columns that reach each stream (most
    candidates reach one sensor: the products stay small); the noise-weighted residuals go
    to ``res (N, axes)``, stream by stream.
    Returns the chunk's ``rᵀr`` and residual count."""
    m = pb.model
    P = pb.P
    spb = _Problem(m, sub, pb.streams, pb.attitude, z[P:], encoder_scale=bool(pb.enc_scale))
    pos = np.full(pb.size, -1)
    pos[cols] = np.arange(len(cols))
    # encoder scale errors: the fit's joint angles come from the encoders (identify's
    # ``_Problem`` scales them); the column is the joint's joint_offset column times
    # -(encoder angle)/(1 + s)
    enc = [(b.name, m.effect(b.name).j) for b in m.blocks
           if b.effect == "encoder_scale" and pos[m.index[b.name].start] >= 0]
    need = {f"{m.arm.joint_names[j]}.joint_offset" for _, j in enc}
    blocks = [b.name for b in m.blocks if np.any(pos[m.index[b.name]] >= 0) or b.name in need]
    st = spb.state(z)
    pred, jac = m.predict_with_jacobian(st, z[:P], spb.streams, blocks=blocks)
    att_cols = [c for c in cols if c >= P]
    att_pred = []
    for c in att_cols:  # the base attitude: forward differences, as identify does
        zz = np.array(z, float)
        zz[c] += 1e-6
        att_pred.append(m.predict(spb.state(zz), z[:P], spb.streams))
    chi2, n_res, col = 0.0, 0, 0
    for s in spb.streams:
        y = pred[s]
        N, k = y.shape
        w = np.broadcast_to(1.0 / sub.sigma_counts[s], (N, k)).ravel()
        r = (y.ravel() - sub.counts[s].ravel()) * w
        parts, idx = [], []
        for b, Jb in jac.get(s, {}).items():
            p = pos[m.index[b]]
            keep = p >= 0
            if keep.any():
                parts.append(Jb.reshape(N * k, -1)[:, keep])
                idx.append(p[keep])
        for b, j in enc:
            off = f"{m.arm.joint_names[j]}.joint_offset"
            if off in jac.get(s, {}):
                c = m.index[b].start
                q_enc = (st.q_rad[:, j] - sub.q_ref_rad[j]) / (1.0 + z[c])
                parts.append((jac[s][off][:, :, 0] * -q_enc[:, None]).reshape(N * k, 1))
                idx.append(np.array([pos[c]]))
        for c, ap in zip(att_cols, att_pred, strict=True):
            parts.append(((ap[s] - y).ravel() / 1e-6)[:, None])
            idx.append(np.array([pos[c]]))
        if parts:
            J = np.concatenate(parts, 1) * w[:, None]
            ix = np.concatenate(idx)
            G[np.ix_(ix, ix)] += J.T @ J
            g[ix] += J.T @ r
        chi2 += float(r @ r)
        n_res += len(r)
        res[:, col:col + k] = r.reshape(N, k)
        col += k
    return chi2, n_res


def _chi2(model: Model, data: FitData, streams: Sequence[str], attitude: bool, x: np.ndarray,
          att: np.ndarray, per: int) -> float:
    """Σr² of the data residuals of ``model`` at ``x`` (and base attitude ``att``), by chunks."""
    total = 0.0
    z = np.concatenate([x, att if attitude else []])
    for a0 in range(0, data.n, per):
        sub = data.subset(slice(a0, a0 + per))
        r = _Problem(model, sub, streams, attitude, att, encoder_scale=True).residual(z)
        total += float(r @ r)
    return total


def diagnose(model: Model, data: FitData, settings: DiagnoseSettings | None = None,
             streams: Sequence[str] | None = None, attitude0_rad: np.ndarray | None = None,
             progress: Callable[[str, float], None] | None = None) -> Diagnosis:
    """Fit ``model`` to ``data`` and rank every library effect it lacks (module docstring).

    ``progress(stage, fraction_done)`` is called as the work advances (0 to 1)."""
    import time

    st = settings or DiagnoseSettings()
    t0 = time.perf_counter()
    say = progress or (lambda _m, _f: None)
    streams = [s for s in (data.counts if streams is None else streams) if s not in FIT_STREAMS_EXCLUDED]
    say("fitting the model", 0.0)
    max_j = st.identify.max_nfev + 1
    if st.prefit_points and data.n > 2 * st.prefit_points:
        # a long recording: the recording's encoder zeros and the base attitude (the nonlinear
        # nuisances, wide priors) first from evenly spread points, so that the fit of the
        # whole recording starts next to its optimum and needs few iterations
        pre = fit_model(model, data.subset(slice(None, None, int(np.ceil(data.n / st.prefit_points)))),
                        streams, st.identify, attitude0_rad,
                        progress=lambda k, _c: say("fitting the model", 0.1 * min(k / max_j, 1.0)))
        zeros = {b.name: pre.x[pre.model.index[b.name]] for b in pre.model.blocks
                 if b.effect == "joint_offset" and b.name not in model.index}
        model = with_encoder_zeros(model).with_values(zeros)
        attitude0_rad = pre.attitude_rad
    fit = fit_model(model, data, streams, st.identify, attitude0_rad,
                    progress=lambda k, _c: say("fitting the model", 0.1 + 0.35 * min(k / max_j, 1.0)))
    m = fit.model
    arm = m.arm
    cands = _candidates(m, st.effects)
    # every candidate's columns at zero (the prediction is unchanged): the score tests
    pb, z = _problem(fit, data, cands, streams, st.identify)
    P0 = m.size
    free_old = np.concatenate([~fit.held[:P0], np.zeros(pb.P - P0, bool), ~fit.held[P0:]])
    fcols = np.flatnonzero(free_old)
    ccols = np.arange(P0, pb.P)
    cols = np.concatenate([fcols, ccols])
    nf = len(fcols)
    # the sums the score tests need, accumulated over chunks of the recording (memory stays
    # bounded on long recordings): JfᵀJf, JfᵀJc, JcᵀJc, Jcᵀr, rᵀr, and each point's Σr²
    n_axes = sum(data.counts[s].shape[1] for s in pb.streams)
    per = max(20, int(st.chunk_rows // max(n_axes, 1)))
    G = np.zeros((len(cols), len(cols)))
    gv = np.zeros(len(cols))
    chi2_now = 0.0
    n_res = 0
    R = np.zeros((data.n, n_axes))
    n_chunks = -(-data.n // per)
    for ci, a0 in enumerate(range(0, data.n, per)):
        say(f"score tests of {len(cands)} candidates", 0.45 + 0.4 * ci / n_chunks)
        c2, nr = _sums(pb, data.subset(slice(a0, a0 + per)), z, cols, G, gv, R[a0:a0 + per])
        chi2_now += c2
        n_res += nr
    A = G[:nf, :nf] + np.diag(1.0 / pb.sigma0[fcols] ** 2)
    B = G[:nf, nf:]
    CC = G[nf:, nf:]
    g_all = gv[nf:]
    AiB = np.linalg.solve(A, B)
    rms_ratio = float(np.sqrt(chi2_now / n_res))
    excess = max(chi2_now - n_res, 1e-300)
    lnn = np.log(n_res)
    K = max(len(cands), 1)
    # the evidence in words is read off a few thousand evenly spread points
    stride = int(np.ceil(data.n / min(per, st.evidence_points)))
    ev = data.subset(slice(None, None, stride)) if stride > 1 else data
    r, Je = _Problem(pb.model, ev, pb.streams, pb.attitude, z[pb.P:],
                     encoder_scale=bool(pb.enc_scale)).jacobian(z, cols)
    Jperp = Je[:, nf:] - Je[:, :nf] @ AiB
    feat_labels, F = _features(ev, arm.joint_names)
    # row -> (stream, axis) map of the evidence points
    sm = m.stream_models()
    row_axis: list[tuple[str, int, int, int]] = []  # stream, k, start, n
    i = 0
    for s in pb.streams:
        n, k = ev.counts[s].shape
        row_axis.append((s, k, i, n))
        i += n * k
    lin = []
    unseen = []
    for e in cands:
        sl = pb.model.index[e.block_name]
        cs = np.arange(sl.start, sl.stop) - P0
        sig_c = pb.sigma0[sl]
        Sp = Jperp[:, cs] * sig_c
        Mc = CC[np.ix_(cs, cs)] - B[:, cs].T @ AiB[:, cs]
        Ms = Mc * np.outer(sig_c, sig_c)
        lam, V = np.linalg.eigh(0.5 * (Ms + Ms.T))
        keep = lam > max(1.0, 1e-9 * lam.max(initial=0.0))
        if not keep.any():
            unseen.append(e.block_name)
            continue
        gs = V[:, keep].T @ (g_all[cs] * sig_c)
        lm = float(np.sum(gs**2 / lam[keep]))
        dof = int(keep.sum())
        step_s = -V[:, keep] @ (gs / lam[keep])  # in prior-σ units
        delta = step_s * sig_c
        lo, hi = pb.lower[sl], pb.upper[sl]
        if np.all(np.clip(delta, lo, hi) == 0.0):
            lm = 0.0  # only a step outside the bounds (a negative play or sag) would help
        delta = np.clip(delta, lo, hi)
        cov = (V[:, keep] / lam[keep]) @ V[:, keep].T * np.outer(sig_c, sig_c)
        lin.append((e, lm, dof, delta, np.sqrt(np.clip(np.diag(cov), 0, None)), Sp @ step_s, Mc, cs))
    lin.sort(key=lambda c: -(c[1] - c[2] * lnn))
    out: list[Candidate] = []
    base_model = m.with_values(fit.model_x)
    rstride = int(np.ceil(data.n / max(st.refit_points, 2)))
    sub = data.subset(slice(None, None, rstride)) if rstride > 1 else data
    n_do = sum(1 for rank, c in enumerate(lin) if rank < st.n_refit
               and min(1.0, chi2_dist.sf(c[1], c[2]) * K) < st.alpha)
    done = 0
    best_after = np.inf
    best_target = None
    rivals = 0
    for rank, (e, lm, dof, delta, dsig, dr, Mc, cs) in enumerate(lin):
        p = float(min(1.0, chi2_dist.sf(lm, dof) * K))
        b = pb.model.block(e.block_name)
        names = b.element_names()
        # only a significant score can be significant; past the first n_refit, go on while no
        # refit has reached the noise (the linearised ranking misleads when the current fit
        # has bent other parameters to take up the missing effect)
        # and refit the rivals of the best so far: effects on the same sensor or joint often
        # explain nearly the same (a turned IMU and its accelerometer's axes on a parked chair)
        rival = best_target == e.target and rivals < st.max_rivals
        refit = p < st.alpha and (rank < st.n_refit or rival or (
            rank < st.max_refit and best_after > st.noise_tolerance))
        if refit and rival and rank >= st.n_refit:
            rivals += 1
        if refit:
            # the quick refit: identify with the candidate added, from the current estimates, on
            # at most ``refit_points`` evenly spread fit points; the residual evaluated exactly
            # at its estimates over the whole recording
            say(f"refitting with {e.block_name}", 0.85 + 0.15 * min(done / max(n_do, 1), 1.0))
            done += 1
            res = identify(base_model.with_effects([e]), sub, streams, st.identify,
                           attitude0_rad=fit.attitude_rad)
            sl2 = res.model.index[e.block_name]
            new_free = int((~res.held[sl2]).sum())
            if sub is data:
                chi2_new = chi2_total(res)
            else:
                att = res.attitude_rad if res.attitude_rad is not None else np.zeros(3)
                chi2_new = _chi2(res.model, data, pb.streams, pb.attitude, res.model_x, att, per)
            shrink = np.sqrt(sub.n / data.n)  # σ of the whole recording from the subsample's
            params = {n: (float(res.x[sl2][q]), float(res.sigma[sl2][q] * shrink))
                      for q, n in enumerate(names)}
            if sub is not data:
                # the subsample's estimates carry its noise into every parameter; where the
                # problem is nearly linear, one Gauss-Newton step from the current fit on the
                # whole recording's sums does better: keep whichever fits the recording better
                sig_c = pb.sigma0[pb.model.index[e.block_name]]
                H = Mc + np.diag(1.0 / sig_c**2)
                Hi = np.linalg.inv(0.5 * (H + H.T))
                dc = np.clip(-Hi @ g_all[cs], b.lower, b.upper)
                dz = np.zeros(pb.size)
                dz[fcols] = -AiB[:, cs] @ dc
                xm = np.concatenate([fit.model_x + dz[:P0], dc])
                chi2_gn = _chi2(base_model.with_effects([e]), data, pb.streams, pb.attitude, xm,
                                z[pb.P:] + dz[pb.P:], per)
                if chi2_gn < chi2_new:
                    chi2_new = chi2_gn
                    infl = max(1.0, chi2_gn / max(n_res - nf - dof, 1))
                    sd = np.sqrt(np.clip(np.diag(Hi), 0, None) * infl)
                    params = {n: (float(dc[q]), float(sd[q])) for q, n in enumerate(names)}
            dbic = chi2_new - chi2_now + new_free * lnn
            rms_after = float(np.sqrt(chi2_new / n_res))
            if rms_after < best_after:
                best_after, best_target = rms_after, e.target
        else:
            dbic = -lm + dof * lnn
            rms_after = None
            params = {n: (float(delta[q]), float(dsig[q])) for q, n in enumerate(names)}
        significant = bool(p < st.alpha and dbic < 0)
        explained = float(min(lm / excess, 1.0)) if chi2_now > n_res else 0.0
        # evidence: the axis the candidate changes most, what its residual follows
        shares = [(float(np.sum(dr[a:a + n * k] ** 2)), s, k, a, n) for s, k, a, n in row_axis]
        best = max(((float(np.sum(dr[a + q::k][:n] ** 2)), s, q, a, n, k)
                    for _, s, k, a, n in shares for q in range(k)), key=lambda t: t[0])
        _, s, q, a, n, k = best
        ra = r[a + q::k][:n]
        da = dr[a + q::k][:n]
        axis_expl = float(1.0 - np.sum((ra + da) ** 2) / max(np.sum(ra**2), 1e-300))
        sensor = sm[s].sensor or s
        axis_name = f"{s if s.startswith('imu') else sensor}'s {sm[s].channels[q]}"
        g_phys = float(np.broadcast_to(data.sigma_counts[s], (k,))[q] / np.abs(sm[s].gain[q]))
        if ra.mean() ** 2 > ra.var():
            follows = (f"is nearly constant ({_fmt_value(float(ra.mean() * g_phys), sm[s].unit)} "
                       f"on average)")
        else:
            lab, corr = _best_correlate(ra, feat_labels, F)
            follows = f"follows {lab} (r = {corr:.2f})"
        evidence = (f"{axis_name} residual {follows}; "
                    f"{EFFECTS[e.name].summary} of {params_words(params, b.units)} "
                    f"explains {100 * max(axis_expl, 0):.0f} % of that axis's residual and "
                    f"{100 * explained:.0f} % of the model's excess over the noise")
        out.append(Candidate(e.name, e.target, lm, dof, p, explained, float(dbic), refit, rms_after,
                             params, b.units, significant, EFFECTS[e.name].description, evidence))
    # ties (effects the recording cannot tell apart, e.g. hard and soft iron on a parked
    # chair): the one with fewer parameters first
    out.sort(key=lambda c: (not c.refitted, float(f"{c.delta_bic:.6g}"), len(c.params)))
    axes = _axes(R, data, pb.streams, m)
    sig = [c for c in out if c.significant]
    if sig:
        verdict = f"missing effect: {sig[0].effect} on {sig[0].target}"
    elif rms_ratio <= st.noise_tolerance:
        verdict = FITS_TO_NOISE
    else:
        verdict = "does not fit the noise, and no effect of the library explains it"
    worst = worst_stretches(np.mean(R**2, 1), data.state.t_s)
    dt = float(np.median(np.diff(data.state.t_s))) if data.n > 1 else 0.0
    analysis = residual_analysis(R, [(a.stream, a.axis) for a in axes],
                                 fit_inputs(data.state, arm.joint_names), dt)
    say("done", 1.0)
    return Diagnosis(fit, data, tuple(axes), rms_ratio, tuple(out), tuple(unseen), verdict,
                     time.perf_counter() - t0, worst, analysis)


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


def parse_add(arm, items: Sequence[str]) -> list[Effect]:
    """``EFFECT[:TARGET]`` -> effects (the target may be omitted where there is only one)."""
    from models.effects import build_effect

    out = []
    for it in items:
        name, _, target = it.partition(":")
        out.append(build_effect(arm, name.strip(), target.strip() or None))
    return out


def add_effects(diag: Diagnosis, effects: Sequence[Effect], settings: DiagnoseSettings | None = None,
                progress=None) -> Diagnosis:
    """Diagnose again with ``effects`` added, starting from ``diag``'s estimates."""
    have = set(diag.fit.model.index)
    new = [e for e in effects if e.block_name not in have]
    model = diag.model.with_effects(new)
    return diagnose(model, diag.data, settings, attitude0_rad=diag.fit.attitude_rad, progress=progress)


def predicted_and_measured(diag: Diagnosis) -> dict[str, tuple]:
    """Per stream: ``(t_s, measured, predicted, unit, channels)`` of the fitted model, in
    physical units (window means), for plots."""
    st = diag.fit
    streams = [f.stream for f in st.fits]
    settings = IdentifySettings(estimate_attitude=st.attitude_rad is not None, encoder_scale=True)
    pb, z = _problem(st, diag.data, [], streams, settings)
    pred = pb.predict(z)
    sm = st.model.stream_models()
    out = {}
    i = 0
    for s in pb.streams:
        shape = diag.data.counts[s].shape
        n = diag.data.counts[s].size
        y = (pb.meas[i:i + n].reshape(shape) - sm[s].zero) / sm[s].gain
        yh = (pred[i:i + n].reshape(shape) - sm[s].zero) / sm[s].gain
        i += n
        out[s] = (diag.data.state.t_s, y, yh, sm[s].unit, sm[s].channels)
    return out


# --------------------------------------------------------------------------------------
# on moving data: the same analysis on the tracker's normalised innovations
INNOVATIONS_WHITE = "innovations white: the model fits the moving recording"


@dataclass(frozen=True)
class InnovationDiagnosis:
    """Whiteness and cross-correlation of the tracker's normalised innovations
    (``L⁻¹ν`` with ``S = LLᵀ``: white, unit variance and following no input when the
    model and its noise are right), and each sensor's mean NIS."""

    analyses: tuple[ResidualAnalysis, ...]
    """One per group of sensors fused at the same instants (the accelerometers; the compass)."""
    nis: dict[str, tuple[float, int, int]]
    """Per sensor: mean NIS, count, degrees of freedom."""
    steps: int
    seconds: float

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
                "analyses": [a.as_dict() for a in self.analyses]}


def chair_moves(arm, rec, rate_rad_s: float = 5 * DEG, share: float = 0.01) -> bool:
    """Whether the chair turns in ``rec``: the IMU gyro reads more than ``rate_rad_s`` (beyond
    its median, the bias) on more than ``share`` of the samples. The fit of :func:`diagnose`
    takes the chair as parked; a moving recording is for :func:`innovation_diagnosis`."""
    from models.sensor_models import stream_models

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


def _shares_noise(stream: str, label: str) -> bool:
    """The chair's acceleration is read off the IMU's accelerometer: not evidence against it."""
    return stream == "imu_acc" and label.startswith("chair accel")


def innovation_inputs(arm, rec, run, t_s: np.ndarray) -> dict[str, np.ndarray]:
    """The inputs at the innovations' instants: each joint's tracked angle, its rate and
    acceleration (from the angle smoothed over 0.2 s), the chair's acceleration (the IMU's
    specific force less gravity at the tracked tilt, base axes, averaged over 0.5 s so that
    the IMU's own noise does not correlate with its innovations) and the temperature."""
    from models.rotations import up_from_tilt
    from models.sensor_models import stream_models

    sm = stream_models(arm)
    tt = np.asarray(run.t_s, float)
    ok = np.all(np.isfinite(run.q_rad), 1)
    tt, q = tt[ok], run.q_rad[ok]
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
        a = _moving_mean(f - up, max(1, int(round(0.5 / max(float(np.median(np.diff(da))), 1e-3)))))
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
    """Run the tracker (``fusion.tracking.tracker``, started on the recording's first still stretch)
    over ``rec`` and analyse its normalised innovations: whiteness per axis and
    cross-correlation with the inputs (:func:`residual_analysis`).

    The innovations are averaged over blocks of ``block_s`` first ("batch means"): a filter's
    innovations carry short-lived colour even when its model is right (the differentiators'
    lag in the motion terms, the encoders' rounding, a gain below the optimum where the
    noise is taken larger than it is), which the block means wash out, while a missing
    effect (a bias that follows the pose, a drift) lasts for seconds and survives."""
    import time

    from fusion.tracking.tracker import start_from_recording
    from models.sensor_models import stream_models

    t0 = time.perf_counter()
    say = progress or (lambda _m, _f: None)
    say("starting the tracker", 0.0)
    tr, _start = start_from_recording(arm, rec, settings, resolve_by_motion_s=20.0)
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
    analyses = []
    for t, members in groups:
        E = np.concatenate([e for _, e, _ in members], 1)
        axes = [(s, f"{s}_{n}") for s, _, names in members for n in names]
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        t, E = _block_means(t, E, max(1, int(round(block_s / max(dt, 1e-9)))))
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        analyses.append(residual_analysis(E, axes, innovation_inputs(arm, rec, run, t), dt, max_lag,
                                          source="tracker innovations", exclude=_shares_noise))
    say("done", 1.0)
    return InnovationDiagnosis(tuple(analyses), tr.nis_stats(), run.steps, time.perf_counter() - t0)
