"""The model workbench: compare the model with the measurements, see where it fails, learn
which physical effect is missing.

``diagnose(model, data)``:

1. **Compare.** Fit the model (its effects, the recording's encoder zeros, the base
   attitude) with :func:`armfusion.fusion.identification.identify.identify`; per sensor axis the residual RMS
   against the noise floor of the sensor model, and the fit in % (NRMSE, as MATLAB's
   ``compare``: ``100 (1 - |y - ŷ| / |y - mean y|)``). ``rms_ratio`` is the whole model's
   residual RMS over its noise floor (1.0: it fits to noise).
2. **Which effect is missing.** Every effect of the library the model lacks, on every
   target it could apply to, is appended at zero (the identity) to one big model; one
   Jacobian evaluation gives all their columns. For each candidate the score
   (Lagrange-multiplier) test: with the weighted residual ``r`` and the candidate's columns
   ``J_c`` with the fitted parameters' columns ``J_f`` projected out (they would re-adjust),
   ``LM = gᵀ M⁺ g``, ``g = J_cᵀ r`` less what the fitted parameters' re-adjustment would
   take of it (the efficient score), ``M = J_c⊥ᵀ J_c⊥``, restricted to the directions the
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
   (:func:`~armfusion.fusion.workbench.whiteness.residual_analysis`, as MATLAB's ``resid``) and the worst
   stretches.

On moving data (the chair driving) :func:`~armfusion.fusion.workbench.innovations.innovation_diagnosis`
runs the same analysis on the tracker's normalised innovations. See docs/workbench.md.

This module is the workbench's entry (:func:`diagnose`, :func:`add_effects`) and its result
(:class:`Diagnosis`); its neighbours hold the parts: ``residuals`` (step 1), ``scores``
(step 2), ``candidates`` (step 3), ``whiteness`` (step 4), ``innovations`` (moving data).
The names other modules import from here are re-exported (``__all__``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from armfusion.fusion.identification.data import FIT_STREAMS_EXCLUDED, FitData, with_encoder_zeros
from armfusion.fusion.identification.result import Identification
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.workbench.candidates import Candidate, at_bound, params_words, rank_candidates
from armfusion.fusion.workbench.gauges import Gauge, structural_gauges
from armfusion.fusion.workbench.heldout import HeldOut, HeldOutFit, judge
from armfusion.fusion.workbench.innovations import (
    INNOVATIONS_WHITE,
    InnovationDiagnosis,
    chair_moves,
    innovation_diagnosis,
    innovation_inputs,
)
from armfusion.fusion.workbench.residuals import (
    AxisFit,
    axis_fits,
    chi2_total,
    fit_model,
    problem_at,
    rms_ratio_of,
)
from armfusion.fusion.workbench.scores import EXCLUDED_CANDIDATES, candidate_effects, score_tests
from armfusion.fusion.workbench.whiteness import (
    InputCorrelation,
    ResidualAnalysis,
    fit_inputs,
    residual_analysis,
    worst_stretches,
)
from armfusion.models.effects import Effect, Model, build_effect
from armfusion.models.effects.library import JointOffset

__all__ = [
    "EXCLUDED_CANDIDATES", "FITS_TO_NOISE", "INNOVATIONS_WHITE", "AxisFit", "Candidate", "DiagnoseSettings",
    "Diagnosis", "InnovationDiagnosis", "InputCorrelation", "ResidualAnalysis", "add_effects", "chair_moves",
    "chi2_total", "diagnose", "fit_inputs", "fit_model", "innovation_diagnosis", "innovation_inputs",
    "params_words", "parse_add", "predicted_and_measured", "residual_analysis", "rms_ratio_of",
    "worst_stretches",
]

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
    start_points: int = 150
    """Where the fit does not reach the noise and the recording's still start has rival
    branches, each rival is tried on this many evenly spread fit points (:func:`best_start`)."""
    start_nfev: int = 10
    start_rival_gain: float = 2.0
    """A rival start replaces the first only where its trial leaves at most ``1 / this`` of the
    first's RMS over the noise: from a wrong basin the fit stays at tens to hundreds of times
    the noise, while between two starts whose fits both miss an effect (discovery's first
    rungs) a small difference says which basin absorbs the missing effect better, not which
    is right (planned sweep, seed 3001 of tools/bench_discover.py: 17.9x against the first's
    19.2x, and the ladder from there ended at 2.4x with nine spurious effects)."""
    """Jacobians each such trial may take (a wrong branch is hundreds of times the noise)."""
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
    gauges: tuple[Gauge, ...] = ()
    """The model's own directions held at their priors (a mount about its own joint's axis)."""
    at_bound: tuple[str, ...] = ()
    """Elements of the model's effects whose estimate ended at the parameter's bound: the
    model does not explain what pulled them there; never written."""
    held_out: HeldOut | None = None
    """The data the fit is judged on (None: judged on nothing but itself)."""
    held_out_fit: HeldOutFit | None = None
    """The fit on the held-out data (None where there is none, or it cannot be judged)."""

    @property
    def held_out_ratio(self) -> float | None:
        """Residual RMS over the noise on the held-out data, at the fit's estimates."""
        return None if self.held_out_fit is None else self.held_out_fit.rms_ratio

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

    def stream_ratios(self) -> dict[str, float]:
        """Per stream, the RMS over its axes of each axis's residual over its noise."""
        return {s: float(np.sqrt(np.mean([a.ratio**2 for a in self.axes if a.stream == s])))
                for s in dict.fromkeys(a.stream for a in self.axes)}

    def measured_noise_ratios(self) -> tuple[float, dict[str, float]]:
        """The residual against the noise the recording itself shows rather than the noise
        model's: each axis's window-mean noise with the single-sample excess the fit
        measured (``FitData.sample_excess_counts``: vibration, say) averaged over the window
        as white noise is. Overall (RMS over the axes) and per stream. Where a ladder stops
        above the model's floor but near 1 here, what is left is noise the datasheet does
        not know, not a missing effect."""
        sm = self.data.sample_excess_counts
        gains = {s: np.abs(m.gain) for s, m in self.fit.model.stream_models().items()}
        seen: dict[str, int] = {}
        ratios: dict[str, list[float]] = {}
        for a in self.axes:
            k = seen[a.stream] = seen.get(a.stream, -1) + 1
            excess = sm.get(a.stream)
            per_sample = 0.0 if excess is None else float(excess[k] / gains[a.stream][k])
            fast = per_sample / np.sqrt(self.data.window)
            ratios.setdefault(a.stream, []).append(a.rms / float(np.hypot(a.noise, fast)))
        per = {s: float(np.sqrt(np.mean(np.square(r)))) for s, r in ratios.items()}
        overall = float(np.sqrt(np.mean(np.square([x for r in ratios.values() for x in r]))))
        return overall, per

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
            "held_out": None if self.held_out is None else {
                "data": self.held_out.label,
                "rms_ratio": None if self.held_out_ratio is None else round(self.held_out_ratio, 4)},
            "gauges": [g.as_dict() for g in self.gauges],
            "at_bound": list(self.at_bound),
            "seconds": round(self.seconds, 3),
        }


