"""A batched sigma-point (unscented) Kalman filter.

Built on filterpy's sigma-point machinery: :class:`SigmaPoints` *is* filterpy's
``MerweScaledSigmaPoints`` (same parameters, same weights ``Wm``/``Wc``, same point
order ``x, x + U[k], x - U[k]``), with the points made in one array operation instead of
filterpy's loop over the state dimension. What differs from filterpy's
``UnscentedKalmanFilter``:

- the process and measurement models are called **once per step with every sigma point**
  (``fx(X (2n+1, n)) -> (2n+1, n)``, ``hx(X) -> (2n+1, m)``), never once per point;
- the update uses the sigma points of the *predicted* covariance (process noise
  included), not the propagated points of the previous posterior;
- the covariance update is the general (Joseph-equivalent) form
  ``P - K Pxz^T - Pxz K^T + K S K^T``, valid for any gain, so a gain with some
  directions held (Schmidt "consider" states, see ``hold``) keeps ``P`` honest; ``P`` is
  symmetrised after every update and repaired (eigenvalue floor) if round-off ever
  makes it indefinite;
- each measurement group (a sensor) is gated on its own normalised innovation squared
  (NIS) before it may enter the update, and every update returns its innovations and
  their covariances (:class:`Innovation`) for the diagnosis workbench;
- the state lives behind read-only properties: nobody pokes ``x`` or ``P``.

Angles in the state or the measurement (a heading) are handled by ``angle_states`` /
``angle_rows``: residuals are wrapped to (-pi, pi] and means taken about the central
sigma point.

The arithmetic of a step runs in compiled kernels (:mod:`armfusion.fusion.tracking.ukf_kernels`, one call per
stage) in the common case: :class:`SigmaPoints`' own points, at most one angle state and
one angle row, a diagonal ``R``, groups that tile the measurement rows, a positive definite
``P + Q`` and ``S``. Everything else takes the NumPy path, which stays the reference the
kernels are tested against (to round-off).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from armfusion.fusion.tracking.ukf_groups import (
    GroupPlan,
    Innovation,
    MeasurementGroup,
    group_nis,
    nis_bound,
)
from armfusion.fusion.tracking.ukf_kernels import (
    DIAGONAL_NOT_POSITIVE,
    NOT_POSITIVE_DEFINITE,
    OK,
    innovation_into,
    kalman_update_into,
    sigma_points_into,
    unscented_moments_into,
)
from armfusion.models.rotations import wrap_angle
from filterpy.kalman import MerweScaledSigmaPoints
from scipy.linalg import lapack

_NONE_2D = np.zeros((0, 0))  # "no hold / no gain mask" for the compiled update


# --------------------------------------------------------------------------------------
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


def _ut(Y: np.ndarray, Wm: np.ndarray, WcT: np.ndarray, angle: int | None):
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


def _weighted_prediction(Z: np.ndarray, w: np.ndarray, angle_rows) -> np.ndarray:
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


class BatchedUKF:
    """An unscented Kalman filter whose models see every sigma point at once.

    ``fx(X, **kw) -> X'`` and ``hx(X, **kw) -> Z`` take and return ``(2n+1, ·)`` arrays.
    ``angle_states`` are the state indices that are angles (wrapped residuals and means).
    """

    def __init__(self, x0: np.ndarray, P0: np.ndarray, points: SigmaPoints | None = None,
                 angle_states: Sequence[int] = ()):
        x0 = np.array(x0, dtype=float).reshape(-1)
        P0 = np.array(P0, dtype=float)
        n = x0.shape[0]
        if P0.shape != (n, n):
            raise ValueError(f"P0 must have shape ({n}, {n}) for a state of size {n}, got {P0.shape}")
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(P0))):
            raise ValueError("initial state and covariance must be finite")
        self.points = SigmaPoints(n) if points is None else points
        if self.points.n != n:
            raise ValueError(f"sigma points are for n = {self.points.n}, the state has {n}")
        self._angles = np.array(sorted(angle_states), dtype=int)
        self._angle1 = int(self._angles[0]) if len(self._angles) == 1 else None
        self._x = x0
        self._P = repair_covariance(P0)
        self._sigmas: np.ndarray | None = None
        self._Wm = self.points.Wm
        self._Wc = self.points.Wc
        # the compiled step (armfusion.fusion.tracking.ukf_kernels) serves the common case: SigmaPoints' own
        # points and at most one angle state; anything else takes the NumPy path below
        sp = type(self.points)
        self._use_kernels = (isinstance(self.points, SigmaPoints) and sp.points_of is SigmaPoints.points_of
                             and sp.sqrt_rows is SigmaPoints.sqrt_rows and len(self._angles) <= 1
                             and (self._angle1 is None or -n <= self._angle1 < n))
        if self._use_kernels:
            self._weights = np.ascontiguousarray(np.stack([self._Wm, self._Wc]), dtype=np.float64)  # (2, N)
            self._angle_index = -1 if self._angle1 is None else self._angle1 % n  # (-1: none)
            self._scale = float(self.points.scale)

    # -- read-only state ------------------------------------------------------------------
    @property
    def n(self) -> int:
        return self._x.shape[0]

    @property
    def x(self) -> np.ndarray:
        v = self._x.copy()
        v.setflags(write=False)
        return v

    @property
    def P(self) -> np.ndarray:
        v = self._P.copy()
        v.setflags(write=False)
        return v

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diagonal(self._P), 0.0, None))

    @property
    def mean(self) -> np.ndarray:
        """The state's mean itself, not a copy (:attr:`x` is a read-only copy): to read within
        a step. The filter replaces the array on every change and never writes into it, so a
        reference keeps the value of its moment; a caller must not write into it either."""
        return self._x

    @property
    def covariance(self) -> np.ndarray:
        """The state's covariance itself, not a copy (:attr:`P` is one); as :attr:`mean`."""
        return self._P

    @property
    def propagated_points(self) -> np.ndarray | None:
        """The sigma points the last :meth:`predict` propagated, ``(2n+1, n)``, while no
        correction has been applied since (None after one, or before any predict)."""
        return self._sigmas

    @property
    def mean_weights(self) -> np.ndarray:
        """The sigma points' weights in the unscented mean, ``(2n+1,)``."""
        return self._Wm

    def sigma_points(self) -> np.ndarray:
        return self.points.sigma_points(self._x, self._P)

    # -- lifecycle ------------------------------------------------------------------------
    def reset(self, x: np.ndarray, P: np.ndarray) -> None:
        """Replace the state (a restart, a restore from a snapshot)."""
        x = np.array(x, dtype=float).reshape(-1)
        P = np.array(P, dtype=float)
        if x.shape != self._x.shape or P.shape != self._P.shape:
            raise ValueError(f"reset: expected x {self._x.shape} and P {self._P.shape}, "
                             f"got {x.shape} and {P.shape}")
        self._x, self._P = x, repair_covariance(P)
        self._sigmas = None

    def recentre(self, x: np.ndarray) -> None:
        """Replace the mean with ``x`` (the same point in other coordinates: an attitude's
        tangent vector folded back into Euler angles about its anchor), keeping the
        covariance and the points this step propagated."""
        x = np.asarray(x, dtype=float)
        if x.shape != self._x.shape:
            raise ValueError(f"recentre: expected a mean of shape {self._x.shape}, got {x.shape}")
        self._x = x

    def inflate(self, index: Sequence[int] | np.ndarray, variance: np.ndarray | float) -> None:
        """Add ``variance`` to the diagonal at ``index`` (a re-acquisition after a slip)."""
        idx = np.asarray(index, dtype=int)
        P = self._P.copy()
        P[idx, idx] += variance
        self._P = P
        self._sigmas = None

    def set_component(self, index: int, value: float, variance: float | None = None) -> None:
        """Set one state (and optionally its variance, decorrelating it from the rest)."""
        x = self._x.copy()
        x[index] = value
        self._x = x
        if variance is not None:
            P = self._P.copy()
            P[index, :] = 0.0
            P[:, index] = 0.0
            P[index, index] = variance
            self._P = P
        self._sigmas = None

    # -- predict ----------------------------------------------------------------------------
    def predict(self, fx: Callable[..., np.ndarray], Q: np.ndarray, **kw) -> None:
        """Propagate every sigma point through ``fx`` in one call.

        The process noise ``Q`` is added to the covariance *before* the sigma points are
        drawn (exact for the additive, near-identity steps of a tracker: one step of a
        random walk or of a slowly decaying state), so the propagated points represent
        the predicted density, noise included, and the next update uses them directly:
        one matrix square root per step, not two.
        """
        if self._use_kernels and self._predict_compiled(fx, Q, kw):
            return
        X = self.points.points_of(self._x, self._P + Q)
        self._propagate(fx(X, **kw))

    def _propagate(self, Y: np.ndarray) -> None:
        """The NumPy unscented transform of the propagated points ``Y`` (any number of angles)."""
        if len(self._angles) <= 1:
            m, D, DW, C = _ut(Y, self._Wm, self._Wc, self._angle1)
        else:
            m, D, C = unscented_transform(Y, self._Wm, self._Wc, None, self._angles)
            DW = D.T * self._Wc
        self._x = m
        C += C.T
        C *= 0.5
        self._P = C
        self._sigmas = Y
        self._sigmas_DW = DW

    def _predict_compiled(self, fx: Callable[..., np.ndarray], Q, kw: dict) -> bool:
        """:meth:`predict` through the compiled kernels: the points from a Cholesky factor of
        ``P + Q``, then the unscented transform of ``fx``'s points. False, with nothing done,
        when ``Q`` is not an ``(n, n)`` matrix or ``P + Q`` is not positive definite (the
        NumPy path and its eigen-decomposition take over)."""
        P = self._P
        Qc = np.ascontiguousarray(Q, dtype=np.float64)
        if Qc.shape != P.shape:
            return False
        n = P.shape[0]
        N = 2 * n + 1
        X = np.empty((N, n))
        if not sigma_points_into(X, self._x, P, Qc, self._scale):
            return False
        Y = fx(X, **kw)
        Yc = np.ascontiguousarray(Y, dtype=np.float64)
        if Yc.shape != X.shape:
            self._propagate(Y)  # (let NumPy say what is wrong with Y)
            return True
        x, P, DW = np.empty(n), np.empty((n, n)), np.empty((n, N))
        unscented_moments_into(Yc, self._weights, self._angle_index, x, P, DW)
        self._x, self._P, self._sigmas, self._sigmas_DW = x, P, Yc, DW
        return True

    def sigma_points_now(self) -> np.ndarray:
        """The sigma points of the current state: those the last predict propagated when no
        correction has happened since, else fresh ones."""
        return self._sigmas if self._sigmas is not None else self.sigma_points()

    # -- update -----------------------------------------------------------------------------
    def innovate(
        self,
        z: np.ndarray,
        hx: Callable[..., np.ndarray],
        R: np.ndarray,
        groups: Sequence[MeasurementGroup] | GroupPlan | None = None,
        angle_rows: Sequence[int] = (),
        X: np.ndarray | None = None,
        z_weights: np.ndarray | None = None,
        **kw,
    ) -> Innovation:
        """Predict ``z (m,)`` through ``hx`` (every sigma point in one call), with noise
        ``R (m, m)`` (or its diagonal ``(m,)``), and test each group against its gate.
        Nothing is applied yet.

        ``groups`` may be a prepared :class:`GroupPlan` (repeated updates of one shape).
        ``X`` may pass sigma points already made from the current state.

        ``z_weights (2n+1,)`` (summing to 1): the weights of the points in the predicted
        measurement that the innovation is taken against, ``ν = z - Σ w_i Z_i`` (angle rows
        as wrapped offsets from the central point); None: the unscented mean's (filterpy's).
        ``(1, 0, …, 0)`` is the prediction at the mean state. ``S`` and the cross covariance
        stay the unscented ones whatever the weights.
        """
        z = np.asarray(z, dtype=float).reshape(-1)
        R = np.asarray(R, dtype=float)
        if groups is None:
            groups = [MeasurementGroup("z", np.arange(z.shape[0]))]
        plan = groups if isinstance(groups, GroupPlan) else GroupPlan(groups)
        if X is None and self._sigmas is not None:
            X, DXW = self._sigmas, self._sigmas_DW
        else:
            X = self.sigma_points() if X is None else X
            DXW = residuals(X, self._x, self._angles).T * self._Wc
        Z = hx(X, **kw)
        if self._use_kernels and R.ndim == 1 and len(angle_rows) <= 1 and plan._tiled:
            a = int(angle_rows[0]) if len(angle_rows) else None
            inn = self._innovation_compiled(z, Z, R, plan, a, DXW, z_weights)
            if inn is not None:
                return inn
        if len(angle_rows) <= 1:
            a = int(angle_rows[0]) if len(angle_rows) else None
            zp, DZ, _, S = _ut(Z, self._Wm, self._Wc, a)
            if R.ndim == 1:
                S.reshape(-1)[::S.shape[0] + 1] += R
            else:
                S += R
            if z_weights is not None:
                zp = _weighted_prediction(Z, z_weights, () if a is None else (a,))
            nu = z - zp
            if a is not None:
                nu[a] = wrap_angle(nu[a])
        else:
            ang = np.asarray(angle_rows, dtype=int)
            zp, DZ, S = unscented_transform(Z, self._Wm, self._Wc, np.diag(R) if R.ndim == 1 else R, ang)
            if z_weights is not None:
                zp = _weighted_prediction(Z, z_weights, ang)
            nu = z - zp
            nu[ang] = wrap_angle(nu[ang])
        Pxz = DXW @ DZ
        nis = plan.nis(nu, S)
        # (a NaN NIS fails any gate; an infinite one fails every finite gate)
        ok = nis <= plan.gates if plan._finite_gates else np.isfinite(nis) & (nis <= plan.gates)
        return Innovation(plan.names, plan.rows, nu, S, Pxz, nis, ok, zp, plan.last_blocks)

    def _innovation_compiled(self, z: np.ndarray, Z: np.ndarray, R: np.ndarray, plan: GroupPlan,
                             angle_row: int | None, DXW: np.ndarray,
                             z_weights: np.ndarray | None = None) -> Innovation | None:
        """:meth:`innovate`'s statistics from the compiled kernel (a diagonal ``R``, a tiled
        plan, at most one angle row); None when the shapes are not those of the common case."""
        Zc = np.ascontiguousarray(Z, dtype=np.float64)
        N, n = self._weights.shape[1], self._x.shape[0]
        m = plan.m
        if Zc.shape != (N, m) or z.shape[0] != m or R.shape[0] != m or DXW.shape != (n, N):
            return None
        if angle_row is None:
            angle_row = -1
        elif -m <= angle_row < m:
            angle_row %= m
        else:
            return None
        G = len(plan.rows)
        z_pred, nu, S, Pxz = np.empty(m), np.empty(m), np.empty((m, m)), np.empty((n, m))
        flat, nis, ok = np.empty(plan._block_size), np.empty(G), np.empty(G, dtype=np.bool_)
        wz = self._weights[0] if z_weights is None else np.ascontiguousarray(z_weights, dtype=np.float64)
        status = innovation_into(Zc, self._weights, wz, angle_row, np.ascontiguousarray(z),
                                 np.ascontiguousarray(R), np.ascontiguousarray(DXW), plan._group_rows,
                                 plan._group_start, plan._block_start, plan._gates_c,
                                 z_pred, nu, S, Pxz, flat, nis, ok)
        blocks = plan.last_blocks = plan._blocks_from(flat)
        if status != OK:  # a block of S is not positive definite: NumPy, block by block
            nis = plan._nis_blocks(nu)
            ok = nis <= plan.gates if plan._finite_gates else np.isfinite(nis) & (nis <= plan.gates)
        return Innovation(plan.names, plan.rows, nu, S, Pxz, nis, ok, z_pred, blocks)

    def correct(self, inn: Innovation, accept: np.ndarray | None = None,
                hold: np.ndarray | None = None, gain_mask: np.ndarray | None = None) -> bool:
        """Apply the groups ``accept`` (default: those that passed their gate).

        ``hold`` is an ``(n, n)`` projection applied to the gain (``K' = hold @ K``): the
        state directions it removes get no correction from this update (Schmidt-Kalman
        "consider" states). ``gain_mask (n, m)`` then zeroes single gain entries (a
        measurement row that may correct only some states). Either way the covariance
        stays consistent through the general form. Returns whether anything was applied.
        """
        ok = (inn.gate_ok if accept is None else np.asarray(accept, dtype=bool)).reshape(-1).tolist()
        if all(ok):
            self._apply(inn.innovation, inn.S, inn.Pxz, hold, gain_mask)
        elif not any(ok):
            return False
        else:
            use = np.concatenate([r for r, a in zip(inn.rows, ok, strict=True) if a])
            self._apply(inn.innovation[use], inn.S[np.ix_(use, use)], inn.Pxz[:, use], hold,
                        None if gain_mask is None else gain_mask[:, use])
        return True

    def update(self, z, hx, R, groups=None, angle_rows=(), hold=None, X=None, gain_mask=None,
               **kw) -> Innovation:
        """:meth:`innovate` then :meth:`correct` with the groups that pass their gates."""
        inn = self.innovate(z, hx, R, groups, angle_rows, X, **kw)
        self.correct(inn, None, hold, gain_mask)
        return inn

    def _apply(self, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray, hold: np.ndarray | None,
               gain_mask: np.ndarray | None = None) -> None:
        if not (self._use_kernels and self._apply_compiled(nu, S, Pxz, hold, gain_mask)):
            self._apply_numpy(nu, S, Pxz, hold, gain_mask)

    def _apply_compiled(self, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray, hold: np.ndarray | None,
                        gain_mask: np.ndarray | None) -> bool:
        """:meth:`_apply` through the compiled kernel; False, with nothing done, when ``S``
        is not positive definite or a shape is not the common case's (``hold (n, n)``,
        ``gain_mask (n, m)``)."""
        n, m = Pxz.shape
        hold_c = _NONE_2D if hold is None else np.ascontiguousarray(hold, dtype=np.float64)
        mask_c = _NONE_2D if gain_mask is None else np.ascontiguousarray(gain_mask, dtype=np.float64)
        if not (m > 0 and nu.shape == (m,) and S.shape == (m, m) and n == self._x.shape[0]
                and (hold is None or hold_c.shape == (n, n))
                and (gain_mask is None or mask_c.shape == (n, m))):
            return False
        x, P = np.empty(n), np.empty((n, n))
        status = kalman_update_into(self._x, self._P, np.ascontiguousarray(nu, dtype=np.float64),
                                    np.ascontiguousarray(S, dtype=np.float64),
                                    np.ascontiguousarray(Pxz, dtype=np.float64), hold_c, mask_c,
                                    self._angle_index, x, P)
        if status == NOT_POSITIVE_DEFINITE:
            return False
        if status == DIAGONAL_NOT_POSITIVE:
            P = repair_covariance(P, 1e-18)
        self._x, self._P = x, P
        self._sigmas = None
        return True

    def _apply_numpy(self, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray, hold: np.ndarray | None,
                     gain_mask: np.ndarray | None = None) -> None:
        """:meth:`_apply` in NumPy: any gain, any angles, an ``S`` that is not positive definite."""
        _, Kt, info = lapack.dposv(S, Pxz.T)  # S is symmetric positive definite
        if info != 0:
            Kt = np.linalg.lstsq(S, Pxz.T, rcond=None)[0]
        K = Kt.T
        if hold is None and gain_mask is None:
            # the optimal gain: P - K S K^T = P - K Pxz^T
            P = self._P - K @ Pxz.T
        else:
            # a held gain is not optimal: the general (Joseph-equivalent) form stays exact
            if hold is not None:
                K = hold @ K
            if gain_mask is not None:
                K = K * gain_mask
            # P - K Pxz^T - Pxz K^T + K S K^T = P + B + B^T with B = (K S / 2 - Pxz) K^T:
            # exactly symmetric as it is summed
            B = K @ S
            B *= 0.5
            B -= Pxz
            B = B @ K.T
            B += B.T
            P = self._P + B
        x = self._x + K @ nu
        a = self._angle1
        if a is not None:
            x[a] = wrap_angle(float(x[a]))
        elif len(self._angles):
            x[self._angles] = wrap_angle(x[self._angles])
        if hold is None and gain_mask is None:
            P += P.T
            P *= 0.5
        if not P.diagonal().min() > 0.0:  # (NaN too)
            P = repair_covariance(P, 1e-18)
        self._x, self._P = x, P
        self._sigmas = None


__all__ = [
    "BatchedUKF", "GroupPlan", "Innovation", "MeasurementGroup", "SigmaPoints", "group_nis", "nis_bound",
    "repair_covariance", "residuals", "symmetrise", "unscented_mean", "unscented_transform", "wrap_angle",
]
