"""The sigma points of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`: filterpy's scaled
sigma points (:class:`SigmaPoints`: its parameters, weights and point order) made by the
compiled kernel the filter's step uses, and the covariance's symmetrisation and repair.
The unscented transform itself runs in :mod:`armfusion.fusion.tracking.ukf_kernels`; its
NumPy form, the tests' oracle, is :mod:`armfusion.fusion.tracking.ukf_reference`."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.ukf_kernels import sigma_points_into
from filterpy.kalman import MerweScaledSigmaPoints


class SigmaPoints(MerweScaledSigmaPoints):
    """filterpy's scaled sigma points (van der Merwe), made in one compiled call.

    ``sigma_points(x, P)`` returns what filterpy's does (rows of the upper Cholesky factor
    of ``(n + lambda) P``, to round-off), as one ``(2n+1, n)`` array. When ``P`` is not
    numerically positive definite the square root comes from a symmetric
    eigen-decomposition with negative eigenvalues clipped to zero.
    """

    def __init__(self, n: int, alpha: float = 0.5, beta: float = 2.0, kappa: float = 0.0):
        super().__init__(n, alpha, beta, kappa)
        self.lambda_ = alpha**2 * (n + kappa) - n
        self.Wm.setflags(write=False)
        self.Wc.setflags(write=False)
        self._no_noise = np.zeros((n, n))

    @property
    def scale(self) -> float:
        """``n + lambda``: the points sit at ``x ± sqrt(scale) * columns of sqrt(P)``."""
        return self.n + self.lambda_

    def sigma_points(self, x, P) -> np.ndarray:
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.shape[0] != self.n:
            raise ValueError(f"expected size(x) {self.n}, but size is {x.shape[0]}")
        return self.points_of(x, np.atleast_2d(np.asarray(P, dtype=float)))

    def points_of(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """:meth:`sigma_points` for a float ``x (n,)`` and ``P (n, n)`` as they are (no checks)."""
        X = np.empty((2 * self.n + 1, self.n))
        sigma_points_into(X, np.ascontiguousarray(x), np.ascontiguousarray(P), self._no_noise, self.scale)
        return X


def symmetrise(P: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2``."""
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
