"""The startup solve's Levenberg-Marquardt, compiled (numba), for every start at once.

A still solve (:func:`armfusion.fusion.startup.solve.solve_still`) is a few batched Levenberg-Marquardt
runs over 9 to 90 starts, each iteration one evaluation of every start's weighted
residuals and Jacobian and one 9x9 linear solve per start. That is a few thousand
floating-point operations per start, which as NumPy calls on small arrays cost far more
in call overhead than in arithmetic. Here each start is iterated on its own, in one
compiled loop:

- the gravity chain is :mod:`armfusion.models.gravity_kernels` (the one implementation, which
  :class:`armfusion.models.kinematics.GravityChain` calls too): the state ``x = [q, roll, pitch]``
  seeds ``V = [up, 0 ... 0, d up/d roll, d up/d pitch]`` (3 x (n + 3)), and each joint
  turns it and sets its own derivative column;
- a sensor on link k reads rows ``W_s V`` with V taken after joint k - 1 (``W_s = -D_s /
  sigma_s``, the read-out weighted and negated), column 0 plus ``meas / sigma`` being its
  weighted residual and the others its Jacobian (:func:`augmented`, which
  :meth:`armfusion.fusion.startup.problem.StillWindowProblem.residuals_and_jacobian` returns);
  without the base accelerometer two rows of the level-chair prior follow: residual
  ``(roll, pitch) / s``, Jacobian ``1 / s`` on the tilt's columns;
- LM (:func:`lm_solve`) works from ``N = [r J]^T [r J]``: with
  ``f`` the free mask and ``h = 1 - f``, ``A = N_JJ * f f^T``, ``g = N_Jr * f``, the
  diagonal damped ``A_ii += lam (A_ii + 1e-9) + h_i``, step ``-A^-1 g`` (LU with partial
  pivoting). A start stops when its step is below 1e-7 rad (not taken), when ``lam``
  passes 1e8, or when its iterations are used; a step is kept when it lowers the cost
  ``r . r / 2`` (``lam * 0.3``), else refused (``lam * 10``).

The layout of one kind of solve (:class:`armfusion.fusion.startup.problem.SolveLayout`) is passed as
arrays: the read-outs ``read_W (R, 3, 3)``, their first rows ``read_row (R,)`` and links
``read_link (R,)``, the weighted measurements ``meas_w (m,)``, the rows of the sensors
``n_sensor_rows``, whether the base accelerometer is in (``imu``; else the prior's two
rows with ``tilt_prior``), and the last joint any row needs (``last``).

The tests (tests/fusion/test_startup_kernels.py) hold the evaluation to the kinematics of
the frames (:func:`armfusion.models.kinematics.gravity_jacobian`) and the LM to its NumPy form.
Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import numpy as np
from armfusion.models.gravity_kernels import seed_up_and_tilt, turn_joint
from numba import njit


@njit(cache=True, nogil=True)
def _evaluate(x, step_in, offset, read_W, read_row, read_link, meas_w, n_sensor_rows, imu,
              tilt_prior, last, V, rJ):  # pragma: no cover - compiled
    """Weighted residuals and Jacobian of one state ``x (n + 2,)`` into ``rJ (m, n + 3)``
    (column 0 the residual); ``V (3, n + 3)`` is work space. Columns of a row that do not
    depend on the state (joints past the row's link) are left as they are: zero."""
    n = offset.shape[0]
    w = n + 3
    seed_up_and_tilt(x[n], x[n + 1], V)
    R = read_row.shape[0]
    for k in range(last + 2):  # k: the link whose rows are read (V after joint k - 1)
        if k > 0:
            turn_joint(V, step_in[k - 1], x[k - 1] + offset[k - 1], k - 1, n)
        for r in range(R):
            if read_link[r] != k:
                continue
            W = read_W[r]
            row = read_row[r]
            for j in range(w):
                if j > k and j <= n:
                    continue
                v0, v1, v2 = V[0, j], V[1, j], V[2, j]
                for a in range(3):
                    rJ[row + a, j] = W[a, 0] * v0 + W[a, 1] * v1 + W[a, 2] * v2
    m = meas_w.shape[0]
    if not imu:  # the level-chair prior's two rows
        rJ[n_sensor_rows, 0] = x[n] / tilt_prior
        rJ[n_sensor_rows + 1, 0] = x[n + 1] / tilt_prior
        rJ[n_sensor_rows, n + 1] = 1.0 / tilt_prior
        rJ[n_sensor_rows + 1, n + 2] = 1.0 / tilt_prior
    for r in range(m):
        rJ[r, 0] += meas_w[r]


@njit(cache=True, nogil=True)
def _normal(rJ, N):  # pragma: no cover - compiled
    """``N = rJ^T rJ`` (symmetric: the upper triangle, mirrored)."""
    m, w = rJ.shape
    for a in range(w):
        for b in range(a, w):
            acc = 0.0
            for r in range(m):
                acc += rJ[r, a] * rJ[r, b]
            N[a, b] = acc
            N[b, a] = acc


@njit(cache=True, nogil=True)
def _lu_solve(A, b, out):  # pragma: no cover - compiled
    """``out = A^-1 b`` by Gaussian elimination with partial pivoting (``A`` and ``b`` are
    overwritten)."""
    p = b.shape[0]
    for c in range(p):
        piv = c
        big = abs(A[c, c])
        for r in range(c + 1, p):
            if abs(A[r, c]) > big:
                big = abs(A[r, c])
                piv = r
        if piv != c:
            for j in range(p):
                A[c, j], A[piv, j] = A[piv, j], A[c, j]
            b[c], b[piv] = b[piv], b[c]
        d = A[c, c]
        for r in range(c + 1, p):
            f = A[r, c] / d
            if f != 0.0:
                for j in range(c + 1, p):
                    A[r, j] -= f * A[c, j]
                b[r] -= f * b[c]
    for c in range(p - 1, -1, -1):
        acc = b[c]
        for j in range(c + 1, p):
            acc -= A[c, j] * out[j]
        out[c] = acc / A[c, c]


@njit(cache=True, nogil=True)
def augmented(X, step_in, offset, read_W, read_row, read_link, meas_w, n_sensor_rows, imu,
              tilt_prior, last):  # pragma: no cover - compiled
    """Weighted residuals and Jacobian side by side for states ``X (B, n + 2)``: ``(B, m,
    n + 3)``."""
    B = X.shape[0]
    n = offset.shape[0]
    m = meas_w.shape[0]
    out = np.zeros((B, m, n + 3))
    V = np.empty((3, n + 3))
    for b in range(B):
        _evaluate(X[b], step_in, offset, read_W, read_row, read_link, meas_w, n_sensor_rows, imu,
                  tilt_prior, last, V, out[b])
    return out


@njit(cache=True, nogil=True, inline="always")
def _damped_system(N, f, lam, A, g):  # pragma: no cover - compiled
    """The Levenberg-Marquardt system of one iteration from the augmented normal matrix ``N``
    (row and column 0 the residuals, the rest the unknowns): ``A = J^T J`` restricted to the
    free unknowns (``f`` 1.0 free, 0.0 held: a held unknown's row is the identity, so its
    step is zero) with ``lam`` times its diagonal added, and ``g = J^T r`` likewise."""
    p = A.shape[0]
    for i in range(p):
        for j in range(p):
            A[i, j] = N[1 + i, 1 + j] * f[i] * f[j]
        g[i] = N[1 + i, 0] * f[i]
    for i in range(p):
        A[i, i] += lam * (A[i, i] + 1e-9)
        A[i, i] += 1.0 - f[i]


@njit(cache=True, nogil=True, inline="always")
def _negated_size(step):  # pragma: no cover - compiled
    """Turns the solution of the system into the step (its negative, in place) and returns
    its largest element's magnitude."""
    big = 0.0
    for i in range(step.shape[0]):
        step[i] = -step[i]
        big = max(big, abs(step[i]))
    return big


@njit(cache=True, nogil=True)
def lm_solve(X0, free, iters, step_in, offset, read_W, read_row, read_link, meas_w, n_sensor_rows,
             imu, tilt_prior, last):  # pragma: no cover - compiled
    """Levenberg-Marquardt from every start ``X0 (B, n + 2)``, each on its own: ``free (B,
    n + 2)`` 1.0 where the unknown moves, 0.0 where it is held; ``iters (B,)`` the most
    iterations. Returns the solutions ``(B, n + 2)`` and their costs ``(B,)`` (half the sum
    of squared weighted residuals)."""
    B, p = X0.shape
    n = offset.shape[0]
    m = meas_w.shape[0]
    w = n + 3
    X = X0.copy()
    cost = np.empty(B)
    V = np.empty((3, w))
    rJ = np.zeros((m, w))
    N = np.empty((w, w))
    Nt = np.empty((w, w))
    A = np.empty((p, p))
    g = np.empty(p)
    step = np.empty(p)
    xt = np.empty(p)
    for b in range(B):
        x = X[b]
        f = free[b]
        left = iters[b]
        lam = 1e-3
        c = 0.0
        xt[:] = x
        first = True
        while True:  # one evaluation per pass (one call site: a smaller compiled loop)
            _evaluate(xt, step_in, offset, read_W, read_row, read_link, meas_w, n_sensor_rows, imu,
                      tilt_prior, last, V, rJ)
            _normal(rJ, Nt)
            ct = 0.5 * Nt[0, 0]
            if first:  # the start itself
                N, Nt = Nt, N
                c = ct
                first = False
            else:
                if ct < c:  # the step lowers the cost: taken
                    x[:] = xt
                    N, Nt = Nt, N
                    c = ct
                    lam = lam * 0.3
                else:
                    lam = lam * 10.0
                left -= 1
                if lam > 1e8:  # no step lowers the cost
                    break
            if left <= 0:
                break
            _damped_system(N, f, lam, A, g)
            _lu_solve(A, g, step)
            if _negated_size(step) < 1e-7:  # converged: the step is not taken
                break
            for i in range(p):
                xt[i] = x[i] + step[i]
        cost[b] = c
    return X, cost
