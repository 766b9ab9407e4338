"""The batched sigma-point filter: filterpy's points and weights, models called once per step
with every sigma point, exact on linear problems, per-group gates, held directions, angles."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.tracking.ukf import (
    BatchedUKF,
    GainLimits,
    GroupPlan,
    Innovation,
    MeasurementGroup,
    SigmaPoints,
    nis_bound,
    repair_covariance,
    wrap_angle,
)
from armfusion.fusion.tracking.ukf_kernels import (
    DIAGONAL_NOT_POSITIVE,
    OK,
    kalman_update_into,
    sigma_points_into,
)
from armfusion.fusion.tracking.ukf_reference import ReferenceUKF, unscented_transform
from armfusion.fusion.tracking.ukf_reference import sigma_points as reference_sigma_points
from filterpy.kalman import MerweScaledSigmaPoints
from scipy.stats import chi2


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
    f.update(z, lambda X: X @ H.T, R, limits=GainLimits(hold=T))
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
             limits=GainLimits(gain_mask=mask))
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


# -- the compiled step (armfusion.fusion.tracking.ukf_kernels) against the NumPy reference -----------
# The tolerances: the kernels and the reference (NumPy, LAPACK) sum the same products in
# different orders, so they agree to round-off: relative 1e-12 for one stage, a little
# more where a stage feeds on another's round-off (an inverse of S, a repaired P).
N_STATE, YAW = 19, 12  # the tracker's state size and its one angle state


def _compiled_and_reference(x0, P0, angle_states=(YAW,)):
    """Two filters from one state: the compiled one, and the NumPy reference (the oracle)."""
    return BatchedUKF(x0, P0, angle_states=angle_states), ReferenceUKF(x0, P0, angle_states=angle_states)


def _state(rng, yaw=np.pi - 0.01, yaw_sigma=0.05):
    """A random state and covariance, the yaw at ``yaw`` with its own ``yaw_sigma``."""
    x = 0.3 * rng.normal(size=N_STATE)
    x[YAW] = yaw
    P = spd(rng, N_STATE, 1e-3)
    P[YAW, :] = P[:, YAW] = 0.0
    P[YAW, YAW] = yaw_sigma**2
    return x, P


def _fx(X, dt=0.01):
    """A nonlinear step. The yaw turns by 0.02 rad plus a little more the further a point is
    from the central one (so wide points are not symmetric about it), and is left unwrapped
    (the filter wraps its mean)."""
    Y = X + dt * np.sin(X[:, ::-1])
    Y[:, YAW] = X[:, YAW] + 0.02 + 0.2 * (X[:, YAW] - X[0, YAW]) ** 2
    return Y


def _plan(still: bool, gates=None):
    """The tracker's shape of plan: five 3-row accelerometers (+ 3 "still" rows), one heading
    row last."""
    k = 5 + still
    gates = [float(nis_bound(3, 1e-3))] * k + [float(nis_bound(1, 1e-3))] if gates is None else gates
    groups = [MeasurementGroup(f"s{i}", np.arange(3 * i, 3 * i + 3), gates[i]) for i in range(k)]
    return GroupPlan([*groups, MeasurementGroup("heading", np.array([3 * k]), gates[k])])


def _hx_of(rng, m):
    """A nonlinear measurement of ``m`` rows: ``m - 1`` of the state but the yaw, then the yaw."""
    H = 0.5 * rng.normal(size=(m - 1, N_STATE))
    H[:, YAW] = 0.0  # accelerometers do not see the yaw

    def hx(X):
        Z = np.empty((X.shape[0], m))
        Z[:, :m - 1] = np.tanh(X @ H.T)
        Z[:, m - 1] = X[:, YAW]  # the heading measures the yaw
        return Z
    return hx


def _assert_close(a, b, rel=1e-12):
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a, b, rtol=rel, atol=rel * max(np.abs(b).max(), 1e-300))


def test_compiled_sigma_points_are_filterpys_and_an_indefinite_covariance_gets_the_eigen_points(rng):
    x, P = _state(rng)
    Q = np.diag(rng.uniform(1e-5, 1e-4, N_STATE))
    pts = SigmaPoints(N_STATE)
    X = np.empty((2 * N_STATE + 1, N_STATE))
    assert sigma_points_into(X, x, P, Q, pts.scale)
    ref = MerweScaledSigmaPoints(N_STATE, 0.5, 2.0, 0.0).sigma_points(x, P + Q)
    np.testing.assert_allclose(X, ref, rtol=0, atol=1e-13)
    indefinite = P.copy()
    indefinite[3, 3] = -1e-3
    assert not sigma_points_into(X, x, indefinite, Q, pts.scale)  # the eigen-decomposition's points
    np.testing.assert_allclose(X, reference_sigma_points(pts, x, indefinite + Q), rtol=0, atol=1e-12)


@pytest.mark.parametrize("yaw_sigma", [0.05, 1.5], ids=["points-near", "points-wrapped"])
@pytest.mark.parametrize("angle_states", [(YAW,), ()], ids=["yaw", "no-angle"])
def test_compiled_predict_is_the_numpy_predict(rng, yaw_sigma, angle_states):
    """The mean (the yaw wrapped across pi, its points spread near or wide enough to wrap),
    the covariance and the weighted residuals the update needs, equal to round-off."""
    x, P = _state(rng, yaw_sigma=yaw_sigma)
    fast, ref = _compiled_and_reference(x, P, angle_states)
    Q = np.diag(rng.uniform(1e-5, 1e-4, N_STATE))
    seen = []
    for _ in range(3):
        for f in (fast, ref):
            f.predict(lambda X: seen.append(X.copy()) or _fx(X), Q)
        np.testing.assert_allclose(seen[-2], seen[-1], rtol=0, atol=1e-12)
        _assert_close(fast.x, ref.x)
        _assert_close(fast.P, ref.P)
        _assert_close(fast._sigmas_DW, ref.sigmas_DW)
        np.testing.assert_array_equal(fast.P, fast.P.T)
    if angle_states:
        assert -np.pi <= fast.x[YAW] < np.pi
        if yaw_sigma < 1.0:
            assert fast.x[YAW] < 0.0  # the yaw has crossed pi
    # the points of a covariance that is not positive definite: the eigen-decomposition's
    fast.set_component(3, 0.0, -1e-3)
    ref.set_component(3, 0.0, -1e-3)
    fast.predict(_fx, Q)
    ref.predict(_fx, Q)
    _assert_close(fast.x, ref.x)
    _assert_close(fast.P, ref.P, 1e-10)


@pytest.mark.parametrize("weights", ["unscented", "central", "some-pairs"])
@pytest.mark.parametrize("still", [False, True], ids=["m16", "m19"])
def test_compiled_innovation_is_the_numpy_innovation(rng, still, weights):
    """Predicted measurement, innovation (the heading wrapped across pi), S, Pxz, each
    group's NIS and gate verdict (an outlier fails its gate; an infinite gate passes), and
    the diagonal blocks of S, equal to round-off; with the prediction the unscented mean, the
    central point's, or a mean that leaves some pairs of points out."""
    x, P = _state(rng, yaw=-np.pi + 0.02)
    fast, ref = _compiled_and_reference(x, P)
    wz = None
    if weights != "unscented":
        wz = np.zeros(2 * N_STATE + 1)
        if weights == "some-pairs":  # the first three pairs keep their weight, the rest go
            wz[1:4] = wz[1 + N_STATE:4 + N_STATE] = fast._Wm[1]
        wz[0] = 1.0 - wz.sum()
    fast.predict(_fx, np.eye(N_STATE) * 1e-5)
    ref.predict(_fx, np.eye(N_STATE) * 1e-5)
    k = 5 + still
    m = 3 * k + 1
    gates = [float(nis_bound(3, 1e-3))] * k + [float(nis_bound(1, 1e-3))]
    gates[1] = np.inf
    plan_fast, plan_ref = _plan(still, gates), _plan(still, gates)
    hx = _hx_of(rng, m)
    z = hx(fast.x[None])[0] + 0.05 * rng.normal(size=m)
    z[6:9] += 3.0  # the third sensor is an outlier
    z[-1] = np.pi - 0.01  # the heading, measured across pi from the yaw near -pi
    R = rng.uniform(0.01, 0.03, m)
    a = fast.innovate(z, hx, R, plan_fast, angle_rows=(m - 1,), z_weights=wz)
    b = ref.innovate(z, hx, R, plan_ref, angle_rows=(m - 1,), z_weights=wz)
    for name in ("innovation", "S", "Pxz", "nis", "z_pred"):
        _assert_close(getattr(a, name), getattr(b, name), 1e-11)
    np.testing.assert_array_equal(a.gate_ok, b.gate_ok)
    assert not a.gate_ok[2] and a.gate_ok.sum() == k
    assert abs(a.innovation[-1]) < 0.1  # wrapped: not 2 pi
    _assert_blocks_of_S(a, b)
    np.testing.assert_array_equal(a.S, a.S.T)
    assert plan_fast.last_blocks is a.blocks


