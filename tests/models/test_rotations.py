"""The one set of rotation and angle helpers (armfusion.models.rotations): conventions a user relies on."""

from __future__ import annotations

import numpy as np
from armfusion.models.rotations import (
    DEG,
    R_from_rpy,
    exp_so3,
    exp_so3_one,
    skew,
    tilt_from_up,
    up_from_tilt,
    wrap_angle,
)


def test_up_is_the_world_up_seen_from_the_tilted_base():
    rng = np.random.default_rng(3)
    roll, pitch, yaw = rng.uniform(-1.2, 1.2, (3, 50))
    expected = np.swapaxes(R_from_rpy(roll, pitch, yaw), -1, -2) @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(up_from_tilt(roll, pitch), expected, atol=1e-15)
    # roll and pitch broadcast against each other (one roll, many pitches)
    assert up_from_tilt(0.1, pitch).shape == (50, 3)
    np.testing.assert_allclose(tilt_from_up(up_from_tilt(roll, pitch)), np.stack([roll, pitch], -1),
                               atol=1e-14)
    # any length: an accelerometer reading in g, not a unit vector
    np.testing.assert_allclose(tilt_from_up(0.98 * up_from_tilt(0.2, -0.3)), [0.2, -0.3], atol=1e-14)


def test_wrap_angle_keeps_minus_pi_to_pi_and_the_input_type():
    a = np.array([-np.pi, np.pi, 3 * np.pi / 2, -7.0, 0.0, 1e-3])
    np.testing.assert_allclose(wrap_angle(a), [-np.pi, -np.pi, -np.pi / 2, 2 * np.pi - 7.0, 0.0, 1e-3],
                               atol=1e-15)
    assert type(wrap_angle(190 * DEG)) is float
    assert abs(wrap_angle(190 * DEG) + 170 * DEG) < 1e-15


def test_wrap_angle_compiled_gives_the_numpy_numbers():
    from armfusion.fusion.tracking.ukf_kernels import _wrap

    x = np.random.default_rng(4).uniform(-20.0, 20.0, 200)
    assert np.array_equal([_wrap(float(v)) for v in x], wrap_angle(x))


def test_skew_is_the_cross_product_for_columns_and_rows():
    rng = np.random.default_rng(5)
    w, u = rng.normal(size=3), rng.normal(size=(10, 3))
    np.testing.assert_allclose(skew(w) @ u.T, np.cross(w, u).T, atol=1e-15)
    np.testing.assert_allclose(u @ skew(w), np.cross(u, w), atol=1e-15)
    # batched: one matrix per vector, the same as one at a time
    assert np.array_equal(skew(u), np.stack([skew(x) for x in u]))
    np.testing.assert_allclose(skew(u) @ w, np.cross(u, w), atol=1e-15)


def test_one_vector_rodrigues_is_the_batched_one():
    rng = np.random.default_rng(6)
    v = rng.normal(0.0, 1.0, (200, 3)) * rng.choice([1e-13, 1e-4, 1.0], (200, 1))
    one = np.stack([exp_so3_one(x) for x in v])
    # below 1e-12 rad the one-vector form returns the identity: off by at most the angle
    np.testing.assert_allclose(one, exp_so3(v), atol=1e-12)
    np.testing.assert_allclose(exp_so3_one(tuple(v[0])), one[0], atol=0)


def test_the_one_attitude_form_of_R_from_rpy_is_the_same_rotation():
    """The scalar form the compiled kernels use equals the batched one (to rounding)."""
    from armfusion.models.rotations import R_from_rpy, R_from_rpy_into

    rng = np.random.default_rng(7)
    for r, p, y in rng.uniform(-np.pi, np.pi, (50, 3)):
        R = np.empty((3, 3))
        R_from_rpy_into(r, p, y, R)
        np.testing.assert_allclose(R, R_from_rpy(r, p, y), atol=1e-15)
