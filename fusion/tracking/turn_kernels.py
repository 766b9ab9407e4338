"""Compiled (numba) cross products of one update's small arrays, each in one call: what
``np.cross`` gives, the same arithmetic in the same order (``a1 b2 - a2 b1``, ...; so the
same numbers to the bit), without its per-call cost (axis handling and temporaries, tens of
microseconds on a 3-vector, paid a few times at every instant).

- :func:`origin_accel_points`: the sigma points' acceleration columns moved from the pivot
  the base turns about to its origin (:meth:`armfusion.fusion.tracking.measurement.Measurements.h_all`);
- :func:`cross_rows`: ``a x b`` row by row for ``(k, 3)`` arrays;
- :func:`cross_vec`: ``a x b`` of two 3-vectors.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.chain_kernels import cross3
from numba import njit


@njit(cache=True, nogil=True)
def _origin_accel_into(X, pivot, accel, w, wd):  # pragma: no cover - compiled
    w0, w1, w2 = w[0], w[1], w[2]
    d0, d1, d2 = wd[0], wd[1], wd[2]
    for i in range(X.shape[0]):
        r0, r1, r2 = X[i, pivot], X[i, pivot + 1], X[i, pivot + 2]
        e0, e1, e2 = cross3(d0, d1, d2, r0, r1, r2)  # ω̇ x r
        c0, c1, c2 = cross3(w0, w1, w2, r0, r1, r2)  # ω x r
        f0, f1, f2 = cross3(w0, w1, w2, c0, c1, c2)  # ω x (ω x r)
        X[i, accel] += e0 + f0
        X[i, accel + 1] += e1 + f1
        X[i, accel + 2] += e2 + f2


def origin_accel_points(X: np.ndarray, pivot: int, accel: int, omega: np.ndarray,
                        omega_dot: np.ndarray) -> np.ndarray:
    """A copy of the points ``X (N, ns)`` whose acceleration columns ``accel:accel+3`` have
    ``ω̇ x r + ω x (ω x r)`` added, ``r`` each point's columns ``pivot:pivot+3`` (``omega``,
    ``omega_dot``: 3-vectors, rad/s and rad/s²)."""
    out = np.array(X, dtype=float, order="C", copy=True)
    _origin_accel_into(out, pivot, accel, np.asarray(omega, dtype=float).reshape(3),
                       np.asarray(omega_dot, dtype=float).reshape(3))
    return out


@njit(cache=True, nogil=True)
def _cross_rows(a, b):  # pragma: no cover - compiled
    out = np.empty((a.shape[0], 3))
    for i in range(a.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = cross3(a[i, 0], a[i, 1], a[i, 2], b[i, 0], b[i, 1], b[i, 2])
    return out


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` row by row, ``(k, 3)`` each (float)."""
    return _cross_rows(np.asarray(a, dtype=float), np.asarray(b, dtype=float))


def cross_vec(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` of two 3-vectors (float), ``(3,)``."""
    return np.array(cross3(*a.tolist(), *b.tolist()))


def turned_back(v: np.ndarray, a: np.ndarray, s: float) -> np.ndarray:
    """``v - s (a x v)`` of two 3-vectors (float), ``(3,)``: a reading ``v`` turned back by a
    rate ``a`` over ``s``. :func:`cross_vec`'s product and NumPy's scaled difference, element
    by element in floats (one array made, not three), so the same numbers."""
    v0, v1, v2 = v.tolist()
    c0, c1, c2 = cross3(*a.tolist(), v0, v1, v2)
    return np.array([v0 - s * c0, v1 - s * c1, v2 - s * c2])
