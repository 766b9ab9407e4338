"""The compiled cross products give np.cross's numbers, to the bit."""

import numpy as np
from armfusion.fusion.tracking.turn_kernels import cross_rows, cross_vec, origin_accel_points


def test_cross_rows_and_vec_are_numpys_to_the_bit():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(5, 3)) * 1e3, rng.normal(size=(5, 3)) * 1e-3
    assert np.array_equal(cross_rows(a, b), np.cross(a, b))
    assert np.array_equal(cross_vec(a[0], b[0]), np.cross(a[0], b[0]))


def test_origin_accel_points_moves_only_the_acceleration_columns_as_numpy_would():
    rng = np.random.default_rng(4)
    X = rng.normal(size=(9, 12))
    w, wd = rng.normal(size=3), rng.normal(size=3) * 10.0
    pivot, accel = 7, 2
    want = X.copy()
    r = want[:, pivot:pivot + 3]
    want[:, accel:accel + 3] += np.cross(wd, r) + np.cross(w, np.cross(w, r))
    got = origin_accel_points(X, pivot, accel, w, wd)
    assert np.array_equal(got, want)
    assert got is not X and not np.shares_memory(got, X)
    assert not np.array_equal(X, want)  # the points handed in are left as they were
