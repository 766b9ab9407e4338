"""The compiled process and measurement models equal their NumPy form on the same inputs.

The NumPy form is the filterpy baseline's (``tools/bench_track_numpy.py``), written apart
from the compiled one (whose equations are :mod:`armfusion.models.sensor_kernels`').

(The measurement model itself is held to the motion model computed from scratch in
tests/fusion/test_tracker.py; here, that the two implementations of it agree wherever the
tracker may call them: any subset of sensors in any order, the IMU in or out, the still
rows, the heading row near its wrap.)"""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.process_kernels import process_points
from armfusion.fusion.tracking.settings import StateLayout
from armfusion.fusion.tracking.tracker import BaseTurn, G, JointMotion, Tracker, make_frames
from armfusion.fusion.tracking.tracker_kernels import measurement_points

from tools.bench_track_numpy import measurement_points_numpy, process_points_numpy


@pytest.fixture(scope="module")
def setup():
    arm = load_arm("wmra")
    tr = Tracker(arm)
    rng = np.random.default_rng(7)
    q = rng.normal(0, 1, (1, 7))
    offset, qd, qdd = rng.normal(0, 0.1, 7), rng.normal(0, 0.5, (1, 7)), rng.normal(0, 1, (1, 7))
    w, wd = rng.normal(0, 0.3, (1, 3)), rng.normal(0, 1, (1, 3))
    fr = make_frames(arm, tr.accel_names, JointMotion(q, qd, qdd), offset, BaseTurn(w, wd)).take(0)
    L = tr.layout
    X = rng.normal(0, 0.05, (39, L.size))
    X[:, L.offset] += fr.offset_ref
    X[:, L.accel] = rng.normal(0, 1.0, (39, 3))
    X[:, L.imu_bias] = rng.normal(0, 0.01, (39, 3))
    return tr, fr, X


def _args(tr, fr, X, sel, still, m_B, shift):
    L = tr.layout
    n = L.n_joints
    return (X, np.asarray(sel, dtype=np.int64), tr._links.astype(np.int64), fr.axes, fr.offset_ref,
            fr.motion_mps2, fr.R_0S, tr._imu_acc_index, L.roll, n + 2, L.yaw, n + 9, G, still,
            np.asarray(m_B, float), shift)


@pytest.mark.parametrize("sel", [[0, 1, 2, 3, 4], [4, 0, 2], [3, 1], [2], [4]])
def test_accelerometers_of_any_subset_agree(setup, sel):
    tr, fr, X = setup
    a = _args(tr, fr, X, sel, False, [np.nan] * 3, 0.0)
    got, ref = measurement_points(*a), measurement_points_numpy(*a)
    assert got.shape == (39, 3 * len(sel))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13)
    # a subset's columns are the full set's columns of those sensors
    full = measurement_points(*_args(tr, fr, X, [0, 1, 2, 3, 4], False, [np.nan] * 3, 0.0))
    np.testing.assert_allclose(got, full.reshape(39, 5, 3)[:, sel].reshape(39, -1), rtol=0, atol=1e-15)


def test_still_rows_and_the_heading_row_near_its_wrap_agree(setup):
    tr, fr, X = setup
    L = tr.layout
    X = X.copy()
    m_B = np.array([18.0, -4.0, -41.0])
    # yaw spread across the heading's -pi/+pi seam: residuals on both sides of it
    heading = np.arctan2(np.cos(X[:, L.roll]) * m_B[1] - np.sin(X[:, L.roll]) * m_B[2], m_B[0])
    X[:, L.yaw] = np.pi - heading + np.linspace(-0.2, 0.2, 39)
    a = _args(tr, fr, X, [0, 1, 2, 3, 4], True, m_B, 0.03 - np.pi)
    got, ref = measurement_points(*a), measurement_points_numpy(*a)
    assert got.shape == (39, 19)
    np.testing.assert_allclose(got[:, 15:18], X[:, L.accel], rtol=0, atol=0)
    assert got[:, -1].min() < -3.0 and got[:, -1].max() > 3.0  # the seam is crossed
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


def test_heading_only_update_agrees(setup):
    tr, fr, X = setup
    a = _args(tr, fr, X, [], False, [18.0, -4.0, -41.0], 0.03 - np.pi)
    got = measurement_points(*a)
    assert got.shape == (39, 1)
    np.testing.assert_allclose(got, measurement_points_numpy(*a), rtol=0, atol=1e-12)


@pytest.mark.parametrize("have_w", [True, False])
def test_process_model_agrees_with_and_without_a_gyro(setup, have_w):
    tr, _, X = setup
    L = tr.layout
    w = np.array([0.4, -0.7, 1.3])
    a = (X, 0.01, w, have_w, L.roll, L.yaw, L.bias.start, L.accel.start, L.scale, 0.98)
    got, ref = process_points(*a), process_points_numpy(*a)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-15)
    moved = np.abs(got - X).max(axis=0) > 0
    # the gyro turns roll, pitch and yaw; the base's acceleration decays; nothing else moves
    expect = np.zeros(L.size, bool)
    expect[L.accel] = True
    if have_w:
        expect[[L.roll, L.pitch, L.yaw]] = True
    np.testing.assert_array_equal(moved, expect)


def test_a_gyro_scale_state_slows_the_turn_it_reads(setup):
    """With the gyro's z scale as a state, a point whose scale error is +2 % turns 2 % less
    about z than the gyro reads (the reading is (1 + s) times the true rate)."""
    tr, _, X = setup
    L = StateLayout(tr.layout.n_joints, gyro_scale=True)
    Xs = np.zeros((len(X), L.size))
    Xs[:, :L.scale] = X[:, :L.scale]
    Xs[:, L.roll] = Xs[:, L.pitch] = 0.0  # level: the z rate is the heading's
    Xs[:, L.bias] = 0.0
    Xs[1, L.scale] = 0.02
    w = np.array([0.0, 0.0, 1.0])
    a = (Xs, 0.01, w, True, L.roll, L.yaw, L.bias.start, L.accel.start, L.scale, 1.0)
    got = process_points(*a)
    np.testing.assert_allclose(got, process_points_numpy(*a), rtol=0, atol=1e-15)
    turned = got[:, L.yaw] - Xs[:, L.yaw]
    assert turned[0] == pytest.approx(0.01, rel=1e-9)
    assert turned[1] == pytest.approx(0.01 / 1.02, rel=1e-9)
