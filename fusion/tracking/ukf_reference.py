"""The NumPy reference of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`'s step: the oracle
the compiled kernels (:mod:`armfusion.fusion.tracking.ukf_kernels`) are tested against, and
the filterpy benchmark's helpers. The tracker never imports it (a test says so).

The same filter written with whole-array NumPy operations and LAPACK: the sigma points from
``dpotrf`` (an eigen-decomposition when it fails), the unscented transform with any number
of angle columns, each group's NIS from a solve of its block, the gain from ``dposv`` (a
least-squares solve when ``S`` is not positive definite). Its numbers equal the compiled
filter's to round-off: the two sum the same products in different orders."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from armfusion.fusion.tracking.ukf_groups import GroupPlan, Innovation, MeasurementGroup
from armfusion.fusion.tracking.unscented import SigmaPoints, repair_covariance
from armfusion.models.rotations import wrap_angle
from scipy.linalg import lapack


def sigma_points(points: SigmaPoints, x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Van der Merwe's points ``(2n+1, n)`` of ``x`` and ``P``: rows of the upper Cholesky
    factor of ``scale P`` from LAPACK, or of the clipped eigen-decomposition of its
    symmetric part when that fails."""
    A = points.scale * P
    U, info = lapack.dpotrf(A, lower=0, clean=1)
    if info != 0:
        w, V = np.linalg.eigh(0.5 * (A + A.T))
        U = (V * np.sqrt(np.clip(w, 0.0, None))).T
    n = len(x)
    X = np.empty((2 * n + 1, n))
    X[0] = x
    X[1:n + 1] = x + U
    X[n + 1:] = x - U
    return X


