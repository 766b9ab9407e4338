"""Shared fixtures: the shipped arm configs and seeded random generators."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.configfile import load_arm


@pytest.fixture(scope="session")
def wmra():
    return load_arm("wmra")


@pytest.fixture(scope="session")
def crs():
    return load_arm("crs_a465")


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


def random_poses(arm, n, rng):
    """Poses drawn uniformly inside the joint limits, ``(n, n_joints)`` rad."""
    return rng.uniform(arm.min_rad, arm.max_rad, size=(n, arm.n_joints))
