"""What gravity reads where it cannot read single joints (fusion/startup/combinations.py):
found from the covariance the readings leave, never from a list of known pairs."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.startup.combinations import combination_name, observable_combinations
from armfusion.models.rotations import DEG

PRIOR_DEG = 30.0
"""Each variable's prior sigma (the tracker's unknown joint's)."""
READ_DEG = 0.5
"""How well one row of the information reads its combination (1 sigma)."""


def _covariance(rows: list[list[float]], n: int) -> np.ndarray:
    """The covariance a prior of PRIOR_DEG on each of ``n`` variables and the information rows
    ``rows`` (each read to READ_DEG) leave: the readings' Jacobian's row space is what they see."""
    J = np.array(rows, float) / (READ_DEG * DEG)
    return np.linalg.inv(np.eye(n) / (PRIOR_DEG * DEG) ** 2 + J.T @ J)


def test_parallel_axes_are_read_as_their_sum_and_the_sum_is_named():
    """A forearm accelerometer reads j2 + j3 (parallel axes), a wrist one j2 + j3 + j4, and
    nothing reads j1: the one combination is "j2 + j3" (j4 is known alone, j1 not at all), its
    sigma that of exactly j2 + j3 under the covariance."""
    names = ["j1", "j2", "j3", "j4"]
    P = _covariance([[0, 1, 1, 0], [0, 1, 1, 1]], 4)
    x = np.radians([10.0, -60.0, 70.0, -120.0])
    found = observable_combinations(P, x, names, 5.0 * DEG)
    assert [c.name for c in found] == ["j2 + j3"]
    c = found[0]
    v = c.vector(names)
    assert np.isclose(c.sigma_rad, np.sqrt(v @ P @ v)) and c.sigma_rad < 1.0 * DEG
    assert np.isclose(c.angle_rad, x[1] + x[2])
    assert np.sqrt(P[1, 1]) > 20 * DEG  # each alone unknown


def test_three_parallel_joints_read_only_together():
    """Three parallel axes and one reading of their total: "j2 + j3 + j4"; with j2 and j3
    read apart as well, no combination (each is known alone)."""
    names = ["j1", "j2", "j3", "j4"]
    found = observable_combinations(_covariance([[0, 1, 1, 1]], 4), np.zeros(4), names, 5.0 * DEG)
    assert [c.name for c in found] == ["j2 + j3 + j4"]
    P = _covariance([[0, 1, 1, 1], [0, 1, 0, 0], [0, 0, 1, 0]], 4)
    assert observable_combinations(P, np.zeros(4), names, 5.0 * DEG) == ()


def test_a_joint_and_the_base_tilt_and_a_difference():
    """A joint whose axis is parallel to the base's pitch axis is read with the tilt: named
    with the tilt's name; a reading of a difference gets a minus."""
    found = observable_combinations(_covariance([[1, 1]], 2), np.zeros(2), ["shoulder", "base pitch"],
                                    5.0 * DEG)
    assert [c.name for c in found] == ["shoulder + base pitch"]
    found = observable_combinations(_covariance([[1, -1]], 2), np.radians([20.0, 5.0]), ["a", "b"], 5.0 * DEG)
    assert [c.name for c in found] == ["a - b"] and np.isclose(found[0].angle_rad, np.radians(15.0))


def test_a_combination_known_no_better_than_its_terms_is_not_reported():
    """Two joints each read alone, to a few degrees: their sum is no better known than they
    are, and is not reported; a limit below the sum's sigma reports nothing either."""
    P = np.diag(np.radians([3.0, 3.0]) ** 2)
    assert observable_combinations(P, np.zeros(2), ["a", "b"], 5.0 * DEG, np.array([True, True])) == ()
    P = _covariance([[1, 1]], 2)
    assert observable_combinations(P, np.zeros(2), ["a", "b"], 0.1 * DEG) == ()


def test_names_read_as_written():
    assert combination_name([("shoulder", 1.0), ("elbow", 1.0)]) == "shoulder + elbow"
    assert combination_name([("a", 1.0), ("b", -0.5)]) == "a - 0.5 b"
