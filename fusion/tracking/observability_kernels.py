"""The observability of the joint offsets, compiled (numba): what
:meth:`armfusion.fusion.tracking.observability.Observability.update` recomputes 20 times a second.

The arithmetic is small (a 7×7 information matrix, its eigen-decomposition, a few
projections) but, written as some thirty NumPy calls, cost the tracker a tenth of its time
in interpreter overhead. :func:`offsets_observability` does the same arithmetic in one
compiled call. tests/fusion/test_observability_kernels.py holds it to the equations written
out in NumPy.

Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def offsets_observability(axes, up, lock_deg, motion_mps2, base_mps2, K, R_0S, sel, coef, P_offsets,
                          weak_info, wide_var, blind, axis_deg, locked, wide,
                          achievable):  # pragma: no cover - compiled
    """The offsets' observability at one instant, for ``n`` joints and the ``S'`` link
    accelerometers ``sel``.

    In: ``axes (n, 3)`` the joint axes in the base frame; ``up (3,)`` the base frame's up;
    ``lock_deg`` the angle to vertical below which an axis counts as gimbal-locked (its
    margin for the tilt's doubt included); ``motion_mps2 (S, 3)`` each link accelerometer's
    motion acceleration; ``base_mps2 (3,)`` the base's acceleration less gravity; ``K (n, 3, 3)``
    each axis's cross-product matrix; ``R_0S (S, 3, 3)`` each sensor's orientation;
    ``coef (S', 3, n)`` the factor that turns a Jacobian row into an information row;
    ``P_offsets (n, n)`` the filter's offset covariance; ``weak_info`` the information below
    which a direction is weak; ``wide_var`` the variance above which a locked joint is wide;
    ``blind (n,)`` the joints another test found gravity-blind (locked whatever ``up`` says).

    Out (written): ``axis_deg (n,)`` each axis's angle to vertical; ``locked (n,)``;
    ``wide (n,)`` locked and known no better than ``wide_var``; ``achievable (n,)`` the sigma
    the window's information alone would give each offset (inf where it gives none: a
    direction with an eigenvalue below 1e-12 of the largest is unread).

    Returns ``(W, U)``: the information rows ``W (3S', n)`` (the Jacobian of each reading
    with respect to the offsets over its sigma, times sqrt(rate * window)) and an orthonormal
    basis ``U (n, h)`` of the directions to hold (``h = 0``: none): the weak directions that
    the window would not read better than the filter already knows them, and the locked
    joints.
    """
    n = axes.shape[0]
    _axes_to_vertical(axes, up, lock_deg, blind, axis_deg, locked)
    W = _information_rows(sel, motion_mps2, base_mps2, K, R_0S, coef, n)
    info = W.T @ W
    lam, V = np.linalg.eigh(info)
    _achievable_sigmas(lam, V, achievable)
    weak = _weak_directions(lam, V, P_offsets, weak_info)
    for j in range(n):
        wide[j] = locked[j] and P_offsets[j, j] > wide_var
    return W, _held_basis(V, weak, locked)


@njit(cache=True, nogil=True, inline="always")
def _axes_to_vertical(axes, up, lock_deg, blind, axis_deg, locked):  # pragma: no cover - compiled
    """Each joint axis's angle to vertical ``axis_deg (n,)`` and whether it is locked (within
    ``lock_deg``, or ``blind``), written."""
    for j in range(axes.shape[0]):
        c = abs(axes[j, 0] * up[0] + axes[j, 1] * up[1] + axes[j, 2] * up[2])
        axis_deg[j] = math.degrees(math.acos(min(c, 1.0)))
        locked[j] = axis_deg[j] < lock_deg or blind[j]


@njit(cache=True, nogil=True, inline="always")
def _information_rows(sel, motion_mps2, base_mps2, K, R_0S, coef, n):  # pragma: no cover - compiled
    """The information rows ``W (3S', n)``: each selected reading's Jacobian with respect to
    the offsets (its turn about each axis, in the sensor's axes), times ``coef``."""
    m = sel.shape[0]
    W = np.zeros((3 * m, n))
    for r in range(m):
        s = sel[r]
        v0 = motion_mps2[s, 0] + base_mps2[0]
        v1 = motion_mps2[s, 1] + base_mps2[1]
        v2 = motion_mps2[s, 2] + base_mps2[2]
        for j in range(n):
            # K_j v (the reading's turn about axis j), into the sensor's axes, times coef
            k0 = K[j, 0, 0] * v0 + K[j, 0, 1] * v1 + K[j, 0, 2] * v2
            k1 = K[j, 1, 0] * v0 + K[j, 1, 1] * v1 + K[j, 1, 2] * v2
            k2 = K[j, 2, 0] * v0 + K[j, 2, 1] * v1 + K[j, 2, 2] * v2
            for a in range(3):
                Rk = R_0S[s, 0, a] * k0 + R_0S[s, 1, a] * k1 + R_0S[s, 2, a] * k2
                W[3 * r + a, j] = Rk * coef[r, a, j]
    return W


@njit(cache=True, nogil=True, inline="always")
def _achievable_sigmas(lam, V, achievable):  # pragma: no cover - compiled
    """The sigma the information (eigenvalues ``lam``, vectors ``V``) alone would give each
    offset, written to ``achievable (n,)``: inf where a direction it touches is unread."""
    n = lam.shape[0]
    # a direction is unread where its eigenvalue is round-off of the largest (info's
    # entries reach 1e7 1/rad², so an absolute threshold would be the round-off's to decide)
    readable = 1e-12 * max(lam[n - 1], 0.0)
    for j in range(n):
        acc = 0.0
        for i in range(n):
            v2 = V[j, i] * V[j, i]
            if lam[i] > readable:
                acc += v2 / lam[i]
            elif v2 > 1e-12:
                acc = np.inf
                break
        achievable[j] = math.sqrt(acc)


@njit(cache=True, nogil=True, inline="always")
def _weak_directions(lam, V, P_offsets, weak_info):  # pragma: no cover - compiled
    """Which eigen-directions are weak ``(n,)``: below ``weak_info`` and not read better by
    the window than the filter already knows them (prior variance times information below
    one)."""
    n = lam.shape[0]
    weak = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if lam[i] < weak_info:
            prior_var = 0.0
            for a in range(n):
                pv = 0.0
                for b in range(n):
                    pv += P_offsets[a, b] * V[b, i]
                prior_var += V[a, i] * pv
            if lam[i] * prior_var < 1.0:
                weak[i] = True
    return weak


@njit(cache=True, nogil=True, inline="always")
def _held_basis(V, weak, locked):  # pragma: no cover - compiled
    """An orthonormal basis ``(n, h)`` of the held span: the ``weak`` eigen-directions (columns
    of ``V``) and the ``locked`` joints' own axes; ``(n, 0)`` when there is none."""
    n = V.shape[0]
    n_weak = 0
    n_locked = 0
    for j in range(n):
        if weak[j]:
            n_weak += 1
        if locked[j]:
            n_locked += 1
    if n_weak == 0 and n_locked == 0:
        return np.zeros((n, 0))
    B = np.zeros((n, n_weak + n_locked))
    c = 0
    for i in range(n):
        if weak[i]:
            B[:, c] = V[:, i]
            c += 1
    for j in range(n):
        if locked[j]:
            B[j, c] = 1.0
            c += 1
    if n_locked == 0 or n_weak == 0:  # orthonormal already when of one kind
        return B
    w, Ub = np.linalg.eigh(B @ B.T)
    h = 0
    for i in range(n):
        if w[i] > 1e-6:
            h += 1
    U = np.empty((n, h))
    c = 0
    for i in range(n):
        if w[i] > 1e-6:
            U[:, c] = Ub[:, i]
            c += 1
    return U
