"""The score tests: for every library effect the fitted model lacks, how much χ² would fall
if it were added, without a refit.

Every candidate is appended at zero (the identity: the prediction is unchanged) to one big
model, and one Jacobian evaluation, accumulated chunk by chunk over the recording, gives
all their columns. For each candidate the score (Lagrange-multiplier) test: with the
weighted residual ``r`` and the candidate's columns ``J_c`` with the fitted parameters'
columns ``J_f`` projected out (they would re-adjust), ``LM = gᵀ M⁺ g``,
``M = J_c⊥ᵀ J_c⊥``, restricted to the directions the data know better than the candidate's
prior; ``g`` is the efficient score, ``J_cᵀ r`` less what the fitted parameters'
re-adjustment would take of it (:func:`score_tests`). Under "nothing is missing" LM is χ²
with that many degrees of freedom.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from armfusion.fusion.identification.data import FitData
from armfusion.fusion.identification.problem import FitProblem
from armfusion.fusion.identification.result import Identification
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.workbench.gauges import (
    STRUCTURAL_SHARE,
    Gauge,
    candidate_gauges,
    still_jacobian,
    structural_gauges,
)
from armfusion.fusion.workbench.residuals import problem_at
from armfusion.models.effects import Effect, Model, all_effects
from armfusion.models.effects.library import EncoderScale

EXCLUDED_CANDIDATES = frozenset({"enc.time_offset", "enc.time_drift"})
"""The encoders are the time reference: their own delay (and its drift) is every other device's."""


def candidate_effects(model: Model, names: Sequence[str] | None) -> list[Effect]:
    """Every effect of the library (``names``: only those; None: all) on every target it could
    apply to, that ``model`` lacks."""
    out = []
    for e in all_effects(model.arm, names):
        if e.block_name in model.index or e.block_name in EXCLUDED_CANDIDATES:
            continue
        out.append(e)
    return out


class Linearised(NamedTuple):
    """One candidate's score test and its linearised step."""

    effect: Effect
    score: float
    """The LM statistic (0 when only a step outside the bounds would help)."""
    dof: int
    """Directions of its parameters the data see better than its prior."""
    delta: np.ndarray
    """The linearised step of its parameters, clipped to their bounds."""
    delta_sigma: np.ndarray
    residual_change: np.ndarray
    """The step's change of the evidence points' weighted residual."""
    information: np.ndarray
    """``M``: its columns' information with the fitted parameters projected out."""
    cols: np.ndarray
    """Its columns among the candidates' (0 = the first candidate column)."""
    gauges: tuple[Gauge, ...] = ()
    """Its directions the fit cannot tell from what it already makes free (held in a refit;
    :mod:`armfusion.fusion.workbench.gauges`)."""


@dataclass(frozen=True)
class ScoreTests:
    """The score tests of every candidate, and the sums a refit's Gauss-Newton step reuses."""

    problem: FitProblem
    """The fitted model with every candidate appended at zero."""
    z: np.ndarray
    """Its unknowns at the fit (the candidates at zero)."""
    fcols: np.ndarray
    """The fit's free columns."""
    AiB: np.ndarray
    """``A⁻¹B``: the fitted parameters' re-adjustment per unit of each candidate column."""
    g_candidates: np.ndarray
    """``J_cᵀ r`` less the part the fitted parameters would take up, ``(A⁻¹B)ᵀ g_f`` (``g_f``:
    their gradient, data and prior; zero at an unscaled optimum): the efficient score."""
    chi2: float
    """Σ r² of the fit over the whole recording."""
    n_residuals: int
    residuals: np.ndarray
    """``(points, axes)``: the noise-weighted residuals, stream by stream."""
    points_per_chunk: int
    n_candidates: int
    tested: tuple[Linearised, ...]
    """The candidates the data see, best linearised ΔBIC first."""
    unseen: tuple[str, ...]
    """Candidates the recording cannot see at all (no direction known beyond the prior)."""
    evidence_residual: np.ndarray
    """The weighted residual at the evidence points (a few thousand, evenly spread)."""
    feature_labels: list[str]
    features: np.ndarray
    """What a residual may follow, at the evidence points (:func:`features`)."""
    row_axis: list[tuple[str, int, int, int]]
    """Per stream of the evidence rows: ``(stream, axes, first row, points)``."""

    @property
    def rms_ratio(self) -> float:
        return float(np.sqrt(self.chi2 / self.n_residuals))

    @property
    def log_n(self) -> float:
        """ln of the residual count: BIC's price of a parameter."""
        return np.log(self.n_residuals)


def features(data: FitData, names: Sequence[str]) -> tuple[list[str], np.ndarray]:
    """What a residual may follow, at the fit points: each joint's angle, its sine and cosine
    and its rate, the temperature and time."""
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


@dataclass(frozen=True)
class _Projection:
    """The information the score tests share: the candidates' ``JcᵀJc`` (``CC``), the fitted
    parameters' cross terms (``B``) and ``A⁻¹B`` (``A``: the fitted parameters' information
    with their priors), in the problem ``pb``; ``fcols``: the fitted parameters' columns of
    ``z``, ``P0``: the model's size (the candidates' columns follow it)."""

    pb: FitProblem
    CC: np.ndarray
    B: np.ndarray
    AiB: np.ndarray
    fcols: np.ndarray
    P0: int


