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

Its parts: the sigma points and the unscented transform in
:mod:`armfusion.fusion.tracking.unscented`, the measurement groups, their gates and the
prepared update plan (with the compiled innovation that reads it) in
:mod:`armfusion.fusion.tracking.ukf_groups`, the correction in
:mod:`armfusion.fusion.tracking.ukf_correct`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from armfusion.fusion.tracking.ukf_correct import correct_compiled, correct_numpy
from armfusion.fusion.tracking.ukf_groups import (
    GroupPlan,
    Innovation,
    MeasurementGroup,
    group_nis,
    nis_bound,
)
from armfusion.fusion.tracking.ukf_kernels import sigma_points_into, unscented_moments_into
from armfusion.fusion.tracking.unscented import (
    SigmaPoints,
    repair_covariance,
    residuals,
    symmetrise,
    unscented_mean,
    unscented_moments,
    unscented_transform,
    weighted_prediction,
)
from armfusion.models.rotations import wrap_angle


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
            m, D, DW, C = unscented_moments(Y, self._Wm, self._Wc, self._angle1)
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
        if self._use_kernels and R.ndim == 1 and len(angle_rows) <= 1 and plan.tiled:
            a = int(angle_rows[0]) if len(angle_rows) else None
            inn = plan.innovation_compiled(z, Z, R, self._weights, z_weights, a, DXW)
            if inn is not None:
                return inn
        if len(angle_rows) <= 1:
            a = int(angle_rows[0]) if len(angle_rows) else None
            zp, DZ, _, S = unscented_moments(Z, self._Wm, self._Wc, a)
            if R.ndim == 1:
                S.reshape(-1)[::S.shape[0] + 1] += R
            else:
                S += R
            if z_weights is not None:
                zp = weighted_prediction(Z, z_weights, () if a is None else (a,))
            nu = z - zp
            if a is not None:
                nu[a] = wrap_angle(nu[a])
        else:
            ang = np.asarray(angle_rows, dtype=int)
            zp, DZ, S = unscented_transform(Z, self._Wm, self._Wc, np.diag(R) if R.ndim == 1 else R, ang)
            if z_weights is not None:
                zp = weighted_prediction(Z, z_weights, ang)
            nu = z - zp
            nu[ang] = wrap_angle(nu[ang])
        Pxz = DXW @ DZ
        nis = plan.nis(nu, S)
        ok = plan.gate_ok(nis)
        return Innovation(plan.names, plan.rows, nu, S, Pxz, nis, ok, zp, plan.last_blocks)

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
        """Correct the state (:mod:`armfusion.fusion.tracking.ukf_correct`): through the compiled
        kernel in the common case, else (or when it declines) in NumPy."""
        out = (correct_compiled(self._x, self._P, nu, S, Pxz, hold, gain_mask, self._angle_index)
               if self._use_kernels else None)
        if out is None:
            self._apply_numpy(nu, S, Pxz, hold, gain_mask)
            return
        self._x, self._P = out
        self._sigmas = None

    def _apply_numpy(self, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray, hold: np.ndarray | None,
                     gain_mask: np.ndarray | None = None) -> None:
        """:meth:`_apply` in NumPy: any gain, any angles, an ``S`` that is not positive definite."""
        self._x, self._P = correct_numpy(self._x, self._P, nu, S, Pxz, hold, gain_mask, self._angles)
        self._sigmas = None


__all__ = [
    "BatchedUKF", "GroupPlan", "Innovation", "MeasurementGroup", "SigmaPoints", "group_nis", "nis_bound",
    "repair_covariance", "residuals", "symmetrise", "unscented_mean", "unscented_transform", "wrap_angle",
]