def _assert_blocks_of_S(a: Innovation, b: Innovation) -> None:
    """``a``'s diagonal blocks (size -> groups, blocks) are those of the reference's ``S``."""
    sizes = {len(r) for r in a.rows}
    assert a.blocks.keys() == sizes
    for size, (which, blocks) in a.blocks.items():
        assert [len(a.rows[g]) for g in which] == [size] * len(which)
        for g, block in zip(which, blocks, strict=True):
            _assert_close(block, b.S[np.ix_(a.rows[g], a.rows[g])], 1e-11)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "reference"])
def test_the_innovation_about_the_mean_state_is_not_shrunk_by_a_wide_angle(compiled):
    """A vector of 0.6 m/s² turned by a joint known to 30° (a joint gravity cannot read): the
    sigma points spread it over ±65° and their weighted mean is 13 % short (exp(-σ²/2));
    measured exactly at the mean angle, the innovation about the central point is zero,
    about the weighted mean it is that shortfall. S and the cross covariance are the same."""
    sigma = np.radians(30.0)
    x0, P0 = np.array([0.0, 0.1]), np.diag([sigma**2, 1e-4])

    def hx(X):  # the horizontal vector (0.6, 0) turned by the first state, plus the second
        return np.stack([0.6 * np.cos(X[:, 0]) + X[:, 1], 0.6 * np.sin(X[:, 0])], 1)

    z = hx(x0[None])[0]
    inn = {}
    for central in (False, True):
        f = (BatchedUKF if compiled else ReferenceUKF)(x0, P0)
        wz = np.eye(5)[0] if central else None
        inn[central] = f.innovate(z, hx, np.full(2, 1e-6), [MeasurementGroup("acc", np.arange(2))],
                                  z_weights=wz)
    np.testing.assert_allclose(inn[True].innovation, 0.0, atol=1e-12)
    np.testing.assert_allclose(inn[True].z_pred, z, atol=1e-12)
    shortfall = inn[False].innovation[0] / 0.6
    assert 0.10 < shortfall < 0.16, shortfall  # exp(-sigma^2 / 2) = 0.87, as the points see it
    np.testing.assert_allclose(inn[True].S, inn[False].S, rtol=1e-12)
    np.testing.assert_allclose(inn[True].Pxz, inn[False].Pxz, rtol=1e-12)