def unscented_mean(Y: np.ndarray, Wm: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
    """Weighted mean of sigma points ``Y (2n+1, k)``; ``angles`` (column indices) are
    averaged as wrapped offsets from the central point."""
    if angles is None or len(angles) == 0:
        return Wm @ Y
    ref = Y[0, angles]
    m = Wm @ Y
    m[angles] = wrap_angle(ref + Wm @ wrap_angle(Y[:, angles] - ref))
    return m


def residuals(Y: np.ndarray, mean: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
    """``Y - mean``, the ``angles`` columns wrapped."""
    d = Y - mean
    if angles is not None and len(angles):
        d[..., angles] = wrap_angle(d[..., angles])
    return d


def unscented_transform(Y, Wm, Wc, noise_cov=None, angles=None):
    """Mean, residuals and covariance of transformed sigma points (plus an additive noise).

    Angle columns are averaged as wrapped offsets from the central point, and their
    residuals are those offsets minus the mean offset (one wrap, no second pass).
    """
    m = Wm @ Y
    D = Y - m
    if angles is not None and len(angles):
        ref = Y[0, angles]
        dA = wrap_angle(Y[:, angles] - ref)
        mA = Wm @ dA
        m[angles] = wrap_angle(ref + mA)
        D[:, angles] = dA - mA
    C = (D.T * Wc) @ D
    if noise_cov is not None:
        C = C + noise_cov
    return m, D, C


def unscented_moments(Y: np.ndarray, Wm: np.ndarray, Wc: np.ndarray, angles: np.ndarray):
    """The mean, residuals, weighted residuals ``D^T * Wc`` and covariance of ``Y``, each
    angle column as the compiled kernel takes it: when its points lie within 3 rad of the
    central one (no wrap between them) their plain mean, then wrapped, and plain residuals;
    else :func:`unscented_transform`'s wrapped offsets."""
    m = Wm @ Y
    D = Y - m
    for a in angles:
        y = Y[:, a]
        dA = y - y[0]
        if np.abs(dA).max() < 3.0:
            m[a] = wrap_angle(float(m[a]))
        else:
            dA = wrap_angle(dA)
            mA = float(Wm @ dA)
            m[a] = wrap_angle(float(y[0]) + mA)
            D[:, a] = dA - mA
    DW = D.T * Wc
    return m, D, DW, DW @ D


def weighted_prediction(Z: np.ndarray, w: np.ndarray, angle_rows) -> np.ndarray:
    """``Σ w_i Z_i`` (``w`` summing to 1), the ``angle_rows`` as the central point plus the
    weighted mean of the wrapped offsets from it."""
    zp = np.asarray(w, float) @ Z
    for a in angle_rows:
        zp[a] = wrap_angle(float(Z[0, a] + np.asarray(w, float) @ wrap_angle(Z[:, a] - Z[0, a])))
    return zp


def group_nis(nu: np.ndarray, S: np.ndarray, rows: Sequence[np.ndarray]) -> np.ndarray:
    """Each group's normalised innovation squared from a solve of its block of ``S`` (a
    one-row block that is not positive, or a singular one: inf)."""
    out = np.empty(len(rows))
    for g, r in enumerate(rows):
        v, B = nu[r], S[np.ix_(r, r)]
        if len(r) == 1:
            out[g] = v[0] ** 2 / B[0, 0] if B[0, 0] > 0 else np.inf
            continue
        try:
            out[g] = v @ np.linalg.solve(B, v)
        except np.linalg.LinAlgError:
            out[g] = np.inf
    return out


def correct(x: np.ndarray, P: np.ndarray, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray,
            hold: np.ndarray | None, gain_mask: np.ndarray | None,
            angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The corrected ``(x, P)`` (``angles``: the angle states' indices)."""
    _, Kt, info = lapack.dposv(S, Pxz.T)  # S is symmetric positive definite
    if info != 0:
        Kt = np.linalg.lstsq(S, Pxz.T, rcond=None)[0]
    K = Kt.T
    if hold is None and gain_mask is None:
        P_new = P - K @ Pxz.T  # the optimal gain: P - K S K^T = P - K Pxz^T
        P_new = 0.5 * (P_new + P_new.T)
    else:  # a held gain is not optimal: the general (Joseph-equivalent) form stays exact
        if hold is not None:
            K = hold @ K
        if gain_mask is not None:
            K = K * gain_mask
        B = (0.5 * (K @ S) - Pxz) @ K.T  # P - K Pxz^T - Pxz K^T + K S K^T = P + B + B^T
        P_new = P + (B + B.T)
    x_new = x + K @ nu
    if len(angles):
        x_new[angles] = wrap_angle(x_new[angles])
    if not P_new.diagonal().min() > 0.0:  # (NaN too)
        P_new = repair_covariance(P_new, 1e-18)
    return x_new, P_new


class ReferenceUKF:
    """:class:`armfusion.fusion.tracking.ukf.BatchedUKF`'s predict, innovate and correct in
    NumPy, for the tests to hold the compiled filter to (same arguments, same results to
    round-off)."""

    def __init__(self, x0: np.ndarray, P0: np.ndarray, points: SigmaPoints | None = None,
                 angle_states: Sequence[int] = ()):
        self.x = np.array(x0, dtype=float).reshape(-1)
        self.P = repair_covariance(np.array(P0, dtype=float))
        n = self.x.shape[0]
        self.points = SigmaPoints(n) if points is None else points
        self.Wm, self.Wc = self.points.Wm, self.points.Wc
        self.angles = np.array(sorted(a % n for a in angle_states), dtype=int)
        self.sigmas: np.ndarray | None = None
        self.sigmas_DW: np.ndarray | None = None

    def set_component(self, index: int, value: float, variance: float) -> None:
        """As :meth:`BatchedUKF.set_component` with a variance."""
        self.x = self.x.copy()
        self.x[index] = value
        self.P = self.P.copy()
        self.P[index, :] = self.P[:, index] = 0.0
        self.P[index, index] = variance
        self.sigmas = None

    def predict(self, fx: Callable[..., np.ndarray], Q: np.ndarray, **kw) -> None:
        """The points of ``P + Q`` through ``fx``, then their unscented transform."""
        Y = fx(sigma_points(self.points, self.x, self.P + Q), **kw)
        m, _, DW, C = unscented_moments(Y, self.Wm, self.Wc, self.angles)
        self.x, self.P, self.sigmas, self.sigmas_DW = m, 0.5 * (C + C.T), Y, DW

    def innovate(self, z: np.ndarray, hx: Callable[..., np.ndarray], R: np.ndarray,
                 groups: Sequence[MeasurementGroup] | GroupPlan | None = None,
                 angle_rows: Sequence[int] = (), X: np.ndarray | None = None,
                 z_weights: np.ndarray | None = None, **kw) -> Innovation:
        """As :meth:`BatchedUKF.innovate`."""
        z, R = np.asarray(z, dtype=float).reshape(-1), np.asarray(R, dtype=float)
        m = z.shape[0]
        groups = [MeasurementGroup("z", np.arange(m))] if groups is None else groups
        plan = groups if isinstance(groups, GroupPlan) else GroupPlan(groups)
        if X is None and self.sigmas is not None:
            X, DXW = self.sigmas, self.sigmas_DW
        else:
            X = sigma_points(self.points, self.x, self.P) if X is None else X
            DXW = residuals(X, self.x, self.angles).T * self.Wc
        Z = hx(X, **kw)
        ang = np.array([a % m for a in angle_rows], dtype=int)
        zp, DZ, _, S = unscented_moments(Z, self.Wm, self.Wc, ang)
        S = S + (np.diag(R) if R.ndim == 1 else R)
        S = 0.5 * (S + S.T)
        if z_weights is not None:
            zp = weighted_prediction(Z, z_weights, ang)
        nu = z - zp
        nu[ang] = wrap_angle(nu[ang])
        nis = group_nis(nu, S, plan.rows)
        ok = np.isfinite(nis) & (nis <= plan.gates)
        return Innovation(plan.names, plan.rows, nu, S, DXW @ DZ, nis, ok, zp)

    def correct(self, inn: Innovation, accept: np.ndarray | None = None,
                hold: np.ndarray | None = None, gain_mask: np.ndarray | None = None) -> bool:
        """As :meth:`BatchedUKF.correct`."""
        ok = (inn.gate_ok if accept is None else np.asarray(accept, dtype=bool)).reshape(-1)
        if not ok.any():
            return False
        use = np.concatenate([r for r, a in zip(inn.rows, ok, strict=True) if a])
        self.x, self.P = correct(self.x, self.P, inn.innovation[use], inn.S[np.ix_(use, use)],
                                 inn.Pxz[:, use], hold, None if gain_mask is None else gain_mask[:, use],
                                 self.angles)
        self.sigmas = None
        return True
