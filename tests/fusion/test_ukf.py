"""The batched sigma-point filter: filterpy's points and weights, models called once per step
with every sigma point, exact on linear problems, per-group gates, held directions, angles."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints
from scipy.stats import chi2

from fusion.ukf import (
    BatchedUKF,
    GroupPlan,
    MeasurementGroup,
    SigmaPoints,
    nis_bound,
    repair_covariance,
    unscented_transform,
    wrap_angle,
)


def spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


@pytest.mark.parametrize("alpha, beta, kappa", [(0.5, 2.0, 0.0), (1e-3, 2.0, 0.0), (1.0, 0.0, 3.0 - 6)])
def test_points_and_weights_are_filterpys(rng, alpha, beta, kappa):
    n = 6
    x, P = rng.normal(size=n), spd(rng, n)
    ours = SigmaPoints(n, alpha, beta, kappa)
    ref = MerweScaledSigmaPoints(n, alpha, beta, kappa)
    np.testing.assert_allclose(ours.sigma_points(x, P), ref.sigma_points(x, P), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ours.Wm, ref.Wm)
    np.testing.assert_array_equal(ours.Wc, ref.Wc)
    assert ours.num_sigmas() == 2 * n + 1


def test_sigma_points_survive_a_covariance_that_is_not_positive_definite(rng):
    n = 4
    v = rng.normal(size=n)
    P = np.outer(v, v)  # rank one: Cholesky fails
    X = SigmaPoints(n).sigma_points(np.zeros(n), P)
    assert np.all(np.isfinite(X))
    Wm, Wc = SigmaPoints(n).Wm, SigmaPoints(n).Wc
    _, _, C = unscented_transform(X, Wm, Wc)
    np.testing.assert_allclose(C, P, atol=1e-9)


def _kalman_reference(x, P, F, Q, H, R, z):
    """The textbook linear Kalman filter, one predict and one update."""
    x = F @ x
    P = F @ P @ F.T + Q
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    return x + K @ (z - H @ x), (np.eye(len(x)) - K @ H) @ P


def test_linear_problem_matches_the_kalman_filter_and_calls_each_model_once_per_step(rng):
    n, m = 5, 3
    F = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    Q, R = spd(rng, n, 0.01), spd(rng, m, 0.1)
    x0, P0 = rng.normal(size=n), spd(rng, n)
    calls = {"fx": [], "hx": []}

    def fx(X):
        calls["fx"].append(X.shape)
        return X @ F.T

    def hx(X):
        calls["hx"].append(X.shape)
        return X @ H.T

    f = BatchedUKF(x0, P0, SigmaPoints(n, alpha=0.7))
    # the filter adds its process noise before propagating: give it F^-1 Q F^-T, which
    # the propagation turns into Q, and it must be the Kalman filter to round-off
    Fi = np.linalg.inv(F)
    Q_pre = Fi @ Q @ Fi.T
    x_ref, P_ref = x0, P0
    for _ in range(20):
        z = rng.normal(size=m)
        f.predict(fx, Q_pre)
        f.update(z, hx, R)
        x_ref, P_ref = _kalman_reference(x_ref, P_ref, F, Q, H, R, z)
    np.testing.assert_allclose(f.x, x_ref, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(f.P, P_ref, rtol=1e-8, atol=1e-10)
    # every call saw all 2n + 1 sigma points at once
    assert calls["fx"] == [(2 * n + 1, n)] * 20
    assert calls["hx"] == [(2 * n + 1, n)] * 20
    np.testing.assert_allclose(f.P, f.P.T, atol=0)


def test_identity_process_is_exactly_the_kalman_filter(rng):
    """With F = I (offsets, biases: the tracker's slow states) noise added before or after
    the propagation is the same, and the filter is the Kalman filter to round-off."""
    n, m = 4, 2
    H = rng.normal(size=(m, n))
    Q, R = spd(rng, n, 0.01), spd(rng, m, 0.1)
    x0, P0 = rng.normal(size=n), spd(rng, n)
    f = BatchedUKF(x0, P0, SigmaPoints(n, alpha=0.3))
    x_ref, P_ref = x0, P0
    for _ in range(30):
        z = rng.normal(size=m)
        f.predict(lambda X: X, Q)
        f.update(z, lambda X: X @ H.T, R)
        x_ref, P_ref = _kalman_reference(x_ref, P_ref, np.eye(n), Q, H, R, z)
    np.testing.assert_allclose(f.x, x_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(f.P, P_ref, rtol=1e-9, atol=1e-12)


def test_nonlinear_update_matches_a_per_point_reference(rng):
    """The batched update equals the sigma-point update written point by point."""
    n = 3
    x, P = np.array([0.3, -0.2, 1.0]), spd(rng, n, 0.01)
    R = np.diag([0.01, 0.02])
    z = np.array([0.5, 0.9])

    def h1(v):
        return np.array([np.sin(v[0]) + v[1] ** 2, v[2] * np.cos(v[1])])

    pts = SigmaPoints(n, alpha=0.5)
    f = BatchedUKF(x, P, pts)
    f.update(z, lambda X: np.stack([h1(v) for v in X]), R)
    # reference, a point at a time
    X = MerweScaledSigmaPoints(n, 0.5, 2.0, 0.0).sigma_points(x, P)
    Z = np.array([h1(v) for v in X])
    zp = pts.Wm @ Z
    S = sum(w * np.outer(zz - zp, zz - zp) for w, zz in zip(pts.Wc, Z, strict=True)) + R
    Pxz = sum(w * np.outer(xx - x, zz - zp) for w, xx, zz in zip(pts.Wc, X, Z, strict=True))
    K = Pxz @ np.linalg.inv(S)
    np.testing.assert_allclose(f.x, x + K @ (z - zp), atol=1e-12)
    np.testing.assert_allclose(f.P, P - K @ S @ K.T, atol=1e-12)


def test_each_group_is_gated_on_its_own_and_the_rest_is_applied(rng):
    n = 4
    f = BatchedUKF(np.zeros(n), np.eye(n) * 0.01)
    H = np.eye(n)
    gate = float(nis_bound(2, 1e-3))
    groups = [MeasurementGroup("a", np.array([0, 1]), gate), MeasurementGroup("b", np.array([2, 3]), gate)]
    z = np.array([0.05, -0.05, 5.0, 5.0])  # b is an outlier
    inn = f.update(z, lambda X: X @ H.T, np.eye(n) * 0.01, GroupPlan(groups))
    assert inn.names == ("a", "b")
    assert inn.gate_ok.tolist() == [True, False]
    S = np.eye(2) * 0.02
    assert inn.nis[1] == pytest.approx(z[2:] @ np.linalg.solve(S, z[2:]), rel=1e-9)
    x = f.x
    assert abs(x[0] - 0.025) < 1e-9 and abs(x[2]) < 1e-12  # a applied, b not
    assert gate == pytest.approx(chi2.ppf(0.999, 2))


def test_a_held_direction_gets_no_correction_and_its_covariance_stays_honest(rng):
    n = 3
    P0 = spd(rng, n, 0.1)
    f = BatchedUKF(np.zeros(n), P0)
    H = rng.normal(size=(2, n))
    R = np.eye(2) * 0.05
    d = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    T = np.eye(n) - np.outer(d, d)
    z = np.array([1.0, -0.5])
    f.update(z, lambda X: X @ H.T, R, hold=T)
    assert abs(f.x @ d) < 1e-12
    # the covariance is the Joseph form of the held gain
    S = H @ P0 @ H.T + R
    K = T @ P0 @ H.T @ np.linalg.inv(S)
    IKH = np.eye(n) - K @ H
    np.testing.assert_allclose(f.P, IKH @ P0 @ IKH.T + K @ R @ K.T, atol=1e-12)
    # nothing was learnt along the held direction
    assert d @ f.P @ d == pytest.approx(d @ P0 @ d, rel=1e-9)
    np.testing.assert_allclose(f.P, f.P.T, atol=0)


def test_a_gain_mask_limits_which_states_a_row_may_correct(rng):
    n = 3
    f = BatchedUKF(np.zeros(n), spd(rng, n, 0.1))
    mask = np.zeros((n, 1))
    mask[2, 0] = 1.0
    f.update(np.array([1.0]), lambda X: (X[:, 0] + X[:, 1] + X[:, 2])[:, None], np.eye(1) * 0.1,
             gain_mask=mask)
    assert f.x[0] == 0.0 and f.x[1] == 0.0 and f.x[2] != 0.0
    assert np.all(np.linalg.eigvalsh(f.P) > 0)


def test_angles_average_and_wrap_across_pi():
    f = BatchedUKF(np.array([np.pi - 0.01]), np.eye(1) * 0.05**2, angle_states=(0,))
    f.predict(lambda X: wrap_angle(X + 0.02), np.eye(1) * 1e-6)
    assert f.x[0] == pytest.approx(-np.pi + 0.01, abs=1e-9)
    assert f.sigma[0] == pytest.approx(0.05, rel=0.01)
    # a heading measured just the other side of pi pulls the estimate, not 2 pi away
    inn = f.update(np.array([np.pi - 0.005]), lambda X: X.copy(), np.eye(1) * 0.05**2, angle_rows=(0,))
    assert abs(inn.innovation[0]) < 0.02
    assert abs(wrap_angle(f.x[0] - np.pi)) < 0.02


def test_state_is_read_only_and_inputs_are_validated():
    f = BatchedUKF(np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match="read-only"):
        f.x[0] = 1.0
    with pytest.raises(ValueError, match=r"P0 must have shape \(2, 2\)"):
        BatchedUKF(np.zeros(2), np.eye(3))
    with pytest.raises(ValueError, match="must be finite"):
        BatchedUKF(np.array([np.nan, 0.0]), np.eye(2))


def test_repair_restores_positive_definiteness():
    P = np.array([[1.0, 2.0], [2.0, 1.0]])  # indefinite
    Q = repair_covariance(P, 1e-9)
    assert np.all(np.linalg.eigvalsh(Q) >= 1e-9 - 1e-15)
    np.testing.assert_allclose(Q, Q.T)