def test_compiled_innovation_takes_groups_in_any_order(rng):
    """Groups that cover the rows but not in order (a 1-row group between 3-row ones, rows
    listed backwards): NIS, verdicts and diagonal blocks as NumPy has them."""
    x, P = _state(rng)
    fast, ref = _compiled_and_reference(x, P)
    m = 10
    rows = [np.array([2, 1, 0]), np.array([3]), np.array([4, 6, 5]), np.array([9]), np.array([7, 8])]
    gate = float(nis_bound(3, 1e-3))
    plans = [GroupPlan([MeasurementGroup(f"g{i}", r, gate) for i, r in enumerate(rows)]) for _ in range(2)]
    hx = _hx_of(rng, m)
    z = hx(x[None])[0] + 0.1 * rng.normal(size=m)
    R = rng.uniform(0.01, 0.03, m)
    a = fast.innovate(z, hx, R, plans[0], angle_rows=(9,))
    b = ref.innovate(z, hx, R, plans[1], angle_rows=(9,))
    _assert_close(a.nis, b.nis, 1e-11)
    np.testing.assert_array_equal(a.gate_ok, b.gate_ok)
    assert a.blocks.keys() == {1, 2, 3}
    _assert_blocks_of_S(a, b)


def test_compiled_innovation_falls_back_when_a_block_of_S_is_not_positive_definite(rng):
    x, P = _state(rng)
    fast, ref = _compiled_and_reference(x, P)
    m = 16
    hx = _hx_of(rng, m)
    R = np.full(m, 0.01)
    R[3:6] = -50.0  # the second sensor's block of S is indefinite
    z = hx(x[None])[0] + 0.05 * rng.normal(size=m)
    a = fast.innovate(z, hx, R, _plan(False), angle_rows=(m - 1,))
    b = ref.innovate(z, hx, R, _plan(False), angle_rows=(m - 1,))
    _assert_close(a.nis, b.nis, 1e-10)
    np.testing.assert_array_equal(a.gate_ok, b.gate_ok)
    assert a.nis[1] < 0.0  # (a solve of the indefinite block: no Cholesky factor gives that)


