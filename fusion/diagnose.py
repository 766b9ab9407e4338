"""The model workbench: compare the model with the measurements, see where it fails, learn
which physical effect is missing.

``diagnose(model, data)``:

1. **Compare.** Fit the model (its effects, the recording's encoder zeros, the base
   attitude) with :func:`fusion.identify.identify`; per sensor axis the residual RMS
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
   refitted (``identify`` with the candidate added,
   starting from the current estimates): residual RMS after, ΔBIC, the estimated
   parameters with σ. A candidate is **significant** when its corrected p-value is below
   ``alpha`` and its ΔBIC is negative. Each comes with the effect's plain-language
   description and the evidence: which input its residual follows, and how much of the
   residual the candidate explains.

See docs/workbench.md.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2 as chi2_dist

from fusion.identify import (
    FIT_STREAMS_EXCLUDED,
    FitData,
    Identification,
    IdentifySettings,
    _Problem,
    identify,
    with_encoder_zeros,
)
from models.effects import EFFECTS, Effect, Model, all_effects

DEG = np.pi / 180.0
EXCLUDED_CANDIDATES = frozenset({"enc.time_offset"})
"""The encoders are the time reference: their own delay is every other device's."""

FITS_TO_NOISE = "fits to noise"


@dataclass(frozen=True)
class DiagnoseSettings:
    alpha: float = 0.05
    """Family-wise false-alarm rate of the score tests (Bonferroni over the candidates)."""
    n_refit: int = 3
    """Candidates refitted (the best by the linearised ΔBIC whose score test is significant)."""
    noise_tolerance: float = 1.1
    """``rms_ratio`` at or below this counts as noise (the sensor model's floor ±10 %)."""
    chunk_rows: int = 400_000
    """Residual rows per chunk of the score tests' Jacobian (bounds memory: rows × ~200
    candidate columns × 8 bytes; the evidence sentences use one chunk's worth of points)."""
    effects: tuple[str, ...] | None = None
    """Library effects to consider (None: all)."""
    identify: IdentifySettings = field(default_factory=IdentifySettings)


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
            "seconds": round(self.seconds, 3),
        }


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
    pb = _Problem(big, data, streams, settings.estimate_attitude, att)
    return pb, pb.x0.copy()


def _axes(pb: _Problem, z: np.ndarray, data: FitData, model: Model) -> list[AxisFit]:
    pred = pb.predict(z)
    sm = model.stream_models()
    out = []
    i = 0
    for s in pb.streams:
        shape = data.counts[s].shape
        n = data.counts[s].size
        y = pb.meas[i:i + n].reshape(shape)
        yh = pred[i:i + n].reshape(shape)
        i += n
        g = np.abs(sm[s].gain)
        sig = np.broadcast_to(data.sigma_counts[s], (shape[1],))
        for k in range(shape[1]):
            e = yh[:, k] - y[:, k]
            spread = np.linalg.norm(y[:, k] - y[:, k].mean())
            # an axis that does not vary beyond its noise has no fit % (MATLAB's would be ~0)
            varies = np.std(y[:, k]) > 3.0 * sig[k]
            fit = 100.0 * (1.0 - np.linalg.norm(e) / spread) if varies else None
            ec = e - e.mean()
            ac = float(ec[1:] @ ec[:-1] / max(ec @ ec, 1e-300)) if len(e) > 2 else 0.0
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