def diagnose(model: Model, data: FitData, settings: DiagnoseSettings | None = None,
             streams: Sequence[str] | None = None, attitude0_rad: np.ndarray | None = None,
             progress: Callable[[str, float], None] | None = None,
             held_out: HeldOut | None = None) -> Diagnosis:
    """Fit ``model`` to ``data`` and rank every library effect it lacks (module docstring);
    with ``held_out``, the fit is judged there too (:mod:`armfusion.fusion.workbench.heldout`).

    ``progress(stage, fraction_done)`` is called as the work advances (0 to 1)."""
    st = settings or DiagnoseSettings()
    t0 = time.perf_counter()
    say = progress or (lambda _m, _f: None)
    streams = [s for s in (data.counts if streams is None else streams) if s not in FIT_STREAMS_EXCLUDED]
    fit = _fit(model, data, streams, st, attitude0_rad, say)
    if data.start_rivals_rad:
        better = best_start(model, data, streams, st, rms_ratio_of(fit), attitude0_rad)
        if better is not None:
            fit = _fit(model, better, streams, st, attitude0_rad, say)
        data = better or replace(data, start_rivals_rad=())
    m = fit.model
    cands = candidate_effects(m, st.effects)
    tests = score_tests(fit, data, cands, streams, st.identify, st.chunk_rows, st.evidence_points, say)
    out = rank_candidates(tests, fit, data, streams, st, say)
    R = tests.residuals
    axes = axis_fits(R, data, tests.problem.streams, m)
    sig = [c for c in out if c.significant]
    if sig:
        verdict = f"missing effect: {sig[0].effect} on {sig[0].target}"
    elif tests.rms_ratio <= st.noise_tolerance:
        verdict = FITS_TO_NOISE
    else:
        verdict = "does not fit the noise, and no effect of the library explains it"
    worst = worst_stretches(np.mean(R**2, 1), data.state.t_s)
    dt = float(np.median(np.diff(data.state.t_s))) if data.n > 1 else 0.0
    analysis = residual_analysis(R, [(a.stream, a.axis) for a in axes],
                                 fit_inputs(data.state, m.arm.joint_names), dt)
    gauges = tuple(structural_gauges(m, data))
    bound = tuple(n for b in m.blocks if b.effect != JointOffset.name
                  for n in at_bound({el: float(fit.x[m.index[b.name]][q])
                                     for q, el in enumerate(b.element_names())
                                     if not fit.held[m.index[b.name]][q]}, b))
    judged = None
    if held_out is not None:
        say("judging on the held-out data", 0.98)
        judged = judge(fit, data, held_out, tests.problem.streams, st.identify)
    say("done", 1.0)
    return Diagnosis(fit, data, tuple(axes), tests.rms_ratio, tuple(out), tests.unseen, verdict,
                     time.perf_counter() - t0, worst, analysis, gauges, bound, held_out, judged)