def _hold_and_mask(m):
    d = np.zeros(N_STATE)
    d[[0, 4]] = 1.0 / np.sqrt(2.0)
    hold = np.eye(N_STATE) - np.outer(d, d)  # no correction along d
    mask = np.ones((N_STATE, m))
    mask[:, -1] = 0.0
    mask[[YAW, 15], -1] = 1.0  # the heading corrects only the yaw and one bias
    return hold, mask


@pytest.mark.parametrize("held, masked, reject", [
    (False, False, None), (True, False, None), (True, True, None), (False, True, None),
    (True, True, 2), (False, False, 2)],
    ids=["optimal", "held", "held-masked", "masked", "held-masked-rejected", "optimal-rejected"])
def test_compiled_correction_is_the_numpy_correction(rng, held, masked, reject):
    """The state (the yaw wrapped across pi) and the covariance after an update with the
    optimal gain, a held and / or masked one (the general form) and a group rejected through
    ``accept``, equal to round-off over a few steps."""
    x, P = _state(rng, yaw=np.pi - 0.15)
    fast, ref = _compiled_and_reference(x, P)
    m = 16
    hx = _hx_of(rng, m)
    hold, mask = _hold_and_mask(m)
    accept = np.ones(6, bool)
    if reject is not None:
        accept[reject] = False
    crossed = False
    for _ in range(4):
        for f in (fast, ref):
            f.predict(_fx, np.eye(N_STATE) * 1e-5)
        z = hx(fast.x[None])[0] + 0.1 * rng.normal(size=m)
        z[-1] = wrap_angle(fast.x[YAW] + 0.1)  # a precise heading pulls the yaw on by 0.1 rad
        R = rng.uniform(0.01, 0.03, m)
        R[-1] = 1e-4
        before = fast.x[YAW]
        for f in (fast, ref):
            inn = f.innovate(z, hx, R, _plan(False), angle_rows=(m - 1,))
            assert f.correct(inn, accept, hold if held else None, mask if masked else None)
        crossed |= before > 3.0 and fast.x[YAW] < -3.0  # the update itself crossed pi
        _assert_close(fast.x, ref.x)
        _assert_close(fast.P, ref.P, 1e-11)
        np.testing.assert_array_equal(fast.P, fast.P.T)
    assert crossed


def _innovation(nu, S, Pxz):
    m = len(nu)
    return Innovation(("z",), (np.arange(m),), nu, S, Pxz, np.zeros(1), np.ones(1, bool), np.zeros(m))



def _kernel_status(ukf, nu, S, Pxz) -> int:
    """What the compiled correction says of these inputs (it writes into scratch arrays)."""
    x_new, P_new = np.empty(N_STATE), np.empty((N_STATE, N_STATE))
    return kalman_update_into(ukf._x, ukf._P, nu, S, Pxz, np.zeros((0, 0)), np.zeros((0, 0)),
                              np.array([YAW]), x_new, P_new)


