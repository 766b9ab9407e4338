"""A chair's acceleration changes smoothly: with ``base_jerk_sigma_mps3`` above zero (off by
default) the tracker holds its jerk (the acceleration's rate of change) as a state, where the
config does not describe its base's motion otherwise."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.process import ProcessModel
from armfusion.fusion.tracking.settings import StateLayout, TrackerSettings
from armfusion.fusion.tracking.tracker import Tracker
from armfusion.fusion.tracking.process_kernels import process_points_tangent
from armfusion.models.arm import BaseMotion


def test_the_acceleration_changes_by_its_jerk_and_the_jerk_decays():
    L = StateLayout(2, jerk=True)
    X = np.zeros((3, L.size))
    X[:, L.accel] = [0.1, -0.2, 0.0]
    X[:, L.jerk_B] = [[1.0, 0.0, -0.5], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]]
    dt, steps = 0.01, 10
    for _ in range(steps):
        X, _ = process_points_tangent(X, dt, np.zeros(3), False, L.roll, L.yaw, L.bias.start, L.accel.start,
                                      L.scale, 1.0, -1, 0.0, L.jerk_B.start, 1.0)
    np.testing.assert_allclose(X[0, L.accel], [0.1 + 0.1, -0.2, -0.05], atol=1e-12)
    np.testing.assert_allclose(X[1, L.accel], [0.1, -0.2 + 0.2, 0.0], atol=1e-12)
    # decaying jerk: a geometric sum; no jerk block: the acceleration only decays, as before
    Y, _ = process_points_tangent(X[:1].copy(), dt, np.zeros(3), False, L.roll, L.yaw, L.bias.start,
                                  L.accel.start, L.scale, 0.5, -1, 0.0, L.jerk_B.start, 0.25)
    np.testing.assert_allclose(Y[0, L.accel], 0.5 * X[0, L.accel] + dt * X[0, L.jerk_B])
    np.testing.assert_allclose(Y[0, L.jerk_B], 0.25 * X[0, L.jerk_B])
    Z, _ = process_points_tangent(X[:1].copy(), dt, np.zeros(3), False, L.roll, L.yaw, L.bias.start,
                                  L.accel.start, L.scale, 0.5)
    np.testing.assert_allclose(Z[0, L.accel], 0.5 * X[0, L.accel])


def test_a_chair_holds_its_jerk_where_asked_and_a_described_base_does_not():
    arm = load_arm("wmra")
    st = TrackerSettings(base_jerk_sigma_mps3=3.0)
    tr = Tracker(arm, st)
    assert tr.layout.jerk_B is not None
    assert [n for n in tr.state_names if n.startswith("jerk_B")] == ["jerk_B[x]", "jerk_B[y]", "jerk_B[z]"]
    # its noise: the jerk's Gauss-Markov spread, the acceleration's own share of its spread
    Q = ProcessModel(st, tr.layout).Q(0.01, True, False).diagonal()
    assert Q[tr.layout.jerk_B] == pytest.approx(st.base_jerk_sigma_mps3**2 * (1 - np.exp(-0.02 / 0.3)))
    assert Q[tr.layout.accel] == pytest.approx((st.base_accel_direct_share * 0.7) ** 2
                                               * (1 - np.exp(-0.02 / st.base_accel_tau_s)))
    # a base the config describes (a hand) keeps the first-order acceleration it describes
    assert st.for_base(BaseMotion(3.0, 0.5)).base_jerk_sigma_mps3 == 0.0
    assert StateLayout(7).size + 3 == StateLayout(7, jerk=True).size
    assert Tracker(arm).layout.jerk_B is None  # off by default


def test_the_euler_angle_path_and_its_numpy_reference_carry_the_jerk_alike():
    """The Euler-angle path (the speed baseline's, one point at a time) moves the acceleration
    by its jerk as the tangent path does, and the NumPy reference agrees."""
    from tools.bench_track_numpy import process_points_numpy

    L = StateLayout(3, jerk=True)
    rng = np.random.default_rng(7)
    X = rng.normal(scale=0.1, size=(7, L.size))
    args = (X, 0.01, np.array([0.1, -0.2, 0.3]), True, L.roll, L.yaw, L.bias.start, L.accel.start, L.scale,
            0.99, L.jerk_B.start, 0.9)
    Y = ProcessModel(TrackerSettings(base_jerk_sigma_mps3=3.0), L).fx(X, 0.01, np.array([0.1, -0.2, 0.3]))
    decay = np.exp(-0.01 / TrackerSettings().base_accel_tau_s)
    np.testing.assert_allclose(Y[:, L.accel], decay * X[:, L.accel] + 0.01 * X[:, L.jerk_B], atol=1e-12)
    ref = process_points_numpy(*args)
    np.testing.assert_allclose(ref[:, L.accel], 0.99 * X[:, L.accel] + 0.01 * X[:, L.jerk_B], atol=1e-12)
    np.testing.assert_allclose(ref[:, L.jerk_B], 0.9 * X[:, L.jerk_B], atol=1e-12)
    from armfusion.fusion.tracking.process_kernels import process_points

    np.testing.assert_allclose(process_points(*args), process_points_numpy(*args), atol=1e-12)
