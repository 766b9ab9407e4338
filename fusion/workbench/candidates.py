"""The candidate effects ranked: the best by their score test refitted (ΔBIC and the
residual after), the rest by their linearised ΔBIC, each with the effect's description and
the evidence in words (which input its residual follows, how much of it the candidate
explains).

A candidate is **significant** when its score test's p-value, Bonferroni-corrected over the
candidates, is below ``alpha`` and its ΔBIC is negative.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from armfusion.fusion.identification.data import FitData
from armfusion.fusion.identification.identify import identify
from armfusion.fusion.identification.problem import FitProblem
from armfusion.fusion.identification.result import Identification
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.workbench.gauges import Gauge, held_elements, structural_gauges
from armfusion.fusion.workbench.residuals import chi2_total
from armfusion.fusion.workbench.scores import Linearised, ScoreTests
from armfusion.models.effects import EFFECTS, Model
from scipy.stats import chi2 as chi2_dist


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
    gauges: tuple[Gauge, ...] = ()
    """Its directions held at the prior in the refit (:mod:`armfusion.fusion.workbench.gauges`)."""
    at_bound: tuple[str, ...] = ()
    """Elements whose refit ended at the parameter's bound: the model does not explain what
    the candidate was pulled to (never significant, never written)."""

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
                "explanation": self.explanation, "evidence": self.evidence,
                "gauges": [g.as_dict() for g in self.gauges], "at_bound": list(self.at_bound)}


@dataclass(frozen=True)
class RefitBasis:
    """What every quick refit of a candidate starts from: the score tests, the fit and its
    model at the estimates, the whole recording and the refits' evenly spread subsample, the
    streams fitted, the identify settings and the model's own held gauges."""

    tests: ScoreTests
    fit: Identification
    base_model: Model
    data: FitData
    sub: FitData
    streams: Sequence[str]
    identify: IdentifySettings
    model_holds: Sequence[str] = ()


def refit_basis(tests: ScoreTests, fit: Identification, data: FitData, streams: Sequence[str],
                settings) -> RefitBasis:
    """The refits' basis (:class:`RefitBasis`): the subsample at most ``settings.refit_points``
    evenly spread fit points, the model's structural gauges held on it."""
    rstride = int(np.ceil(data.n / max(settings.refit_points, 2)))
    sub = data.subset(slice(None, None, rstride)) if rstride > 1 else data
    return RefitBasis(tests, fit, fit.model.with_values(fit.model_x), data, sub, streams, settings.identify,
                      held_elements(structural_gauges(fit.model, sub)))


@dataclass
class _RefitPlan:
    """Which candidates, in the linearised ranking, are refitted: the first ``n_refit``
    significant ones, more while no refit has reached the noise (up to ``max_refit``), and
    the rivals of the best so far on its target (up to ``max_rivals``); what the refits found."""

    settings: Any
    n_do: int
    done: int = 0
    chi2_base: float | None = None
    best_after: float = np.inf
    best_target: str | None = None
    rivals: int = 0

    def refits(self, rank: int, target: str, p: float) -> bool:
        # only a significant score can be significant; past the first n_refit, go on while no
        # refit has reached the noise (the linearised ranking misleads when the current fit
        # has bent other parameters to take up the missing effect)
        # and refit the rivals of the best so far: effects on the same sensor or joint often
        # explain nearly the same (a turned IMU and its accelerometer's axes on a parked chair)
        st = self.settings
        rival = self.best_target == target and self.rivals < st.max_rivals
        refit = p < st.alpha and (rank < st.n_refit or rival or (
            rank < st.max_refit and self.best_after > st.noise_tolerance))
        if refit and rival and rank >= st.n_refit:
            self.rivals += 1
        return refit