def test_compiled_correction_repairs_a_covariance_whose_diagonal_goes_negative(rng):
    """A (wrong) cross covariance larger than P allows: P - K Pxz^T loses its positive
    diagonal, and both paths repair it the same way."""
    x, P = _state(rng)
    fast, ref = _compiled_and_reference(x, P)
    m = 3
    S = np.eye(m) * 1e-4
    Pxz = 0.1 * rng.normal(size=(N_STATE, m))
    nu = rng.normal(size=m) * 0.01
    status = _kernel_status(fast, nu, S, Pxz)
    assert status == DIAGONAL_NOT_POSITIVE
    for f in (fast, ref):
        f.correct(_innovation(nu, S, Pxz))
    _assert_close(fast.x, ref.x)
    _assert_close(fast.P, ref.P, 1e-9)
    assert np.all(np.diagonal(fast.P) > 0)


def test_compiled_correction_of_an_S_that_is_not_positive_definite_is_the_least_squares_gain(rng):
    x, P = _state(rng)
    fast, ref = _compiled_and_reference(x, P)
    m = 3
    S = np.diag([1.0, -1.0, 1.0])
    Pxz = 1e-3 * rng.normal(size=(N_STATE, m))
    nu = rng.normal(size=m) * 0.01
    assert _kernel_status(fast, nu, S, Pxz) == OK
    for f in (fast, ref):
        f.correct(_innovation(nu, S, Pxz))
    _assert_close(fast.x, ref.x, 1e-11)
    _assert_close(fast.P, ref.P, 1e-11)


def _overlapping_plan():
    """Groups that do not tile the rows: row 5 in none, rows 3-4 in two groups, rows listed
    out of order."""
    rows = [np.array([0, 1, 2]), np.array([4, 3]), np.array([3, 4, 6]), np.array([7]), np.array([9, 8])]
    return GroupPlan([MeasurementGroup(f"g{i}", r, float(nis_bound(len(r), 1e-3)))
                      for i, r in enumerate(rows)])


@pytest.mark.parametrize("full_R", [False, True], ids=["diagonal-R", "full-R"])
@pytest.mark.parametrize("plan", ["tiled", "overlapping"])
@pytest.mark.parametrize("angles", [(YAW,), (YAW, 3), ()], ids=["yaw", "two-angles", "no-angle"])
def test_compiled_filter_is_the_reference_over_every_case(rng, full_R, plan, angles):
    """A few predict / innovate / correct steps with one angle state, two or none; the
    heading row and, with two angles, a second angle row; ``R`` diagonal or full; groups
    that tile the rows or skip and overlap them; the second update of a step on points made
    after the first correction: state, covariance, innovation, S, Pxz and NIS to round-off."""
    x, P = _state(rng, yaw=np.pi - 0.05, yaw_sigma=0.3)
    x[3] = -np.pi + 0.02
    fast, ref = _compiled_and_reference(x, P, angles)
    m = 10
    hx = _hx_of(rng, m)
    angle_rows = (m - 1, 0) if len(angles) == 2 else (m - 1,) if angles else ()
    hold, _ = _hold_and_mask(m)
    for step in range(3):
        for f in (fast, ref):
            f.predict(_fx, np.eye(N_STATE) * 1e-5)
        _assert_close(fast.x, ref.x, 1e-11)
        _assert_close(fast.P, ref.P, 1e-11)
        for _update in range(2):  # the second on points made after the first correction
            z = hx(fast.x[None])[0] + 0.05 * rng.normal(size=m)
            R = np.diag(rng.uniform(0.01, 0.03, m))
            if full_R:
                R += 0.004 * (np.eye(m, k=1) + np.eye(m, k=-1))
            else:
                R = np.diagonal(R).copy()
            groups = _overlapping_plan() if plan == "overlapping" else [MeasurementGroup("z", np.arange(m))]
            a = fast.innovate(z, hx, R, groups, angle_rows=angle_rows)
            b = ref.innovate(z, hx, R, groups, angle_rows=angle_rows)
            for name in ("innovation", "S", "Pxz", "nis", "z_pred"):
                _assert_close(getattr(a, name), getattr(b, name), 1e-10)
            np.testing.assert_array_equal(a.gate_ok, b.gate_ok)
            if plan == "tiled":
                for f, inn in ((fast, a), (ref, b)):
                    f.correct(inn, np.ones(1, bool), hold if step == 1 else None)
            _assert_close(fast.x, ref.x, 1e-10)
            _assert_close(fast.P, ref.P, 1e-10)
    for a_ in angles:
        assert -np.pi <= fast.x[a_] < np.pi