def diagnose(model: Model, data: FitData, settings: DiagnoseSettings | None = None,
             streams: Sequence[str] | None = None, attitude0_rad: np.ndarray | None = None,
             progress: Callable[[str], None] | None = None) -> Diagnosis:
    """Fit ``model`` to ``data`` and rank every library effect it lacks (module docstring)."""
    import time

    st = settings or DiagnoseSettings()
    t0 = time.perf_counter()
    say = progress or (lambda _m: None)
    streams = [s for s in (data.counts if streams is None else streams) if s not in FIT_STREAMS_EXCLUDED]
    say("fitting the model")
    fit = fit_model(model, data, streams, st.identify, attitude0_rad)
    m = fit.model
    arm = m.arm
    cands = [e for e in all_effects(arm, st.effects)
             if e.block_name not in m.index and e.block_name not in EXCLUDED_CANDIDATES]
    # one Jacobian for every candidate column (all at zero: the prediction is unchanged)
    say(f"score tests of {len(cands)} candidates")
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
    A = np.diag(1.0 / pb.sigma0[fcols] ** 2)
    B = np.zeros((nf, len(ccols)))
    CC = np.zeros((len(ccols), len(ccols)))
    g_all = np.zeros(len(ccols))
    chi2_now = 0.0
    n_res = 0
    ss = np.zeros(data.n)
    for a0 in range(0, data.n, per):
        sub = data.subset(slice(a0, a0 + per))
        rk, Jk = _Problem(pb.model, sub, pb.streams, pb.attitude, z[pb.P:]).jacobian(z, cols)
        Jf, Jc = Jk[:, :nf], Jk[:, nf:]
        A += Jf.T @ Jf
        B += Jf.T @ Jc
        CC += Jc.T @ Jc
        g_all += Jc.T @ rk
        chi2_now += float(rk @ rk)
        n_res += len(rk)
        i = 0
        for s in pb.streams:
            nk, k = sub.counts[s].shape
            ss[a0:a0 + nk] += np.sum(rk[i:i + nk * k].reshape(nk, k) ** 2, 1)
            i += nk * k
    AiB = np.linalg.solve(A, B)
    rms_ratio = float(np.sqrt(chi2_now / n_res))
    excess = max(chi2_now - n_res, 1e-300)
    lnn = np.log(n_res)
    K = max(len(cands), 1)
    # the evidence in words is read off (at most) one chunk's worth of evenly spread points
    stride = int(np.ceil(data.n / per))
    ev = data.subset(slice(None, None, stride)) if stride > 1 else data
    r, Je = _Problem(pb.model, ev, pb.streams, pb.attitude, z[pb.P:]).jacobian(z, cols)
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
        Ms = (CC[np.ix_(cs, cs)] - B[:, cs].T @ AiB[:, cs]) * np.outer(sig_c, sig_c)
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
        lin.append((e, lm, dof, delta, np.sqrt(np.clip(np.diag(cov), 0, None)), Sp @ step_s))
    lin.sort(key=lambda c: -(c[1] - c[2] * lnn))
    out: list[Candidate] = []
    base_model = m.with_values(fit.model_x)
    for rank, (e, lm, dof, delta, dsig, dr) in enumerate(lin):
        p = float(min(1.0, chi2_dist.sf(lm, dof) * K))
        b = pb.model.block(e.block_name)
        names = b.element_names()
        refit = rank < st.n_refit and p < st.alpha  # only a significant score can be significant
        if refit:
            say(f"refitting with {e.block_name}")
            res = identify(base_model.with_effects([e]), data, streams, st.identify,
                           attitude0_rad=fit.attitude_rad)
            sl2 = res.model.index[e.block_name]
            new_free = int((~res.held[sl2]).sum())
            dbic = chi2_total(res) - chi2_now + new_free * lnn
            rms_after = rms_ratio_of(res)
            params = {n: (float(res.x[sl2][q]), float(res.sigma[sl2][q])) for q, n in enumerate(names)}
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
    out.sort(key=lambda c: (not c.refitted, c.delta_bic))
    axes = _axes(pb, z, data, pb.model)
    sig = [c for c in out if c.significant]
    if sig:
        verdict = f"missing effect: {sig[0].effect} on {sig[0].target}"
    elif rms_ratio <= st.noise_tolerance:
        verdict = FITS_TO_NOISE
    else:
        verdict = "does not fit the noise, and no effect of the library explains it"
    worst = worst_stretches(ss / n_axes, data.state.t_s)
    return Diagnosis(fit, data, tuple(axes), rms_ratio, tuple(out), tuple(unseen), verdict,
                     time.perf_counter() - t0, worst)


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
    settings = IdentifySettings(estimate_attitude=st.attitude_rad is not None)
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