def _refitted(basis: RefitBasis, plan: _RefitPlan, c: Linearised,
              say: Callable[[str, float], None]) -> tuple[float, float, dict[str, tuple[float, float]]]:
    """Candidate ``c`` refitted: its ΔBIC, the whole-model RMS over the noise after it, its
    estimates with σ; the plan's best so far updated."""
    tests, e = basis.tests, c.effect
    say(f"refitting with {e.block_name}", 0.85 + 0.15 * min(plan.done / max(plan.n_do, 1), 1.0))
    plan.done += 1
    chi2_new, new_free, params, stepped = _refit(basis, c)
    if plan.chi2_base is None and not stepped:
        plan.chi2_base = _rerun(basis)
    # a refit by identify is measured from the lower of the fit's χ² and the same refit's
    # without the candidate: re-running the fit from its own estimates (priors re-centred
    # there, each stream's scale estimated again, on the same points) moves χ² a little
    # by itself where streams are scaled (tens, at 10x the noise), which is not the
    # candidate's. The Gauss-Newton step moves only the candidate and what it pulls.
    ref = tests.chi2 if stepped else min(tests.chi2, plan.chi2_base)
    dbic = chi2_new - ref + new_free * tests.log_n
    rms_after = float(np.sqrt(chi2_new / tests.n_residuals))
    if rms_after < plan.best_after:
        plan.best_after, plan.best_target = rms_after, e.target
    return dbic, rms_after, params


def rank_candidates(tests: ScoreTests, fit: Identification, data: FitData, streams: Sequence[str],
                    settings, say: Callable[[str, float], None]) -> list[Candidate]:
    """Every candidate the data see, ranked: the best few by the linearised ΔBIC whose score
    test is significant are refitted (more while none reaches the noise, and the rivals of
    the best on its target), the rest keep their linearised ΔBIC. ``settings`` is the
    workbench's :class:`~armfusion.fusion.workbench.diagnose.DiagnoseSettings`. Refitted first, then by
    ΔBIC; ties (effects the recording cannot tell apart, e.g. hard and soft iron on a parked
    chair): the one with fewer parameters first."""
    K, lin = tests.n_candidates, tests.tested
    basis = refit_basis(tests, fit, data, streams, settings)
    plan = _RefitPlan(settings, sum(1 for rank, c in enumerate(lin) if rank < settings.n_refit
                                    and min(1.0, chi2_dist.sf(c.score, c.dof) * K) < settings.alpha))
    sm = fit.model.stream_models()
    out: list[Candidate] = []
    for rank, c in enumerate(lin):
        p = float(min(1.0, chi2_dist.sf(c.score, c.dof) * K))
        refit = plan.refits(rank, c.effect.target, p)
        if refit:
            dbic, rms_after, params = _refitted(basis, plan, c, say)
        else:
            names = tests.problem.model.block(c.effect.block_name).element_names()
            dbic, rms_after = -c.score + c.dof * tests.log_n, None
            params = {n: (float(c.delta[q]), float(c.delta_sigma[q])) for q, n in enumerate(names)}
        out.append(_candidate(tests, c, sm, data, _Judgement(p, float(dbic), refit, rms_after, params),
                              settings.alpha))
    out.sort(key=lambda c: (not c.refitted, float(f"{c.delta_bic:.6g}"), len(c.params)))
    return out


@dataclass(frozen=True)
class _Judgement:
    """What the ranking found of one candidate: its corrected p-value, its ΔBIC, whether it was
    refitted, the RMS over the noise after the refit (None: not refitted), its estimates."""

    p: float
    delta_bic: float
    refitted: bool
    rms_after: float | None
    params: dict[str, tuple[float, float]]


