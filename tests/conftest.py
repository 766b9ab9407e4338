"""Shared fixtures: the shipped arm configs and seeded random generators; and which tests
share the network, so a parallel run (pytest-xdist, ``-n``) runs them one at a time."""

from __future__ import annotations

import os
import re
from functools import cache
from pathlib import Path

import numpy as np
import pytest

# a parallel run's workers inherit a terminal size (COLUMNS 80) that a serial run does not
# have, and the command line's consoles take their width from it once, at import: each test
# that needs a width gives its own (CliRunner's env), so the workers start without one
for _size in ("COLUMNS", "LINES"):
    os.environ.pop(_size, None)

from armfusion.fusion.configfile import load_arm  # noqa: E402


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


@pytest.fixture(scope="session")
def calibrated_wmra_arm():
    """The WMRA with calibrated sensors (the simulation adds noise only)."""
    from tools.bench_track import calibrated_wmra

    return calibrated_wmra()


@pytest.fixture(scope="session")
def daily_use_110s(calibrated_wmra_arm):
    """110 s of the calibrated WMRA in daily use (seed 21): the model-change alarm's tests
    turn or bias a sensor in it, in the tracker (tests/fusion/test_alarm.py) and replayed
    into the service (tests/service/test_service_health.py)."""
    from armfusion.models.simulator import simulate

    rec, _ = simulate(calibrated_wmra_arm, "daily-use", 110.0, seed=21)
    return rec


_NETWORK = re.compile(r'zenoh|"(serve|demo|replay|record|monitor|drivers|fleet)"')
"""What marks a test module as one that may open Zenoh sessions: it names zenoh, or runs a
command that publishes or listens."""


@cache
def _uses_network(path: Path) -> bool:
    return "service" in path.parts or bool(_NETWORK.search(path.read_text(encoding="utf-8")))


def pytest_collection_modifyitems(items):
    """Every test that may open a Zenoh session goes to one worker of a parallel run: the
    default endpoint (tcp/127.0.0.1:7447), the timing of a node under test and the ports
    picked free are then never contended by a second worker. The rest spread over the workers."""
    for item in items:
        if _uses_network(Path(str(item.path))):
            item.add_marker(pytest.mark.xdist_group("network"))

