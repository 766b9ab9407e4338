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

The arithmetic of a step runs in compiled kernels (:mod:`armfusion.fusion.tracking.ukf_kernels`,
one call per stage), always: any number of angle states and rows, ``R`` full or diagonal,
any groups of rows, a ``P + Q`` or ``S`` that is not positive definite (their own compiled
branches). There is no other run-time path; the NumPy form of the same step,
:mod:`armfusion.fusion.tracking.ukf_reference`, is the oracle the tests hold the kernels to
(to round-off).

Its parts: the sigma points in :mod:`armfusion.fusion.tracking.unscented`, the measurement
groups, their gates and the prepared update plan (with the compiled innovation that reads
it) in :mod:`armfusion.fusion.tracking.ukf_groups`, the correction in
:mod:`armfusion.fusion.tracking.ukf_correct`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.ukf_correct import correct as _correct
from armfusion.fusion.tracking.ukf_groups import (
    GroupPlan,
    Innovation,
    MeasurementGroup,
    nis_bound,
)
from armfusion.fusion.tracking.ukf_kernels import (
    sigma_points_into,
    unscented_moments_into,
    weighted_residuals_into,
)
from armfusion.fusion.tracking.unscented import SigmaPoints, repair_covariance, symmetrise
from armfusion.models.rotations import wrap_angle


class GainLimits(NamedTuple):
    """What an update's gain may not do: ``hold (n, n)``, a projection applied to it (the
    directions it removes get no correction), and ``gain_mask (n, m)``, entries zeroed (a
    row that may correct only some states). None: no limit."""

    hold: np.ndarray | None = None
    gain_mask: np.ndarray | None = None


def _indices(values: Sequence[int], size: int, what: str) -> np.ndarray:
    """``values`` as sorted int64 indices into ``[0, size)`` (negative ones from the end)."""
    out = np.array(sorted({int(v) % size if -size <= int(v) < size else size for v in values}),
                   dtype=np.int64)
    if len(out) and out[-1] >= size:
        raise ValueError(f"{what} {list(values)} must lie within [-{size}, {size})")
    return out


class BatchedUKF:
    """An unscented Kalman filter whose models see every sigma point at once.

    ``fx(X, **kw) -> X'`` and ``hx(X, **kw) -> Z`` take and return ``(2n+1, ·)`` arrays.
    ``angle_states`` are the state indices that are angles (wrapped residuals and means).
    ``points`` are :class:`SigmaPoints` (its ``alpha``, ``beta``, ``kappa``); the filter makes
    them itself in its compiled step.
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
        if type(self.points) is not SigmaPoints:
            raise TypeError(f"points must be SigmaPoints (its alpha, beta, kappa), got "
                            f"{type(self.points).__name__}: the filter makes its points itself")
        if self.points.n != n:
            raise ValueError(f"sigma points are for n = {self.points.n}, the state has {n}")
        self._angles = _indices(angle_states, n, "angle_states")
        self._x = x0
        self._P = repair_covariance(P0)
        self._sigmas: np.ndarray | None = None
        self._sigmas_DW: np.ndarray | None = None
        self._Wm = self.points.Wm
        self._Wc = self.points.Wc
        self._weights = np.ascontiguousarray(np.stack([self._Wm, self._Wc]), dtype=np.float64)  # (2, N)
        self._scale = float(self.points.scale)
        self._no_noise = np.zeros((n, n))
        self._row_angles: dict[tuple, np.ndarray] = {}  # (angle_rows, m) -> their int64 indices

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
        """The sigma points ``(2n+1, n)`` of the current state."""
        X = np.empty((2 * self.n + 1, self.n))
        sigma_points_into(X, self._x, self._P, self._no_noise, self._scale)
        return X

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

        The process noise ``Q (n, n)`` is added to the covariance *before* the sigma points
        are drawn (exact for the additive, near-identity steps of a tracker: one step of a
        random walk or of a slowly decaying state), so the propagated points represent
        the predicted density, noise included, and the next update uses them directly:
        one matrix square root per step, not two.
        """
        P = self._P
        Qc = np.ascontiguousarray(Q, dtype=np.float64)
        if Qc.shape != P.shape:
            raise ValueError(f"Q must have shape {P.shape}, got {Qc.shape}")
        n = P.shape[0]
        N = 2 * n + 1
        X = np.empty((N, n))
        sigma_points_into(X, self._x, P, Qc, self._scale)
        Y = np.ascontiguousarray(fx(X, **kw), dtype=np.float64)
        if Y.shape != X.shape:
            raise ValueError(f"fx returned shape {Y.shape}, expected {X.shape}: every sigma point propagated")
        x, P, DW = np.empty(n), np.empty((n, n)), np.empty((n, N))
        unscented_moments_into(Y, self._weights, self._angles, x, P, DW)
        self._x, self._P, self._sigmas, self._sigmas_DW = x, P, Y, DW

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
            X = self.sigma_points() if X is None else np.ascontiguousarray(X, dtype=np.float64)
            DXW = np.empty((self.n, X.shape[0]))
            weighted_residuals_into(X, self._x, self._angles, self._Wc, DXW)
        Z = hx(X, **kw)
        angles = self._angle_rows(angle_rows, z.shape[0])
        return plan.innovation(z, Z, R, self._weights, z_weights, angles, DXW)

    def _angle_rows(self, angle_rows: Sequence[int], m: int) -> np.ndarray:
        """``angle_rows`` as int64 indices into a measurement of ``m`` rows (kept per shape)."""
        key = (tuple(angle_rows), m)
        rows = self._row_angles.get(key)
        if rows is None:
            rows = self._row_angles[key] = _indices(angle_rows, m, "angle_rows")
        return rows

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

    def update(self, z: np.ndarray, hx: Callable[..., np.ndarray], R: np.ndarray,
               groups: Sequence[MeasurementGroup] | GroupPlan | None = None, angle_rows: Sequence[int] = (),
               X: np.ndarray | None = None, limits: GainLimits | None = None, **kw) -> Innovation:
        """:meth:`innovate` then :meth:`correct` with the groups that pass their gates (the
        gain within ``limits``, None: none)."""
        inn = self.innovate(z, hx, R, groups, angle_rows, X, **kw)
        limits = GainLimits() if limits is None else limits
        self.correct(inn, None, limits.hold, limits.gain_mask)
        return inn

    def _apply(self, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray, hold: np.ndarray | None,
               gain_mask: np.ndarray | None = None) -> None:
        """Correct the state (:mod:`armfusion.fusion.tracking.ukf_correct`)."""
        self._x, self._P = _correct(self._x, self._P, nu, S, Pxz, hold, gain_mask, self._angles)
        self._sigmas = None


__all__ = [
    "BatchedUKF", "GainLimits", "GroupPlan", "Innovation", "MeasurementGroup", "SigmaPoints", "nis_bound",
    "repair_covariance", "symmetrise", "wrap_angle",
]