def _accumulated(pb: FitProblem, data: FitData, z: np.ndarray, cols: np.ndarray, per: int,
                 say: Callable[[str, float], None], n_cands: int) -> tuple[np.ndarray, np.ndarray, float, int,
                                                                          np.ndarray]:
    """The sums the score tests need over the columns ``cols``, accumulated over chunks of
    ``per`` points of the recording (memory stays bounded on long recordings): ``JᵀJ``,
    ``Jᵀr``, ``rᵀr``, the residual count, and each point's noise-weighted residuals."""
    n_axes = sum(data.counts[s].shape[1] for s in pb.streams)
    G = np.zeros((len(cols), len(cols)))
    gv = np.zeros(len(cols))
    chi2_now = 0.0
    n_res = 0
    R = np.zeros((data.n, n_axes))
    n_chunks = -(-data.n // per)
    for ci, a0 in enumerate(range(0, data.n, per)):
        say(f"score tests of {n_cands} candidates", 0.45 + 0.4 * ci / n_chunks)
        c2, nr = _sums(pb, data.subset(slice(a0, a0 + per)), z, cols, G, gv, R[a0:a0 + per])
        chi2_now += c2
        n_res += nr
    return G, gv, chi2_now, n_res, R


def _row_axis(pb: FitProblem, ev: FitData) -> list[tuple[str, int, int, int]]:
    """Row -> (stream, axes, first row, points) of the evidence points' residual."""
    row_axis: list[tuple[str, int, int, int]] = []
    i = 0
    for s in pb.streams:
        n, k = ev.counts[s].shape
        row_axis.append((s, k, i, n))
        i += n * k
    return row_axis


def score_tests(fit: Identification, data: FitData, cands: Sequence[Effect], streams: Sequence[str],
                identify_settings: IdentifySettings, chunk_rows: int, evidence_points: int,
                say: Callable[[str, float], None]) -> ScoreTests:
    """Every candidate's score test at the fit ``fit`` (module docstring); ``chunk_rows``
    residual rows per chunk of the Jacobian, the evidence read off ``evidence_points``."""
    m = fit.model
    pb, z = problem_at(fit, data, cands, streams, identify_settings)
    P0 = m.size
    free_old = np.concatenate([~fit.held[:P0], np.zeros(pb.P - P0, bool), ~fit.held[P0:]])
    fcols = np.flatnonzero(free_old)
    cols = np.concatenate([fcols, np.arange(P0, pb.P)])
    nf = len(fcols)
    n_axes = sum(data.counts[s].shape[1] for s in pb.streams)
    per = max(20, int(chunk_rows // max(n_axes, 1)))
    G, gv, chi2_now, n_res, R = _accumulated(pb, data, z, cols, per, say, len(cands))
    A = G[:nf, :nf] + np.diag(1.0 / pb.sigma0[fcols] ** 2)
    B = G[:nf, nf:]
    proj = _Projection(pb, G[nf:, nf:], B, np.linalg.solve(A, B), fcols, P0)
    # the efficient score: the candidates' gradient less what re-adjusting the fitted
    # parameters would take of it. The fit is at its optimum with each stream at its own
    # weight (identify scales down a stream it fits worse than its noise), not at the
    # optimum of the datasheet χ² the tests measure: where a stream was scaled, the fitted
    # parameters' gradient (data and prior) is not zero and ignoring it misreads the
    # candidates (a turned IMU whose turn the base attitude took from the down-weighted
    # links' side). At an unscaled optimum it is zero and this changes nothing.
    free_fit = np.flatnonzero(~fit.held)
    g_fit = gv[:nf] + (fit.x[free_fit] - fit.x0[free_fit]) / pb.sigma0[fcols] ** 2
    g_all = gv[nf:] - proj.AiB.T @ g_fit
    # the evidence in words is read off a few thousand evenly spread points
    stride = int(np.ceil(data.n / min(per, evidence_points)))
    ev = data.subset(slice(None, None, stride)) if stride > 1 else data
    r, Je = FitProblem(pb.model, ev, pb.streams, pb.attitude, z[pb.P:],
                       encoder_scale=bool(pb.enc_scale)).jacobian(z, cols)
    Jperp = Je[:, nf:] - Je[:, :nf] @ proj.AiB
    feat_labels, F = features(ev, m.arm.joint_names)
    # the model's own structure, in still poses: the fit's columns with each candidate's
    still = still_jacobian(pb.model, ev)
    fit_held = {pb.names[i] for i in range(P0) if fit.held[i]}
    lin, unseen = [], []
    for e in cands:
        one = _linearised(proj, e, Jperp, g_all, (ev, still, fit_held))
        if one is None:
            unseen.append(e.block_name)
        else:
            lin.append(one)
    lin.sort(key=lambda c: -(c.score - c.dof * np.log(n_res)))
    return ScoreTests(pb, z, fcols, proj.AiB, g_all, chi2_now, n_res, R, per, max(len(cands), 1), tuple(lin),
                      tuple(unseen), r, feat_labels, F, _row_axis(pb, ev))


def _linearised(proj: _Projection, e: Effect, Jperp: np.ndarray, g_all: np.ndarray,
                structure: tuple[FitData, tuple, set[str]]) -> Linearised | None:
    """Candidate ``e``'s score test (None: the data see none of its directions): its score and
    dof, its linearised step with σ and the residual's change along it, its information with
    the fitted parameters projected out, its gauges. ``structure``: the evidence points, the
    model's still Jacobian on them (:func:`still_jacobian`) and the fit's held elements."""
    ev, (Js, jnames, _), fit_held = structure
    pb, P0, AiB, CC = proj.pb, proj.P0, proj.AiB, proj.CC
    sl = pb.model.index[e.block_name]
    cs = np.arange(sl.start, sl.stop) - P0
    sig_c = pb.sigma0[sl]
    Sp = Jperp[:, cs] * sig_c
    Mc = CC[np.ix_(cs, cs)] - proj.B[:, cs].T @ AiB[:, cs]
    Ms = Mc * np.outer(sig_c, sig_c)
    lam, V = np.linalg.eigh(0.5 * (Ms + Ms.T))
    keep = lam > max(1.0, 1e-9 * lam.max(initial=0.0))
    if not keep.any():
        return None
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
    jc = np.r_[0:P0, sl.start:sl.stop]
    own = structural_gauges(pb.model, ev, [jnames[i] for i in range(sl.start, sl.stop)], fit_held,
                            (Js[:, jc], [jnames[i] for i in jc], None))
    gauges = _gauges(proj, e.block_name, V[:, ~keep] * sig_c[:, None], Mc, cs, own)
    return Linearised(e, lm, dof, delta, np.sqrt(np.clip(np.diag(cov), 0, None)), Sp @ step_s, Mc, cs, gauges)


def _gauges(proj: _Projection, block: str, V_null: np.ndarray, Mc: np.ndarray, cs: np.ndarray,
            own: list[Gauge]) -> tuple[Gauge, ...]:
    """A candidate's gauges: those of the model's structure (``own``) first, then the directions
    the score test left out (``V_null``, in the block's units: the data know them no better
    than the prior once the fitted parameters are projected out), each named with the fitted
    parameters that take it up (``A⁻¹B`` along it, in their prior σ). ``Mc``: the candidate's
    information with them projected out; ``cs``: its columns among the candidates'."""
    pb, fcols = proj.pb, proj.fcols
    CC, AiB_c = proj.CC[np.ix_(cs, cs)], proj.AiB[:, cs]
    out: list[Gauge] = list(own)
    dirs, structural, partners = [], [], []
    el = pb.model.block(block).element_names()
    U = np.array([[dict(g.direction)[n] for n in el] for g in own]).T if own else np.zeros((len(el), 0))
    for k in range(V_null.shape[1]):
        v = V_null[:, k]
        v = v / max(float(np.linalg.norm(v)), 1e-300)
        if U.shape[1]:  # already held by the structure: what is left of it
            v = v - U @ np.linalg.lstsq(U, v, rcond=None)[0]
            if np.linalg.norm(v) < 0.5:
                continue
            v = v / np.linalg.norm(v)
        raw = float(v @ CC @ v)
        structural.append(raw > 0 and float(v @ Mc @ v) <= STRUCTURAL_SHARE * raw)
        a = np.abs(AiB_c @ v) / pb.sigma0[fcols]
        top = np.argsort(-a)[:4]
        partners.append([pb.names[fcols[i]].split("[")[0] for i in top if a[i] >= 0.3 * a.max() > 0])
        dirs.append(v)
    if dirs:
        held_own = [g.held for g in own]
        V = np.column_stack(dirs)
        out += candidate_gauges(pb.model, block, V, structural, partners, held_own)
    return tuple(out)


def _sums(pb: FitProblem, sub: FitData, z: np.ndarray, cols: np.ndarray, G: np.ndarray, g: np.ndarray,
          res: np.ndarray) -> tuple[float, int]:
    """Add one chunk's ``JᵀJ`` (to ``G``) and ``Jᵀr`` (to ``g``) over the columns ``cols``
    (indices into z), stream by stream with only the columns that reach each stream (most
    candidates reach one sensor: the products stay small); the noise-weighted residuals go
    to ``res (N, axes)``, stream by stream.
    Returns the chunk's ``rᵀr`` and residual count."""
    m = pb.model
    P = pb.P
    spb = FitProblem(m, sub, pb.streams, pb.attitude, z[P:], encoder_scale=bool(pb.enc_scale))
    pos = np.full(pb.size, -1)
    pos[cols] = np.arange(len(cols))
    # encoder scale errors: the fit's joint angles come from the encoders (identify's
    # ``FitProblem`` scales them); the column is the joint's joint_offset column times
    # -(encoder angle)/(1 + s)
    enc = [(b.name, m.effect(b.name).j) for b in m.blocks
           if b.effect == EncoderScale.name and pos[m.index[b.name].start] >= 0]
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

