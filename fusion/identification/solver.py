"""The solver of a fit: Levenberg-Marquardt on the normal equations of a
:class:`~armfusion.fusion.identification.problem.FitProblem` (the priors as pseudo-measurements,
bounds by projection), started on a coarse subset of the points when the recording is
long, and each stream's scale, the factor by which its residual exceeds what white noise
at its weights would give.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from armfusion.fusion.identification.problem import CHUNK_POINTS, FitProblem

STEP_TOL_SIGMA = 0.01
"""A solve has converged when its last step moved every element by less than this share of
its σ (the σ the current normal equations give, priors included)."""
COST_TOL = 1e-3
"""... or when it lowered the cost (half the χ²) by less than this."""
COARSE_FACTOR = 4
"""The coarse start (:func:`solve`) fits one point in this many (or fewer: at most one
chunk of points, :data:`~armfusion.fusion.identification.problem.CHUNK_POINTS`)."""
COARSE_MIN_POINTS = 250
"""A recording gets a coarse start when its coarse subset still has this many points."""
COARSE_BLOCK = 8
"""The coarse subset takes the points in runs of this many consecutive points (so a time
derivative, which the time offsets use, is taken between neighbours)."""
LAMBDA0 = 1e-3
"""The first damping of a solve (in units of the normal matrix's diagonal)."""
ACCELERATION_H = 0.1
"""The finite-difference step (a share of the step) of the geodesic acceleration."""
ACCELERATION_MAX = 0.75
"""The largest ``2‖a‖/‖v‖`` (acceleration against velocity, scaled) of an accepted step."""


def coarse_points(n: int, stance: np.ndarray | None, used: np.ndarray | None = None) -> np.ndarray | None:
    """The points of the coarse start: runs of :data:`COARSE_BLOCK` consecutive points, one
    run in every :data:`COARSE_FACTOR` (or more, to keep one chunk of points); ``None`` when
    the subset would be shorter than :data:`COARSE_MIN_POINTS` or would miss a stance among
    its used points (``used``: per point, whether it enters the fit; each stance has its
    own attitude)."""
    if n // COARSE_FACTOR < COARSE_MIN_POINTS:
        return None
    every = max(COARSE_FACTOR, int(np.ceil(n / (CHUNK_POINTS - COARSE_BLOCK))))
    idx = np.flatnonzero((np.arange(n) // COARSE_BLOCK) % every == 0)
    if stance is not None:
        ok = np.ones(n, bool) if used is None else np.asarray(used, bool)
        if np.unique(stance[idx][ok[idx]]).size != np.unique(stance[ok]).size:
            return None
    return idx


def solve(pb: FitProblem, coarse: FitProblem | None, z0: np.ndarray, fcols: np.ndarray,
          w_stream: dict[str, float], max_jac: int, progress: Callable[[int, float], None]
          ) -> tuple[np.ndarray, bool, int]:
    """:func:`levenberg_marquardt` on ``pb``, started (when ``coarse`` is given: the same
    problem on a subset of the points, :func:`coarse_points`) from the coarse problem's
    optimum, which costs a fraction of the Jacobians' time and lands next to the whole
    recording's optimum; the whole recording's solve starts with the coarse one's last
    damping (the valleys are alike: a fresh λ would take a dozen steps to fall to it
    again). ``progress`` sees the coarse solve's cost scaled to the whole
    recording's points. Returns the estimate, whether the last solve converged and the
    Jacobians of the coarse solve."""
    n_coarse = 0
    z = z0
    if coarse is not None:
        f = pb.data.n / coarse.data.n

        def scaled(k, cost):
            progress(k, cost * f)
        z, _, n_coarse, lam = levenberg_marquardt(coarse, z, fcols, w_stream, max_jac, scaled)
    else:
        lam = LAMBDA0
    z, converged, _, _ = levenberg_marquardt(pb, z, fcols, w_stream, max(1, max_jac - n_coarse), progress,
                                             lam)
    return z, converged, n_coarse


class _Linearisation(NamedTuple):
    """A solve's problem linearised at one estimate: the normal equations over the free
    elements with the priors in (``H``, gradient ``g``), the cost there (half the χ²), each
    element's scale ``√H_ii`` (for the damping), each element's σ at these normal equations,
    and, on a problem of one chunk of points, the residuals and their Jacobian (else None)."""

    H: np.ndarray
    g: np.ndarray
    cost: float
    scale: np.ndarray
    sigma: np.ndarray
    r: np.ndarray | None
    J: np.ndarray | None


@dataclass(frozen=True)
class _FreeElements:
    """What stays fixed through one solve: the problem, its free elements ``cols`` with their
    prior (mean, σ) and bounds, the streams' weights, and whether each step gets its geodesic
    acceleration (a problem of one chunk of points, whose Jacobian is kept)."""

    pb: FitProblem
    cols: np.ndarray
    w_stream: dict[str, float]
    mean: np.ndarray
    sigma: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    accelerate: bool

    @classmethod
    def of(cls, pb: FitProblem, fcols: np.ndarray, w_stream: dict[str, float]) -> _FreeElements:
        return cls(pb, fcols, w_stream, pb.x0[fcols], pb.sigma0[fcols], pb.lower[fcols], pb.upper[fcols],
                   pb.data.n <= CHUNK_POINTS)

    def at(self, z: np.ndarray, x: np.ndarray) -> np.ndarray:
        """A copy of the estimate ``z`` with its free elements ``x``, projected onto the bounds."""
        out = z.copy()
        out[self.cols] = np.clip(x, self.lower, self.upper)
        return out

    def residual(self, z: np.ndarray) -> np.ndarray:
        return self.pb.residual_rows(z, self.w_stream)

    def cost(self, z: np.ndarray) -> float:
        """Half the χ² at ``z``: the weighted residuals' and the priors'."""
        r = self.residual(z)
        p = (z[self.cols] - self.mean) / self.sigma
        return 0.5 * float(r @ r + p @ p)

    def linearise(self, z: np.ndarray) -> _Linearisation:
        """The normal equations at ``z`` (accumulated chunk by chunk), the priors added as
        pseudo-measurements."""
        rows: list = []
        H, g, rr = self.pb.normal_equations(z, self.cols, self.w_stream,
                                            rows_out=rows if self.accelerate else None)
        r0 = J = None
        if self.accelerate:
            r0 = np.concatenate([r for r, _ in rows])
            J = np.concatenate([j for _, j in rows])
        x, sd = z[self.cols], self.sigma
        H = H + np.diag(1.0 / sd**2)
        g = g + (x - self.mean) / sd**2
        cost = 0.5 * (rr + float(np.sum(((x - self.mean) / sd) ** 2)))
        scale = np.sqrt(np.clip(np.diag(H), 1e-300, None))
        # each element's σ at these normal equations (in prior units H is well scaled)
        try:
            sigma = np.sqrt(np.clip(np.diag(np.linalg.inv(H * np.outer(sd, sd))), 0, None)) * sd
        except np.linalg.LinAlgError:
            sigma = sd
        return _Linearisation(H, g, cost, scale, sigma, r0, J)

    def trial(self, z: np.ndarray, at: _Linearisation, lam: float) -> tuple[np.ndarray, np.ndarray | None]:
        """The damped step ``v`` from ``z`` (an element at a bound whose gradient pushes it out
        held) and the point it tries: ``z + v``, or, accelerated, ``z + v + a/2``; None when
        the acceleration bends the step too much for its length."""
        x, d = z[self.cols], at.scale
        stuck = ((x <= self.lower) & (at.g > 0)) | ((x >= self.upper) & (at.g < 0))
        move = ~stuck
        Hm = at.H[np.ix_(move, move)] / np.outer(d[move], d[move])
        Hm[np.diag_indices_from(Hm)] += lam
        v = _damped_step(Hm, at.g, move, d)
        if not self.accelerate:
            return v, self.at(z, x + v)
        zh = self.at(z, x + ACCELERATION_H * v)
        vh = (zh[self.cols] - x) / ACCELERATION_H
        rvv = 2.0 / ACCELERATION_H * ((self.residual(zh) - at.r) / ACCELERATION_H - at.J @ vh)
        a = _damped_step(Hm, at.J.T @ rvv, move, d)
        if 2.0 * np.linalg.norm(a * d) <= ACCELERATION_MAX * np.linalg.norm(v * d):
            return v, self.at(z, x + (v + 0.5 * a))
        return v, None  # the step bends too much for its length: shorten it

    def damping_after(self, lam: float, z: np.ndarray, at: _Linearisation, v: np.ndarray,
                      cost_new: float) -> float:
        """The damping after a step that lowered the cost to ``cost_new`` (Nielsen's rule on
        the gain ratio ρ of the plain step ``v``)."""
        x = z[self.cols]
        vs = np.clip(x + v, self.lower, self.upper) - x
        predicted = -float(at.g @ vs + 0.5 * vs @ at.H @ vs)
        rho = (at.cost - cost_new) / predicted if predicted > 0 else 0.0
        return max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-12)


def levenberg_marquardt(pb: FitProblem, z0: np.ndarray, fcols: np.ndarray, w_stream: dict[str, float],
                        max_jac: int, progress: Callable[[int, float], None], lam: float = LAMBDA0
                        ) -> tuple[np.ndarray, bool, int, float]:
    """Levenberg-Marquardt on the normal equations (accumulated chunk by chunk), the priors
    as pseudo-measurements, bounds by projection: an element at a bound whose gradient
    pushes it out stays there for that step.

    * The damping follows each step's gain ratio ρ (Nielsen's rule: ``λ ← λ·max(1/3,
      1 - (2ρ - 1)³)`` after a step that lowers the cost, ``λ ← λν, ν ← 2ν`` after one that
      does not), so a good step is not followed by a trial the cost rejects.
    * On a problem of one chunk of points (the Jacobian kept), each step ``v`` gets its
      geodesic acceleration (Transtrum & Sethna 2012): the residuals' second derivative
      along ``v`` from one more evaluation, ``r_vv ≈ 2/h·((r(x + hv) - r(x))/h - Jv)``, and
      ``a = -(JᵀJ + λD)⁻¹ Jᵀr_vv``; the step is ``v + a/2``, accepted while ``2‖a‖/‖v‖ ≤``
      :data:`ACCELERATION_MAX`. The step then follows a curved valley (a heading against
      the compass's hard iron, a soft iron against the arm's dipoles) instead of its
      tangent, which the cost lets the plain step go only a little way along.

    Returns the estimate, whether it converged (the last step moved every element by less
    than :data:`STEP_TOL_SIGMA` of its σ, or lowered the cost by less than :data:`COST_TOL`), the
    Jacobians it took and the last damping λ (``lam``: the first)."""
    fit = _FreeElements.of(pb, fcols, w_stream)
    z = np.array(z0, float)
    z = fit.at(z, z[fcols])
    nu = 2.0
    for k in range(max(1, max_jac)):
        at = fit.linearise(z)
        progress(k + 1, at.cost)
        while True:
            v, zn = fit.trial(z, at, lam)
            cn = fit.cost(zn) if zn is not None else np.inf
            if cn <= at.cost:
                lam = fit.damping_after(lam, z, at, v, cn)
                nu = 2.0
                step = zn[fcols] - z[fcols]
                z = zn
                if at.cost - cn <= COST_TOL or np.all(np.abs(step) <= STEP_TOL_SIGMA * at.sigma):
                    return z, True, k + 1, lam
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e10:
                return z, True, k + 1, lam  # no step lowers the cost: at the minimum (to rounding)
    return z, False, max(1, max_jac), lam


def _damped_step(Hm: np.ndarray, b: np.ndarray, move: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``-(H + λD)⁻¹ b`` over the moving elements (``Hm``: the damped matrix scaled by ``d``),
    zero for the others."""
    out = np.zeros_like(b)
    try:
        out[move] = -np.linalg.solve(Hm, b[move] / d[move]) / d[move]
    except np.linalg.LinAlgError:
        out[move] = -np.linalg.lstsq(Hm, b[move] / d[move], rcond=None)[0] / d[move]
    return out


def stream_scales(pb: FitProblem, z: np.ndarray) -> dict[str, float]:
    """Per stream: how many times its (weighted) residual exceeds what white noise at the
    weights would give, counting its lag-1 autocorrelation ρ (smooth, unmodelled errors) as
    fewer independent readings, ``√(χ²/n · (1 + ρ)/(1 - ρ))``; at least 1."""
    pred = pb.predict(z)
    out = {}
    i = 0
    used = pb.data.used
    for s in pb.streams:
        c = pb.data.counts[s]
        k = c.size
        r = ((pred[i:i + k] - c.ravel()).reshape(c.shape) / pb.data.sigma_counts[s])
        i += k
        if used is not None:
            r = r[used]
        chi2 = float(np.mean(r**2))
        rc = r - r.mean(0)
        den = np.sum(rc**2, 0)
        rho = float(np.mean(np.sum(rc[1:] * rc[:-1], 0) / np.where(den > 0, den, 1.0))) if len(r) > 2 else 0.0
        rho = min(max(rho, 0.0), 0.95)
        out[s] = float(np.sqrt(max(chi2, 1.0) * (1.0 + rho) / (1.0 - rho))) if chi2 > 1.0 else \
            float(np.sqrt((1.0 + rho) / (1.0 - rho)))
    return out
