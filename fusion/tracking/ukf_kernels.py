"""Compiled (numba) kernels: every stage of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`'s step.

A step of a 19-state filter is a few dozen small matrix products; called from NumPy, their
interpreter and dispatch overhead, not their arithmetic, sets the pace. Each kernel here
does one stage of the step in one call:

- :func:`sigma_points_into`: the points ``x, x + U[k], x - U[k]`` with ``U^T U = s (P + Q)``
  (the upper Cholesky factor, filterpy's convention);
- :func:`unscented_moments_into`: the unscented transform of the propagated points (the
  weighted mean, with at most one angle column, and the covariance);
- :func:`innovation_into`: the predicted measurement, its covariance ``S``, the innovation,
  the cross covariance and each measurement group's normalised innovation squared;
- :func:`kalman_update_into`: the gain from a Cholesky solve and the updated state and
  covariance (optimal, or held / masked through the general form).

They write into arrays the caller allocates (cheaper than returning new ones to Python)
and are the filter's only implementation: a matrix that is not numerically positive
definite takes its own compiled branch (an eigen-decomposition for the points, a
least-squares gain, a general solve for a group's NIS), the same algorithms the NumPy
reference (:mod:`armfusion.fusion.tracking.ukf_reference`, the tests' oracle) uses. The
caller guarantees shapes, float64 and C order: the kernels do not check bounds.
``angles (int64)`` are column (or row) indices, any number of them.
The matrix products go to BLAS (``np.dot``); the Cholesky factors and triangular solves
are written out, their inner loops running along contiguous rows (``b[j] -= u * a[j]``,
which the compiler turns into vector instructions), four rows at a time.
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.models.rotations import wrap_angle
from numba import njit

# status codes of the update kernel (the caller repairs the covariance on the second)
OK = 0
DIAGONAL_NOT_POSITIVE = 2  # the updated covariance has a diagonal entry <= 0 (or NaN)


# armfusion.models.rotations.wrap_angle compiled: the one definition, a scalar here (numba's float
# ``%`` is Python's: the sign of the divisor, so the same numbers as NumPy's)
_wrap = njit(cache=True)(wrap_angle)


@njit(cache=True)
def _cholesky_upper(A: np.ndarray, U: np.ndarray, k: int) -> bool:
    """``U`` upper triangular with ``U^T U = A`` for the leading ``(k, k)`` blocks, from the
    upper triangle of ``A`` (left alone; ``U`` gets zeros below its diagonal). Row by row:
    ``U[i, i:] = (A[i, i:] - sum_{r<i} U[r, i] U[r, i:]) / sqrt(pivot)``, the sum taken four
    rows at a time. False when a pivot is not positive (or is NaN)."""
    for i in range(k):
        for j in range(i, k):
            U[i, j] = A[i, j]
        r = 0
        while r + 4 <= i:
            a0, a1, a2, a3 = U[r, i], U[r + 1, i], U[r + 2, i], U[r + 3, i]
            for j in range(i, k):
                U[i, j] -= (a0 * U[r, j] + a1 * U[r + 1, j]) + (a2 * U[r + 2, j] + a3 * U[r + 3, j])
            r += 4
        while r < i:
            a0 = U[r, i]
            for j in range(i, k):
                U[i, j] -= a0 * U[r, j]
            r += 1
        d = U[i, i]
        if not d > 0.0:
            return False
        u = math.sqrt(d)
        U[i, i] = u
        for j in range(i + 1, k):
            U[i, j] /= u
        for j in range(i):
            U[i, j] = 0.0
    return True


@njit(cache=True)
def _cholesky_solve_rows(U: np.ndarray, B: np.ndarray) -> None:
    """``B = A^-1 B`` in place for ``A = U^T U`` (``U (m, m)`` upper triangular, ``B (m, c)``):
    the forward substitution ``U^T Y = B``, then the back substitution ``U X = Y``, each row
    of ``B`` losing its multiples of the rows already solved (four at a time)."""
    m = B.shape[0]
    for r in range(m):
        _solve_row(B, r, U[:, r], 0, r, U[r, r])
    for r in range(m - 1, -1, -1):
        _solve_row(B, r, U[r], r + 1, m, U[r, r])


@njit(cache=True, inline="always")
def _solve_row(B: np.ndarray, r: int, u: np.ndarray, q: int, q_end: int, d: float) -> None:
    """Row ``r`` of ``B`` loses ``u[q]`` times row ``q`` for every ``q`` in ``[q, q_end)``
    (four rows at a time), then is divided by ``d``: one row of a triangular solve."""
    c = B.shape[1]
    while q + 4 <= q_end:
        u0, u1, u2, u3 = u[q], u[q + 1], u[q + 2], u[q + 3]
        for j in range(c):
            B[r, j] -= (u0 * B[q, j] + u1 * B[q + 1, j]) + (u2 * B[q + 2, j] + u3 * B[q + 3, j])
        q += 4
    while q < q_end:
        u0 = u[q]
        for j in range(c):
            B[r, j] -= u0 * B[q, j]
        q += 1
    for j in range(c):
        B[r, j] /= d


@njit(cache=True)
def sigma_points_into(X: np.ndarray, x: np.ndarray, P: np.ndarray, Q: np.ndarray, scale: float) -> bool:
    """Van der Merwe's points of ``x (n,)`` and ``P + Q`` into ``X (2n+1, n)``: ``X[0] = x``,
    ``X[1 + k] = x + U[k]``, ``X[1 + n + k] = x - U[k]`` with ``U^T U = scale (P + Q)``: the
    upper Cholesky factor (filterpy's convention). When that is not positive definite the
    rows are ``sqrt(max(w_k, 0)) V[:, k]`` from the symmetric eigen-decomposition
    ``V diag(w) V^T`` of its symmetric part. Returns whether the Cholesky factor served."""
    n = x.shape[0]
    A = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            A[i, j] = scale * (P[i, j] + Q[i, j])
    U = np.empty((n, n))
    factored = _cholesky_upper(A, U, n)
    if not factored:
        w, V = np.linalg.eigh(0.5 * (A + A.T))
        for k in range(n):
            r = math.sqrt(max(w[k], 0.0))
            for j in range(n):
                U[k, j] = V[j, k] * r
    for j in range(n):
        X[0, j] = x[j]
    for k in range(n):
        for j in range(n):
            X[1 + k, j] = x[j] + U[k, j]
            X[1 + n + k, j] = x[j] - U[k, j]
    return factored


@njit(cache=True, inline="always")
def _angle_mean_and_residuals(Y: np.ndarray, Wm: np.ndarray, a: int, mean: np.ndarray, D: np.ndarray) -> None:
    """Column ``a`` of :func:`_mean_and_residuals` made an angle's (its plain mean and
    residuals already in ``mean``, ``D``)."""
    N = Y.shape[0]
    y0 = Y[0, a]
    near = True
    for p in range(N):
        if not abs(Y[p, a] - y0) < 3.0:
            near = False
    if near:
        mean[a] = _wrap(mean[a])
        return
    offset_mean = 0.0
    for p in range(N):
        d = _wrap(Y[p, a] - y0)
        D[p, a] = d
        offset_mean += Wm[p] * d
    mean[a] = _wrap(y0 + offset_mean)
    for p in range(N):
        D[p, a] -= offset_mean


@njit(cache=True)
def _mean_and_residuals(Y: np.ndarray, Wm: np.ndarray, angles: np.ndarray, mean: np.ndarray,
                        D: np.ndarray) -> None:
    """``mean = Wm Y`` and ``D = Y - mean`` for points ``Y (N, k)``, each column in
    ``angles`` treated as an angle: when its points lie within 3 rad of the central one the
    plain mean (then wrapped) and plain residuals stand; else the mean is the central point
    plus the weighted mean of the wrapped offsets from it, and the residuals are those
    offsets minus their mean."""
    N, k = Y.shape
    for j in range(k):
        mean[j] = 0.0
    for p in range(N):
        w = Wm[p]
        for j in range(k):
            mean[j] += w * Y[p, j]
    for p in range(N):
        for j in range(k):
            D[p, j] = Y[p, j] - mean[j]
    for a in angles:
        _angle_mean_and_residuals(Y, Wm, a, mean, D)


@njit(cache=True)
def _symmetrise(C: np.ndarray) -> None:
    """``C = (C + C^T) / 2`` in place: exactly symmetric."""
    k = C.shape[0]
    for i in range(k):
        for j in range(i + 1, k):
            c = 0.5 * (C[i, j] + C[j, i])
            C[i, j] = c
            C[j, i] = c


@njit(cache=True)
def _weighted_transpose(D: np.ndarray, Wc: np.ndarray, DW: np.ndarray) -> None:
    """``DW = D^T diag(Wc)``: residuals ``D (N, k)`` weighted and turned to ``(k, N)``."""
    N, k = D.shape
    for p in range(N):
        w = Wc[p]
        for i in range(k):
            DW[i, p] = D[p, i] * w


@njit(cache=True)
def unscented_moments_into(Y: np.ndarray, W: np.ndarray, angles: np.ndarray, mean: np.ndarray,
                           cov: np.ndarray, DW: np.ndarray) -> None:
    """The unscented transform of propagated points ``Y (N, n)`` with weights ``W (2, N)``
    (rows ``Wm``, ``Wc``): ``mean (n,)``, the weighted residuals ``DW = D^T diag(Wc) (n, N)``
    (the cross covariance needs them) and ``cov = DW D (n, n)``, symmetrised."""
    N, n = Y.shape
    D = np.empty((N, n))
    _mean_and_residuals(Y, W[0], angles, mean, D)
    _weighted_transpose(D, W[1], DW)
    np.dot(DW, D, cov)
    _symmetrise(cov)


@njit(cache=True)
def weighted_residuals_into(X: np.ndarray, x: np.ndarray, angles: np.ndarray, Wc: np.ndarray,
                            DW: np.ndarray) -> None:
    """``DW = (X - x)^T diag(Wc) (n, N)``: the weighted residuals of points ``X (N, n)``
    about the state ``x``, the ``angles`` columns wrapped (points the caller made, or made
    after a correction, that no predict has transformed)."""
    N, n = X.shape
    for p in range(N):
        w = Wc[p]
        for i in range(n):
            DW[i, p] = (X[p, i] - x[i]) * w
    for a in angles:
        for p in range(N):
            DW[a, p] = _wrap(X[p, a] - x[a]) * Wc[p]


@njit(cache=True, inline="always")
def _weighted_prediction(Z: np.ndarray, wz: np.ndarray, angles: np.ndarray, z_pred: np.ndarray) -> None:
    """``z_pred = Σ wz_p Z_p`` (``wz`` summing to 1), each row in ``angles`` as the central
    point plus the weighted mean of the wrapped offsets from it."""
    N, m = Z.shape
    for i in range(m):
        acc = 0.0
        for p in range(N):
            acc += wz[p] * Z[p, i]
        z_pred[i] = acc
    for a in angles:
        acc = 0.0
        for p in range(N):
            acc += wz[p] * _wrap(Z[p, a] - Z[0, a])
        z_pred[a] = _wrap(Z[0, a] + acc)


@njit(cache=True, inline="always")
def _add_noise(S: np.ndarray, R: np.ndarray) -> None:
    """``S += R`` for ``R (m, m)``, or ``S += diag(R[0])`` for one row ``R (1, m)`` (the
    variances of independent rows)."""
    m = S.shape[0]
    if R.shape[0] == m and m > 1:
        for i in range(m):
            for j in range(m):
                S[i, j] += R[i, j]
    else:
        for i in range(m):
            S[i, i] += R[0, i]


@njit(cache=True)
def _block_nis(block: np.ndarray, v: np.ndarray, U: np.ndarray) -> float:
    """``v^T B^-1 v`` for a group's block ``B (k, k)`` of ``S``: from its Cholesky factor
    (into ``U``), or, when ``B`` is not positive definite, a general solve (one row:
    ``v^2 / B``, inf unless ``B > 0``; a singular block: inf)."""
    k = v.shape[0]
    if _cholesky_upper(block, U, k):
        total = 0.0  # the forward substitution U^T u = v, NIS = |u|^2
        u = np.empty(k)
        for i in range(k):
            s = v[i]
            for j in range(i):
                s -= U[j, i] * u[j]
            u[i] = s / U[i, i]
            total += u[i] * u[i]
        return total
    if k == 1:
        return v[0] * v[0] / block[0, 0] if block[0, 0] > 0.0 else np.inf
    try:
        return np.dot(v, np.linalg.solve(block, v))
    except Exception:  # (numba's solve raises on an exactly singular block)
        return np.inf


@njit(cache=True)
def innovation_into(Z: np.ndarray, W: np.ndarray, wz: np.ndarray, angles: np.ndarray, z: np.ndarray,
                    R: np.ndarray, DXW: np.ndarray,
                    group_rows: np.ndarray, group_start: np.ndarray, block_start: np.ndarray,
                    gates: np.ndarray, z_pred: np.ndarray, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray,
                    blocks: np.ndarray, nis: np.ndarray, gate_ok: np.ndarray) -> None:
    """The statistics of a measurement ``z (m,)`` predicted by the points ``Z (N, m)``:
    ``z_pred = Σ wz_p Z_p`` (``wz`` summing to 1: ``W[0]`` for the unscented mean; rows in
    ``angles`` as the central point plus the weighted mean of the wrapped offsets from it),
    ``S = DZ^T diag(Wc) DZ + R`` (``R (m, m)``, or ``(1, m)``: a diagonal; symmetrised;
    ``DZ`` the residuals about the unscented mean, as in :func:`_mean_and_residuals`,
    whatever ``wz``), ``nu = z - z_pred`` (angle rows wrapped), ``Pxz = DXW DZ`` (``DXW (n,
    N)``: the state's weighted residuals) and, for each group ``g`` of ``k`` rows
    ``group_rows[group_start[g]:group_start[g + 1]]`` (any rows, in any order): its diagonal
    block of ``S``, row by row into ``blocks[block_start[g]:block_start[g] + k k]``, its NIS
    ``nu_g^T S_gg^-1 nu_g`` (:func:`_block_nis`), and whether that is finite and within
    ``gates[g]``."""
    N, m = Z.shape
    DZ = np.empty((N, m))
    _mean_and_residuals(Z, W[0], angles, z_pred, DZ)
    DZW = np.empty((m, N))
    _weighted_transpose(DZ, W[1], DZW)
    np.dot(DZW, DZ, S)
    _add_noise(S, R)
    _symmetrise(S)
    np.dot(DXW, DZ, Pxz)
    same = True
    for p in range(N):
        if wz[p] != W[0, p]:
            same = False
    if not same:  # the prediction the innovation is taken against, with the weights wz
        _weighted_prediction(Z, wz, angles, z_pred)
    for i in range(m):
        nu[i] = z[i] - z_pred[i]
    for a in angles:
        nu[a] = _wrap(nu[a])
    G = gates.shape[0]
    largest = 0
    for g in range(G):
        r0 = group_start[g]
        k = group_start[g + 1] - r0
        largest = max(largest, k)
        b0 = block_start[g]
        for i in range(k):
            for j in range(k):
                blocks[b0 + i * k + j] = S[group_rows[r0 + i], group_rows[r0 + j]]
    U = np.empty((largest, largest))
    for g in range(G):
        r0 = group_start[g]
        k = group_start[g + 1] - r0
        b0 = block_start[g]
        v = np.empty(k)
        for i in range(k):
            v[i] = nu[group_rows[r0 + i]]
        total = _block_nis(blocks[b0:b0 + k * k].reshape((k, k)), v, U)
        nis[g] = total
        gate_ok[g] = math.isfinite(total) and total <= gates[g]


@njit(cache=True, inline="always")
def _gain_transposed(S: np.ndarray, PxzT: np.ndarray) -> np.ndarray:
    """``K^T = S^-1 Pxz^T (m, n)``: two triangular solves with the Cholesky factor of ``S``,
    or, when ``S`` is not positive definite, its least-squares solution (LAPACK's
    ``gelsd``, singular values below ``eps m`` of the largest cut, as NumPy's default)."""
    m = S.shape[0]
    U = np.empty((m, m))
    if _cholesky_upper(S, U, m):
        Kt = PxzT.copy()
        _cholesky_solve_rows(U, Kt)
        return Kt
    Kt, _, _, _ = np.linalg.lstsq(S, PxzT, 2.220446049250313e-16 * m)
    return np.ascontiguousarray(Kt)


@njit(cache=True)
def kalman_update_into(x: np.ndarray, P: np.ndarray, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray,
                       hold: np.ndarray, gain_mask: np.ndarray, angles: np.ndarray,
                       x_new: np.ndarray, P_new: np.ndarray) -> int:
    """The Kalman update of ``x (n,)``, ``P (n, n)`` by the innovation ``nu (m,)`` with
    covariance ``S (m, m)`` and cross covariance ``Pxz (n, m)``.

    The gain is ``K = Pxz S^-1`` (:func:`_gain_transposed`). With ``hold (n, n)`` the gain
    is ``hold K``, with ``gain_mask (n, m)`` it is then multiplied entry by entry (an empty
    ``(0, 0)`` array means none). The state is ``x + K nu`` (``angles`` wrapped). The
    covariance is, for the optimal gain, ``P - K Pxz^T`` symmetrised; for a held or masked
    one, the general (Joseph-equivalent) form ``P + B + B^T`` with ``B = (K S / 2 - Pxz) K^T``.

    Returns :data:`DIAGONAL_NOT_POSITIVE` when the new covariance has a diagonal entry that
    is not positive (it needs repair), else :data:`OK`."""
    n, m = Pxz.shape
    PxzT = np.empty((m, n))
    for i in range(n):
        for r in range(m):
            PxzT[r, i] = Pxz[i, r]
    Kt = _gain_transposed(S, PxzT)
    K = np.empty((n, m))
    for i in range(n):
        for r in range(m):
            K[i, r] = Kt[r, i]
    held = hold.shape[0] > 0
    masked = gain_mask.shape[0] > 0
    if held:
        K_held = np.empty((n, m))
        np.dot(hold, K, K_held)
        K = K_held
    if masked:
        for i in range(n):
            for r in range(m):
                K[i, r] *= gain_mask[i, r]
    for i in range(n):
        s = 0.0
        for r in range(m):
            s += K[i, r] * nu[r]
        x_new[i] = x[i] + s
    for a in angles:
        x_new[a] = _wrap(x_new[a])
    if not (held or masked):
        # P - K Pxz^T, symmetrised
        np.dot(K, PxzT, P_new)
        for i in range(n):
            for j in range(i, n):
                p = 0.5 * ((P[i, j] - P_new[i, j]) + (P[j, i] - P_new[j, i]))
                P_new[i, j] = p
                P_new[j, i] = p
    else:
        # P + B + B^T, B = (K S / 2 - Pxz) K^T
        KS = np.empty((n, m))
        np.dot(K, S, KS)
        for i in range(n):
            for c in range(m):
                KS[i, c] = 0.5 * KS[i, c] - Pxz[i, c]
        for i in range(n):
            for r in range(m):
                Kt[r, i] = K[i, r]  # K^T of the held / masked gain
        np.dot(KS, Kt, P_new)
        for i in range(n):
            for j in range(i, n):
                b = P_new[i, j] + P_new[j, i]
                P_new[i, j] = P[i, j] + b
                P_new[j, i] = P[j, i] + b
    for i in range(n):
        if not P_new[i, i] > 0.0:
            return DIAGONAL_NOT_POSITIVE
    return OK
