"""Loopback-only Zenoh fixtures: a free port on 127.0.0.1 and a simulated recording."""

from __future__ import annotations

import socket

import pytest
from armfusion.fusion.service.zenoh_config import ZenohSettings


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
    from armfusion.fusion.cli.simulate import SimulationOptions, simulate

    out = tmp_path_factory.mktemp("rec") / "startup.mcap"
    simulate("wmra", "startup", out, SimulationOptions(duration_s=4.0, rate_hz=100.0, seed=3))
    return out


@pytest.fixture
def loopback_port() -> int:
    """A free TCP port on 127.0.0.1."""
    return free_port()


# --- the fusion node in a thread (helpers: service_helpers.py) ----------------------------------


@pytest.fixture
def fusion_node():
    """``fusion_node(settings, arm, maneuver=None, **node_settings)``: a context manager running a
    FusionNode (its ``NodeSettings`` made of ``node_settings``) in a thread on a session opened
    from ``settings``; yields ``(node, result)`` where ``result["report"]`` is its ServeReport
    once the block has ended."""
    import contextlib
    import threading

    from armfusion.fusion.service.serve import FusionNode
    from armfusion.fusion.service.serve_settings import NodeSettings
    from armfusion.fusion.service.zenoh_config import open_session

    @contextlib.contextmanager
    def run(settings, arm, robot: str = "chair1", maneuver=None, **node_settings):
        stop = threading.Event()
        result: dict = {}
        with open_session(settings) as session:
            node = FusionNode(session, arm, robot, NodeSettings(**node_settings), maneuver=maneuver)
            th = threading.Thread(target=lambda: result.setdefault("report", node.run(stop)), daemon=True)
            th.start()
            try:
                # (the first node of a run compiles the kernels it has no cache for: up to a minute)
                assert node.ready.wait(90.0), "the fusion node never became ready"
                yield node, result
            finally:
                stop.set()
                th.join(30.0)
        assert "report" in result, "the fusion node did not stop"

    return run


@pytest.fixture(scope="session")
def renk_recording():
    """9 s of the WMRA's renk-maneuver at 100 Hz: still until 5 s, then every joint sweeps
    slowly (the chair parked). In memory, with truth."""
    from armfusion.fusion.configfile import load_arm
    from armfusion.models.simulator import simulate

    rec, _ = simulate(load_arm("wmra"), "renk-maneuver", 9.0, 100.0, seed=11)
    return rec
