"""The sigma points and the unscented transform of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`:
filterpy's scaled sigma points made in one array operation (:class:`SigmaPoints`), the
unscented mean and residuals with angles wrapped about the central point, the transform's
moments (any number of angles, or at most one with the weighted residuals the cross
covariance needs again), and the covariance's repair."""

from __future__ import annotations

import numpy as np
from armfusion.models.rotations import wrap_angle
from filterpy.kalman import MerweScaledSigmaPoints
from scipy.linalg import lapack


class SigmaPoints(MerweScaledSigmaPoints):
    """filterpy's scaled sigma points (van der Merwe), made in one shot.

    ``sigma_points(x, P)`` returns exactly what filterpy's does (rows of the upper
    Cholesky factor of ``(n + lambda) P``), as one ``(2n+1, n)`` array without a loop.
    When ``P`` is not numerically positive definite the square root falls back to a
    symmetric eigen-decomposition with negative eigenvalues clipped to zero.
    """

    def __init__(self, n: int, alpha: float = 0.5, beta: float = 2.0, kappa: float = 0.0):
        super().__init__(n, alpha, beta, kappa)
        self.lambda_ = alpha**2 * (n + kappa) - n
        self.Wm.setflags(write=False)
        self.Wc.setflags(write=False)

    @property
    def scale(self) -> float:
        """``n + lambda``: the points sit at ``x ± sqrt(scale) * columns of sqrt(P)``."""
        return self.n + self.lambda_

    def sqrt_rows(self, P: np.ndarray) -> np.ndarray:
        """Rows ``U[k]`` with ``U^T U = (n + lambda) P`` (filterpy's convention: the upper
        Cholesky factor, here straight from LAPACK's ``dpotrf``)."""
        A = self.scale * P
        U, info = lapack.dpotrf(A, lower=0, clean=1)
        if info == 0:
            return U
        w, V = np.linalg.eigh(0.5 * (A + A.T))
        return (V * np.sqrt(np.clip(w, 0.0, None))).T

    def sigma_points(self, x, P) -> np.ndarray:
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.shape[0] != self.n:
            raise ValueError(f"expected size(x) {self.n}, but size is {x.shape[0]}")
        return self.points_of(x, np.atleast_2d(np.asarray(P, dtype=float)))

    def points_of(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """:meth:`sigma_points` for a float ``x (n,)`` and ``P (n, n)`` as they are (no checks)."""
        U = self.sqrt_rows(P)
        n = self.n
        X = np.empty((2 * n + 1, n))
        X[0] = x
        np.add(x, U, out=X[1:n + 1])
        np.subtract(x, U, out=X[n + 1:])
        return X


# --------------------------------------------------------------------------------------
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


def unscented_moments(Y: np.ndarray, Wm: np.ndarray, WcT: np.ndarray, angle: int | None):
    """:func:`unscented_transform` for at most one angle column, returning also the
    weighted residuals ``D^T * Wc`` (the cross covariance needs them again). When the
    angle's points lie within 3 rad of the central one (no wrap between them, the usual
    case) their plain mean and residuals are the wrapped ones; the mean is then wrapped."""
    m = Wm @ Y
    D = Y - m
    if angle is not None:
        y = Y[:, angle]
        dA = y - y[0]
        if np.abs(dA).max() < 3.0:
            m[angle] = wrap_angle(float(m[angle]))
        else:
            dA = wrap_angle(dA)
            mA = float(Wm @ dA)
            m[angle] = wrap_angle(float(y[0]) + mA)
            dA -= mA
            D[:, angle] = dA
    DW = D.T * WcT
    return m, D, DW, DW @ D


def weighted_prediction(Z: np.ndarray, w: np.ndarray, angle_rows) -> np.ndarray:
    """``Σ w_i Z_i`` (``w`` summing to 1), the ``angle_rows`` as the central point plus the
    weighted mean of the wrapped offsets from it."""
    zp = np.asarray(w, float) @ Z
    for a in angle_rows:
        zp[a] = wrap_angle(float(Z[0, a] + np.asarray(w, float) @ wrap_angle(Z[:, a] - Z[0, a])))
    return zp


def symmetrise(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.T)


def repair_covariance(P: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """``P`` symmetrised, with eigenvalues below ``floor`` raised to it (only if needed)."""
    P = symmetrise(P)
    d = np.diagonal(P)
    if np.all(d > floor):
        try:
            np.linalg.cholesky(P)
            return P
        except np.linalg.LinAlgError:
            pass
    w, V = np.linalg.eigh(P)
    return symmetrise((V * np.clip(w, floor, None)) @ V.T)