def test_points_passed_to_the_update_are_weighed_about_the_state(rng):
    """Sigma points the caller makes (``X``, spread by 1.3 P and crossing the ±π seam) give
    the cross covariance the reference gives, their yaw residuals wrapped: the yaw's cross
    covariance with the heading row that reads it is the points' own yaw variance (an
    unwrapped residual of 2π would make it tens of rad²)."""
    x, P = _state(rng, yaw=np.pi - 0.01)
    fast, ref = _compiled_and_reference(x, P)
    X = reference_sigma_points(SigmaPoints(N_STATE), x, 1.3 * P)
    assert X[:, YAW].max() > np.pi  # the points do cross the seam
    m = 10
    hx = _hx_of(rng, m)
    z = hx(x[None])[0]
    a = fast.innovate(z, hx, np.full(m, 0.01), None, (m - 1,), X)
    b = ref.innovate(z, hx, np.full(m, 0.01), None, (m - 1,), X)
    _assert_close(a.Pxz, b.Pxz, 1e-11)
    _assert_close(a.S, b.S, 1e-11)
    assert a.Pxz[YAW, m - 1] == pytest.approx(1.3 * P[YAW, YAW], rel=1e-9)


def test_the_filter_says_what_is_wrong_with_its_inputs(rng):
    f = BatchedUKF(np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match=r"Q must have shape \(3, 3\)"):
        f.predict(lambda X: X, np.eye(2))
    with pytest.raises(ValueError, match=r"fx returned shape \(7, 2\), expected \(7, 3\)"):
        f.predict(lambda X: X[:, :2], np.eye(3))
    with pytest.raises(ValueError, match=r"hx returned shape \(7, 1\), expected \(7, 2\)"):
        f.innovate(np.zeros(2), lambda X: X[:, :1], np.ones(2))
    with pytest.raises(ValueError, match=r"R must be \(2, 2\) or \(2,\)"):
        f.innovate(np.zeros(2), lambda X: X[:, :2], np.ones(3))
    with pytest.raises(ValueError, match="a group's rows lie outside the measurement's 2 rows"):
        f.innovate(np.zeros(2), lambda X: X[:, :2], np.ones(2), [MeasurementGroup("g", np.array([2]))])
    with pytest.raises(ValueError, match="a group's rows must be indices from 0, got -1"):
        GroupPlan([MeasurementGroup("g", np.array([-1]))])
    with pytest.raises(ValueError, match=r"angle_states \[5\] must lie within \[-3, 3\)"):
        BatchedUKF(np.zeros(3), np.eye(3), angle_states=(5,))
    with pytest.raises(TypeError, match="points must be SigmaPoints"):
        BatchedUKF(np.zeros(3), np.eye(3), MerweScaledSigmaPoints(3, 0.5, 2.0, 0.0))


def test_the_tracker_never_imports_the_numpy_reference():
    """The NumPy reference is the tests' oracle (and the filterpy benchmark's), never a
    run-time path: no package module imports it."""
    import re
    from pathlib import Path

    import armfusion.fusion

    root = Path(armfusion.fusion.__file__).parent
    importing = re.compile(r"^\s*(from|import)\s+[\w.]*ukf_reference\b", re.MULTILINE)
    users = [p.relative_to(root).as_posix() for p in root.rglob("*.py") if importing.search(p.read_text())]
    assert users == []