def _candidate(tests: ScoreTests, c: Linearised, sm: dict, data: FitData, j: _Judgement,
               alpha: float) -> Candidate:
    """The ranked candidate ``c``: significant when its corrected p-value is below ``alpha``,
    its ΔBIC negative and no free element at its bound; its evidence in words."""
    e, p, dbic, rms_after, params = c.effect, j.p, j.delta_bic, j.rms_after, j.params
    b = tests.problem.model.block(e.block_name)
    held = set(held_elements(c.gauges))
    bound = at_bound({n: v for n, (v, _s) in params.items() if n not in held}, b)
    significant = bool(p < alpha and dbic < 0 and not bound)
    excess = max(tests.chi2 - tests.n_residuals, 1e-300)
    explained = float(min(c.score / excess, 1.0)) if tests.chi2 > tests.n_residuals else 0.0
    evidence = _evidence(tests, c, sm, data, params, b.units, explained)
    if bound:
        after = (f" and leaves {rms_after:.3g}x the noise" if rms_after is not None
                 else " (the linearised step)")
        where = ", ".join(f"{n.split('[')[-1].rstrip(']')} at {_fmt_value(params[n][0], b.units)}"
                          for n in bound)
        evidence = (f"the model does not explain this: the fit ends at the parameter's bound ({where}) "
                    f"{after}; not significant. {evidence}")
    return Candidate(e.name, e.target, c.score, c.dof, p, explained, dbic, j.refitted, rms_after,
                     params, b.units, significant, EFFECTS[e.name].description, evidence,
                     c.gauges, tuple(bound))


BOUND_SHARE = 0.98
"""An estimate beyond this share of its parameter's bound is at the bound."""


def at_bound(values: dict[str, float], block) -> list[str]:
    """The elements of ``values`` (element name -> estimate, of ``block``) at the block's
    bounds (within ``1 - BOUND_SHARE`` of a non-zero bound)."""
    names = block.element_names()
    out = []
    for n, v in values.items():
        q = names.index(n)
        lo, hi = float(block.lower[q]), float(block.upper[q])
        if (np.isfinite(hi) and hi > 0 and v >= BOUND_SHARE * hi) or (
                np.isfinite(lo) and lo < 0 and v <= BOUND_SHARE * lo):
            out.append(n)
    return out


def _rerun(basis: RefitBasis) -> float:
    """The whole recording's χ² after :func:`_refit`'s identify without a candidate (the same
    start, priors and points): what re-running the fit gives by itself."""
    fit, data, sub = basis.fit, basis.data, basis.sub
    res = identify(basis.base_model, sub, basis.streams, basis.identify, hold=basis.model_holds,
                   attitude0_rad=fit.attitude_rad)
    if sub is data:
        return chi2_total(res)
    att = res.attitude_rad if res.attitude_rad is not None else np.zeros(3)
    pb = basis.tests.problem
    return chi2_of(res.model, data, pb.streams, pb.attitude, res.model_x, att, basis.tests.points_per_chunk)


def _refit(basis: RefitBasis, c: Linearised) -> tuple[float, int, dict[str, tuple[float, float]], bool]:
    """The quick refit of candidate ``c``: identify with it added, from the current estimates,
    on the basis's subsample (at most ``refit_points`` evenly spread fit points); the residual
    evaluated exactly at its estimates over the whole recording. Returns the whole
    recording's χ² after it, the candidate's free elements, its estimates with σ and whether
    the Gauss-Newton step (:func:`_gauss_newton`) gave them rather than identify."""
    tests, fit, data, sub, e = basis.tests, basis.fit, basis.data, basis.sub, c.effect
    pb = tests.problem
    names = pb.model.block(e.block_name).element_names()
    # the candidate's gauges (and the model's own) held at their priors: a direction the fit
    # cannot tell from what it already makes free would wander to wherever the noise takes it
    gauge_held = held_elements(c.gauges)
    res = identify(basis.base_model.with_effects([e]), sub, basis.streams, basis.identify,
                   hold=[*basis.model_holds, *gauge_held], attitude0_rad=fit.attitude_rad)
    sl2 = res.model.index[e.block_name]
    new_free = int((~res.held[sl2]).sum())
    if sub is data:
        chi2_new = chi2_total(res)
    else:
        att = res.attitude_rad if res.attitude_rad is not None else np.zeros(3)
        chi2_new = chi2_of(res.model, data, pb.streams, pb.attitude, res.model_x, att, tests.points_per_chunk)
    shrink = np.sqrt(sub.n / data.n)  # σ of the whole recording from the subsample's
    params = {n: (float(res.x[sl2][q]), float(res.sigma[sl2][q] * shrink))
              for q, n in enumerate(names)}
    stepped = False
    if sub is not data:
        # the subsample's estimates carry its noise into every parameter; where the
        # problem is nearly linear, one Gauss-Newton step from the current fit on the
        # whole recording's sums does better: keep whichever fits the recording better
        chi2_gn, gn_params = _gauss_newton(basis, c, gauge_held)
        if chi2_gn < chi2_new:
            chi2_new, stepped, params = chi2_gn, True, gn_params
    return chi2_new, new_free, params, stepped


