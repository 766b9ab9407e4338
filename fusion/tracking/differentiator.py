"""Causal differentiation: the joint rates and accelerations from the encoders, the base's
angular acceleration from the gyro, by a least-squares polynomial through the last few
samples (no sample after the instant it is evaluated at).

:class:`CausalDifferentiator` is what the filter uses, sample by sample, both live and over
a recording (compiled: :func:`armfusion.fusion.tracking.frame_kernels.push_fit`).
:func:`causal_poly_fit` and :func:`causal_fits` are the same fit in NumPy, batched over
windows: the reference the tests hold the compiled fit to, and the benchmark baseline's
inputs (tools/bench_track.py).
"""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.frame_kernels import extrapolate_fit, poly_fit_one, push_fit, push_fits


def causal_poly_fit(t_win: np.ndarray, y_win: np.ndarray, t_eval: np.ndarray, order: int = 2) -> np.ndarray:
    """Least-squares polynomial through each window, evaluated at ``t_eval``.

    ``t_win (K, W)``, ``y_win (K, W, d)``, ``t_eval (K,)`` -> ``(K, 3, d)``: value, first and
    second derivative (zero for ``order`` 1). Batched over K windows; windows only hold
    samples at or before their evaluation time (causal). ``order`` is capped by W - 1.
    """
    t_win = np.asarray(t_win, float)
    K, W = t_win.shape
    order = int(min(order, W - 1))
    out = np.zeros((K, 3, y_win.shape[-1]))
    if W == 1 or order == 0:
        out[:, 0] = y_win[:, -1]
        return out
    tau = t_win - t_eval[:, None]
    h = np.maximum(tau[:, -1] - tau[:, 0], 1e-9)[:, None]  # the window's span (oldest first)
    s = tau / h
    A = np.stack([s**k for k in range(order + 1)], -1)  # (K, W, order+1)
    AtA = np.einsum("kwi,kwj->kij", A, A)
    Aty = np.einsum("kwi,kwd->kid", A, y_win)
    c = np.linalg.solve(AtA, Aty)  # (K, order+1, d)
    out[:, 0] = c[:, 0]
    out[:, 1] = c[:, 1] / h
    if order >= 2:
        out[:, 2] = 2.0 * c[:, 2] / h**2
    return out


def derivative_noise_gain(t: np.ndarray, order: int) -> float:
    """How much unit white noise on the samples ``t`` puts on the causal fit's first
    derivative at the last sample (the norm of its weights)."""
    W = len(t)
    order = int(min(order, W - 1))
    tau = t - t[-1]
    h = max(abs(tau[0]), 1e-9)
    A = np.stack([(tau / h) ** k for k in range(order + 1)], -1)
    w = np.linalg.pinv(A)[1] / h  # weights of the derivative estimate
    return float(np.linalg.norm(w))


class CausalDifferentiator:
    """Sample-by-sample causal polynomial fit over the last ``window`` samples."""

    def __init__(self, dim: int, window: int, order: int):
        self.window, self.order, self.dim = int(window), int(order), int(dim)
        self._t = np.full(self.window, np.nan)
        self._y = np.zeros((self.window, dim))
        self._n = 0
        self._fit = None  # (3, d) at self._t_last
        self._t_last = -np.inf
        self._no_fit = np.zeros((3, dim))

    def push(self, t: float, y: np.ndarray) -> None:
        """Take one sample (its window shifts in place) and fit the window at it (compiled:
        :func:`armfusion.fusion.tracking.frame_kernels.push_fit`, :func:`causal_poly_fit` for one window)."""
        self._n = min(self._n + 1, self.window)
        self._fit = push_fit(self._t, self._y, float(t), np.asarray(y, dtype=float).reshape(self.dim),
                             self._n, self.order)
        self._t_last = t

    def push_block(self, t: np.ndarray, y: np.ndarray, pushed: np.ndarray) -> tuple:
        """A block of B instants ``t`` at once (compiled: :func:`armfusion.fusion.tracking.frame_kernels.push_fits`):
        where ``pushed[b]``, :meth:`push` ``(t[b], y[b])``; at every instant, what :meth:`at`
        and :attr:`latest` would then give. Returns ``(at (B, 3, d), latest (B, 3, d), have
        (B,))``, ``have[b]`` False where there was no sample yet (those rows zero)."""
        fit = self._no_fit if self._fit is None else self._fit
        at, latest, have, fit, t_last, n = push_fits(self._t, self._y, t, y, pushed, self._n, self.order,
                                                     fit, float(self._t_last), self._fit is not None)
        if self._fit is not None or have.any():
            self._fit, self._t_last, self._n = fit, t_last, n
        return at, latest, have

    @property
    def latest(self) -> np.ndarray | None:
        """Value, rate and acceleration ``(3, d)`` at the last sample."""
        return self._fit

    def at(self, t: float) -> np.ndarray | None:
        """Value, rate and acceleration ``(3, d)`` at ``t`` (extrapolated from the last fit)."""
        if self._fit is None:
            return None
        return extrapolate_fit(self._fit, float(t - self._t_last))

    def snapshot(self) -> dict:
        return {"t": self._t.tolist(), "y": self._y.tolist(), "n": self._n}

    def restore(self, snap: dict) -> None:
        self._t = np.array(snap["t"], float)
        self._y = np.array(snap["y"], float)
        self._n = int(snap["n"])
        if self._n:
            w = self._n
            order = self.order if w > self.order else w - 1
            self._fit = poly_fit_one(self._t[-w:], self._y[-w:], float(self._t[-1]), order) \
                if w >= 2 else np.stack([self._y[-1], np.zeros(self.dim), np.zeros(self.dim)])
            self._t_last = float(self._t[-1])


def causal_fits(t: np.ndarray, y: np.ndarray, window: int, order: int) -> np.ndarray:
    """What :class:`CausalDifferentiator` gives after each sample, for a whole stream at
    once: ``(N, 3, d)`` (vectorised over samples)."""
    t = np.asarray(t, float)
    y = np.asarray(y, float).reshape(len(t), -1)
    N, d = y.shape
    out = np.zeros((N, 3, d))
    if N == 0:
        return out
    out[0, 0] = y[0]
    W = int(window)
    for k in range(1, min(W - 1, N)):  # the first windows are partial
        w = k + 1
        o = order if w > order else w - 1
        out[k] = causal_poly_fit(t[None, :w], y[None, :w], t[k:k + 1], o)[0]
    if N >= W:
        from numpy.lib.stride_tricks import sliding_window_view

        tw = sliding_window_view(t, W)  # (N-W+1, W)
        yw = np.moveaxis(sliding_window_view(y, W, axis=0), -1, 1)  # (N-W+1, W, d)
        o = order if W > order else W - 1
        for a in range(0, tw.shape[0], 20000):
            b = min(tw.shape[0], a + 20000)
            out[W - 1 + a:W - 1 + b] = causal_poly_fit(tw[a:b], yw[a:b], tw[a:b, -1], o)
    return out


def prime(diff: CausalDifferentiator, t: np.ndarray, y: np.ndarray, t_now: float) -> None:
    """Fill ``diff`` with the last window of samples ``(t, y)`` at or before ``t_now``."""
    k = int(np.searchsorted(t, t_now + 1e-9))
    for j in range(max(0, k - diff.window), k):
        diff.push(float(t[j]), y[j])
