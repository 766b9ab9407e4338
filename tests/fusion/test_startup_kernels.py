"""The compiled startup kernels equal their references on the same inputs.

(What the solve gives is tested in tests/fusion/test_startup.py; here, that the compiled
evaluation agrees with the frames of the whole chain (``armfusion.models.kinematics.gravity_jacobian``)
and the compiled Levenberg-Marquardt with its NumPy form, ``batched_lm_numpy`` below (the
reference; it left the production module), for every kind of solve the startup runs: all
sensors with the base accelerometer, without it (the level-chair prior's rows), one sensor
at a time as the thesis's method does, the base accelerometer alone, and readings with no
IMU at all.)"""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.startup.kernels import augmented
from armfusion.fusion.startup.problem import batched_lm, make_problem
from armfusion.fusion.startup.readings import StillReadings
from armfusion.models.kinematics import gravity_in_sensors, gravity_jacobian
from armfusion.models.rotations import DEG, up_from_tilt

Q_DEG = np.array([30.0, 40.0, 20.0, -50.0, 60.0, 30.0, 100.0])


def _normal_matrices(problem, x, active, use_imu):
    """``[r J]^T [r J]`` for states ``x (B, n+2)``: ``(B, n+3, n+3)``, with ``r . r`` at
    [0, 0], ``J^T r`` down the rest of column 0 and ``J^T J`` below right; all LM needs."""
    r, J = problem.residuals_and_jacobian(x, active, use_imu)
    rJ = np.concatenate([r[..., None], J], -1)
    return np.swapaxes(rJ, 1, 2) @ rJ