def _gauss_newton(basis: RefitBasis, c: Linearised,
                  gauge_held: Sequence[str]) -> tuple[float, dict[str, tuple[float, float]]]:
    """One Gauss-Newton step of candidate ``c`` (its ``gauge_held`` elements at their prior)
    from the current fit on the whole recording's sums: the recording's χ² there, and the
    candidate's estimates with σ (inflated by the χ² per degree of freedom where above 1)."""
    tests, fit, e = basis.tests, basis.fit, c.effect
    pb, z = tests.problem, tests.z
    P0 = fit.model.size
    b = pb.model.block(e.block_name)
    names = b.element_names()
    cs = c.cols
    sig_c = pb.sigma0[pb.model.index[e.block_name]]
    H = c.information + np.diag(1.0 / sig_c**2)
    Hi = np.linalg.inv(0.5 * (H + H.T))
    dc = np.clip(-Hi @ tests.g_candidates[cs], b.lower, b.upper)
    dc[[names.index(h) for h in gauge_held]] = 0.0
    dz = np.zeros(pb.size)
    dz[tests.fcols] = -tests.AiB[:, cs] @ dc
    xm = np.concatenate([fit.model_x + dz[:P0], dc])
    chi2_gn = chi2_of(basis.base_model.with_effects([e]), basis.data, pb.streams, pb.attitude, xm,
                      z[pb.P:] + dz[pb.P:], tests.points_per_chunk)
    infl = max(1.0, chi2_gn / max(tests.n_residuals - len(tests.fcols) - c.dof, 1))
    sd = np.sqrt(np.clip(np.diag(Hi), 0, None) * infl)
    return chi2_gn, {n: (float(dc[q]), float(sd[q])) for q, n in enumerate(names)}


def chi2_of(model: Model, data: FitData, streams: Sequence[str], attitude: bool, x: np.ndarray,
            att: np.ndarray, per: int) -> float:
    """Σr² of the data residuals of ``model`` at ``x`` (and base attitude ``att``), by chunks
    of ``per`` points."""
    total = 0.0
    z = np.concatenate([x, att if attitude else []])
    for a0 in range(0, data.n, per):
        sub = data.subset(slice(a0, a0 + per))
        r = FitProblem(model, sub, streams, attitude, att, encoder_scale=True).residual(z)
        total += float(r @ r)
    return total


# --------------------------------------------------------------------------------------
# the evidence in words
def _evidence(tests: ScoreTests, c: Linearised, sm: dict, data: FitData,
              params: dict[str, tuple[float, float]], units: str, explained: float) -> str:
    """The axis candidate ``c`` changes most, what its residual follows, and how much of it and
    of the model's excess over the noise the candidate explains (``sm``: the fitted model's
    stream models)."""
    e, dr, r = c.effect, c.residual_change, tests.evidence_residual
    shares = [(float(np.sum(dr[a:a + n * k] ** 2)), s, k, a, n) for s, k, a, n in tests.row_axis]
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
        lab, corr = _best_correlate(ra, tests.feature_labels, tests.features)
        follows = f"follows {lab} (r = {corr:.2f})"
    return (f"{axis_name} residual {follows}; "
            f"{EFFECTS[e.name].summary} of {params_words(params, units)} "
            f"explains {100 * max(axis_expl, 0):.0f} % of that axis's residual and "
            f"{100 * explained:.0f} % of the model's excess over the noise")


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
