"""Loopback-only Zenoh fixtures: a free port on 127.0.0.1 and a simulated recording."""

from __future__ import annotations

import socket

import pytest

from fusion.service.zenoh_config import ZenohSettings


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def hub_settings():
    """A pair of settings: a node listening on a free loopback port, and one connecting to it."""
    port = free_port()
    listener = ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[])
    connector = ZenohSettings(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])
    return listener, connector


@pytest.fixture(scope="session")
def startup_recording(tmp_path_factory):
    """4 s of the WMRA's startup scenario at 100 Hz, as MCAP."""
    from fusion.simulate_cmd import simulate

    out = tmp_path_factory.mktemp("rec") / "startup.mcap"
    simulate("wmra", "startup", out, duration_s=4.0, rate_hz=100.0, seed=3)
    return out


@pytest.fixture
def loopback_port() -> int:
    """A free TCP port on 127.0.0.1."""
    return free_port()
