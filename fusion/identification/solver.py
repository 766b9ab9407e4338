"""The solver of a fit: Levenberg-Marquardt on the normal equations of a
:class:`~fusion.identification.problem.FitProblem` (the priors as pseudo-measurements,
bounds by projection), and each stream's scale, the factor by which its residual exceeds
what white noise at its weights would give.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fusion.identification.problem import FitProblem


def levenberg_marquardt(pb: FitProblem, z0: np.ndarray, fcols: np.ndarray, w_stream: dict[str, float],
                        max_jac: int, progress: Callable[[int, float], None]) -> tuple[np.ndarray, bool]:
    """Levenberg-Marquardt on the normal equations (accumulated chunk by chunk), the priors
    as pseudo-measurements, bounds by projection: an element at a bound whose gradient
    pushes it out stays there for that step. Returns the estimate and whether it converged
    (the cost lowered by less than 0.05, a tenth of a unit of χ², or every step below 1e-3
    of its prior σ)."""
    mu, sd = pb.x0[fcols], pb.sigma0[fcols]
    lo, hi = pb.lower[fcols], pb.upper[fcols]
    meas, w = pb.measurements(None, None, w_stream)

    def cost(z):
        r = (pb.predict(z) - meas) * w
        p = (z[fcols] - mu) / sd
        a = pb.reference_residual(z)
        return 0.5 * float(r @ r + p @ p + a @ a)

    z = np.array(z0, float)
    z[fcols] = np.clip(z[fcols], lo, hi)
    lam = 1e-3
    c = None
    for k in range(max(1, max_jac)):
        H, g, rr = pb.normal_equations(z, fcols, w_stream)
        x = z[fcols]
        H = H + np.diag(1.0 / sd**2)
        g = g + (x - mu) / sd**2
        c = 0.5 * (rr + float(np.sum(((x - mu) / sd) ** 2)))
        progress(k + 1, c)
        d = np.sqrt(np.clip(np.diag(H), 1e-300, None))
        while True:
            stuck = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
            move = ~stuck
            dx = np.zeros_like(x)
            Hm = H[np.ix_(move, move)] / np.outer(d[move], d[move])
            Hm[np.diag_indices_from(Hm)] += lam
            try:
                dx[move] = -np.linalg.solve(Hm, g[move] / d[move]) / d[move]
            except np.linalg.LinAlgError:
                dx[move] = -np.linalg.lstsq(Hm, g[move] / d[move], rcond=None)[0] / d[move]
            zn = z.copy()
            zn[fcols] = np.clip(x + dx, lo, hi)
            cn = cost(zn)
            if cn <= c:
                lam = max(lam / 5.0, 1e-9)
                step = np.max(np.abs(zn[fcols] - x) / sd)
                z = zn
                if c - cn <= max(1e-7 * c, 0.05) or step < 1e-3:
                    return z, True
                break
            lam *= 5.0
            if lam > 1e10:
                return z, True  # no step lowers the cost: at the minimum (to rounding)
    return z, False


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