def batched_lm_numpy(problem, x0: np.ndarray, free: np.ndarray, iters,
                     active: np.ndarray | None = None, use_imu: bool = True,
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every start at once (the NumPy form of the compiled
    :func:`armfusion.fusion.startup.problem.batched_lm`, the reference it is held to).
    ``free`` selects the unknowns: ``(n+2,)`` for all starts, or ``(B, n+2)`` per start (a
    held unknown keeps its start value). ``iters``: the most iterations, for all starts or
    ``(B,)`` per start.

    Each start stops on its own once it has converged (its next step below 1e-7 rad, not
    taken, or its damping past 1e8: no step lowers the cost) or used its iterations; the
    others go on without it. Returns the solutions and their final cost (half sum of
    squared weighted residuals).
    """
    x = np.array(x0, float)
    B, p = x.shape
    held_mask = ~np.broadcast_to(np.asarray(free, bool), (B, p))
    masked = bool(held_mask.any())
    iters_left = np.broadcast_to(np.asarray(iters), (B,)).astype(int)
    N = _normal_matrices(problem, x, active, use_imu)  # (B, 1 + p, 1 + p): r.r, J^T r, J^T J
    cost = 0.5 * N[:, 0, 0]
    # the starts still iterating, packed: their rows in x, their state
    rows = np.flatnonzero(iters_left > 0)
    xa, Na, ca = x[rows], N[rows], cost[rows]
    lam = np.full(len(rows), 1e-3)
    free_f = (~held_mask[rows]).astype(float)
    held_f = held_mask[rows].astype(float)
    left = iters_left[rows]
    while len(rows):
        if masked:  # a held unknown's column is zero: it takes no step
            A = Na[:, 1:, 1:] * free_f[:, :, None] * free_f[:, None, :]
            g = Na[:, 1:, :1] * free_f[:, :, None]
        else:
            A = Na[:, 1:, 1:].copy()
            g = Na[:, 1:, :1]
        diag = A.reshape(len(A), p * p)[:, :: p + 1]  # a view: damping in place
        diag += lam[:, None] * (diag + 1e-9)
        if masked:
            diag += held_f
        step = -np.linalg.solve(A, g)[..., 0]
        # 1e-7 rad is a thousandth of the smallest sigma these sensors give: converged
        # (that last step is not taken: it could not change anything that is reported)
        done = np.abs(step).max(1) < 1e-7
        if done.any():
            x[rows[done]], cost[rows[done]] = xa[done], ca[done]
            go = ~done
            rows, xa, Na, ca, lam, step = rows[go], xa[go], Na[go], ca[go], lam[go], step[go]
            free_f, held_f, left = free_f[go], held_f[go], left[go]
            if not len(rows):
                break
        xt = xa + step
        Nt = _normal_matrices(problem, xt, active, use_imu)
        ct = 0.5 * Nt[:, 0, 0]
        better = ct < ca
        if better.all():
            xa, Na, ca = xt, Nt, ct
        elif better.any():
            xa, Na, ca = (np.where(better[:, None], xt, xa), np.where(better[:, None, None], Nt, Na),
                          np.where(better, ct, ca))
        lam = np.where(better, lam * 0.3, lam * 10.0)
        left = left - 1
        done = (lam > 1e8) | (left <= 0)  # no step lowers the cost, or no iteration left
        if done.any():
            x[rows[done]], cost[rows[done]] = xa[done], ca[done]
            go = ~done
            rows, xa, Na, ca, lam = rows[go], xa[go], Na[go], ca[go], lam[go]
            free_f, held_f, left = free_f[go], held_f[go], left[go]
    return x, cost


def _readings(arm, seed: int, imu: bool = True) -> StillReadings:
    rng = np.random.default_rng(seed)
    up = up_from_tilt(0.8 * DEG, -1.2 * DEG)
    f = gravity_in_sensors(arm, np.radians(Q_DEG), up)[0]
    names = [s.name for s in arm.link_accelerometers]
    sig = np.array([0.003, 0.003, 0.004])
    means = {nm: f[i] + rng.normal(0, sig) for i, nm in enumerate(names)}
    return StillReadings(means, {nm: sig for nm in names},
                         up + rng.normal(0, 3e-4, 3) if imu else None, np.full(3, 3e-4) if imu else None)


def _layouts(n_sensors: int):
    """(active, use_imu) of every kind of solve the startup runs."""
    one = np.zeros(n_sensors, bool)
    one[2] = True
    return [(None, True), (None, False), (one, False), (np.zeros(n_sensors, bool), True)]


@pytest.fixture(scope="module", params=[True, False], ids=["imu", "no-imu"])
def problem(wmra, request):
    return make_problem(wmra, _readings(wmra, 11, imu=request.param))


def _frames_reference(problem, X, active, use_imu):
    """The weighted residuals and Jacobian of states ``X`` from the frames of the whole
    chain (:func:`armfusion.models.kinematics.gravity_jacobian`; the tilt's columns by central
    differences of up), rows as the solve lays them out."""
    n = problem.n
    used = np.arange(len(problem.names)) if active is None else np.flatnonzero(active)
    names = [problem.names[s] for s in used]
    rows_r, rows_J = [], []
    for x in X:
        up = up_from_tilt(x[n], x[n + 1])
        h = 1e-6
        d_up = np.stack([(up_from_tilt(x[n] + h, x[n + 1]) - up_from_tilt(x[n] - h, x[n + 1])) / (2 * h),
                         (up_from_tilt(x[n], x[n + 1] + h) - up_from_tilt(x[n], x[n + 1] - h)) / (2 * h)], 1)
        if names:
            f, J, R_0S = gravity_jacobian(problem.arm, x[None, :n], up, names, with_frames=True)
        r, Jx = [], []
        for i, s in enumerate(used):
            r.append((problem.meas[s] - f[0, i]) / problem.sigma[s])
            Jx.append(-np.hstack([J[0, i], R_0S[0, i].T @ d_up]) / problem.sigma[s][:, None])
        if use_imu and problem.imu_meas is not None:
            r.append((problem.imu_meas - problem.R_0I.T @ up) / problem.imu_sigma)
            Jx.append(-np.hstack([np.zeros((3, n)), problem.R_0I.T @ d_up]) / problem.imu_sigma[:, None])
        else:  # the level-chair prior
            r.append(x[n:] / problem.tilt_prior_rad)
            Jx.append(np.hstack([np.zeros((2, n)), np.eye(2)]) / problem.tilt_prior_rad)
        rows_r.append(np.concatenate(r))
        rows_J.append(np.vstack(Jx))
    return np.array(rows_r), np.array(rows_J)


def test_evaluation_equals_the_kinematics_of_the_frames(problem):
    """The compiled evaluation (the gravity chain's core, read by each sensor) gives the
    residuals and Jacobian that the frames of the whole chain give, for every kind of
    solve; a row's columns past its sensor's link are exactly zero."""
    n = problem.n
    rng = np.random.default_rng(3)
    X = np.concatenate([rng.uniform(-np.pi, np.pi, (9, n)), rng.normal(0, 0.1, (9, 2))], 1)
    for active, use_imu in _layouts(len(problem.names)):
        r, J = problem.residuals_and_jacobian(X, active, use_imu)
        r_ref, J_ref = _frames_reference(problem, X, active, use_imu)
        assert r.shape == r_ref.shape and J.shape == J_ref.shape
        np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(J[..., :n], J_ref[..., :n], rtol=0, atol=1e-9)
        # central differences of up: about 1e-10 of each unit column, weighted by 1 / sigma
        np.testing.assert_allclose(J[..., n:], J_ref[..., n:], rtol=0, atol=1e-5)
        assert np.all(J[..., :n][J_ref[..., :n] == 0.0] == 0.0)  # joints past a row's link
        assert np.array_equal(augmented(X, *problem.layout(active, use_imu))[..., 0], r)


@pytest.mark.parametrize("spread, atol", [(0.05, 1e-12), (0.6, 1e-6)])
def test_levenberg_marquardt_equals_the_numpy_form(problem, spread, atol):
    """Starts near the pose and far from it, some unknowns held, each start with its own
    iteration limit (some stop on it, some converge, one takes no step at all).

    The two differ in the last bits of each product's sums (the NumPy form's are BLAS's and
    LAPACK's), and a start still crawling along a curved valley after its iterations
    amplifies those: the far starts, whose iteration limits are reached there, agree to
    ``atol`` (3e-8 seen); their first steps, and every near start, to 1e-12 (costs 1e-11)."""
    n = problem.n
    rng = np.random.default_rng(int(spread * 100))
    B = 12
    x_true = np.concatenate([np.radians(Q_DEG), [0.8 * DEG, -1.2 * DEG]])
    x0 = x_true + rng.normal(0, spread, (B, n + 2))
    free = rng.random((B, n + 2)) > 0.15
    free[:3] = True
    iters = np.array([30, 30, 30, 12, 12, 12, 5, 5, 3, 2, 1, 0])
    first = iters <= 3
    for active, use_imu in _layouts(len(problem.names)):
        x, cost = batched_lm(problem, x0, free, iters, active, use_imu)
        x_ref, cost_ref = batched_lm_numpy(problem, x0, free, iters, active, use_imu)
        np.testing.assert_allclose(x, x_ref, rtol=0, atol=atol)
        np.testing.assert_allclose(cost, cost_ref, rtol=atol, atol=1e-12)
        np.testing.assert_allclose(x[first], x_ref[first], rtol=0, atol=1e-12)
        np.testing.assert_allclose(cost[first], cost_ref[first], rtol=1e-11, atol=1e-12)
        assert np.all(x[~free] == x0[~free])  # a held unknown keeps its start value
        assert np.array_equal(x[-1], x0[-1])  # no iteration: the start itself
    # every start free, one iteration limit for all (the joint solve's first batch)
    x, cost = batched_lm(problem, x0, np.ones(n + 2, bool), 30)
    x_ref, cost_ref = batched_lm_numpy(problem, x0, np.ones(n + 2, bool), 30)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=atol)
    np.testing.assert_allclose(cost, cost_ref, rtol=atol, atol=1e-12)