def best_start(model: Model, data: FitData, streams: Sequence[str], st: DiagnoseSettings,
               rms_ratio_now: float, attitude0_rad: np.ndarray | None = None) -> FitData | None:
    """Where the fit from the recording's start pose does not reach the noise
    (``rms_ratio_now`` above ``noise_tolerance``) and the still start has rival branches
    (``data.start_rivals_rad``: e.g. a wrist that reads the same flipped, or a later still
    pose's answer where the start leaves joints untold), each rival is fitted
    on ``start_points`` evenly spread points with at most ``start_nfev`` Jacobians: from the
    wrong branch the fit stays in its basin, with a residual hundreds of times the noise that
    no effect explains (measured: 260-480x on clean random still poses, against 1.0 from the
    right branch; 0.2 s a trial). Returns the data from the rival whose RMS over the noise is
    lowest, if that is below ``rms_ratio_now / start_rival_gain`` (no rivals left; the note
    says which branch was taken), else None."""
    if not data.start_rivals_rad or rms_ratio_now <= st.noise_tolerance:
        return None
    stride = max(1, int(np.ceil(data.n / max(st.start_points, 2))))
    trial = replace(st.identify, max_nfev=st.start_nfev)
    rivals = [data.shifted(q - data.q_ref_rad) for q in data.start_rivals_rad]
    ratios = [rms_ratio_of(fit_model(model, b.subset(slice(None, None, stride)), streams, trial,
                                     attitude0_rad)) for b in rivals]
    k = int(np.argmin(ratios))
    if ratios[k] * st.start_rival_gain >= rms_ratio_now:
        return None
    note = (f"{data.note}; the rival branch {k + 2} of {len(rivals) + 1} (the still start's, then "
            f"later still poses'; the first "
            f"fitted to {rms_ratio_now:.3g}x the noise, this one to {ratios[k]:.3g}x)")
    return replace(rivals[k], start_rivals_rad=(), note=note)


def _fit(model: Model, data: FitData, streams: Sequence[str], st: DiagnoseSettings,
         attitude0_rad: np.ndarray | None, say: Callable[[str, float], None]) -> Identification:
    """Step 1's fit: the model with the recording's encoder zeros and the base attitude."""
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
                 if b.effect == JointOffset.name and b.name not in model.index}
        model = with_encoder_zeros(model).with_values(zeros)
        attitude0_rad = pre.attitude_rad
    return fit_model(model, data, streams, st.identify, attitude0_rad,
                     progress=lambda k, _c: say("fitting the model", 0.1 + 0.35 * min(k / max_j, 1.0)))


def parse_add(arm, items: Sequence[str]) -> list[Effect]:
    """``EFFECT[:TARGET]`` -> effects (the target may be omitted where there is only one)."""
    out = []
    for it in items:
        name, _, target = it.partition(":")
        out.append(build_effect(arm, name.strip(), target.strip() or None))
    return out


def add_effects(diag: Diagnosis, effects: Sequence[Effect], settings: DiagnoseSettings | None = None,
                progress=None) -> Diagnosis:
    """Diagnose again with ``effects`` added, starting from ``diag``'s estimates (judged on the
    same held-out data)."""
    have = set(diag.fit.model.index)
    new = [e for e in effects if e.block_name not in have]
    model = diag.model.with_effects(new)
    return diagnose(model, diag.data, settings, attitude0_rad=diag.fit.attitude_rad, progress=progress,
                    held_out=diag.held_out)


def predicted_and_measured(diag: Diagnosis) -> dict[str, tuple]:
    """Per stream: ``(t_s, measured, predicted, unit, channels)`` of the fitted model, in
    physical units (window means), for plots."""
    st = diag.fit
    streams = [f.stream for f in st.fits]
    settings = IdentifySettings(estimate_attitude=st.attitude_rad is not None, encoder_scale=True)
    pb, z = problem_at(st, diag.data, [], streams, settings)
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
