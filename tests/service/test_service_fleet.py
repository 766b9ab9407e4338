"""A fleet over real Zenoh sessions on 127.0.0.1: `armfusion fleet` runs three simulated
chairs as separate processes (fake drivers -> serve each) through its router, and one
`armfusion monitor` (another process) sees all three with joint states; SIGINT stops the
fleet cleanly and leaves none of its processes behind."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from armfusion.fusion.service.processes import free_loopback_port as free_port

ROBOTS = ("chair1", "chair2", "chair3")


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d.name))
    return out


def _wait_for_port(port: int, timeout_s: float) -> bool:
    """Wait until something accepts TCP connections on 127.0.0.1:``port`` (the router)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.1)
    return False


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_monitor_sees_three_chairs_of_a_fleet(tmp_path):
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    cli = [sys.executable, "-m", "armfusion.fusion.cli"]
    fleet = subprocess.Popen([*cli, "fleet", "--chairs", "3", "--duration", "60", "--rate", "50",
                              "--router-listen", router,
                              "--workdir", str(tmp_path / "fleet")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    children: list[int] = []
    try:
        assert _wait_for_port(port, 60.0), "the fleet's router did not start"
        mon = subprocess.run([*cli, "monitor", "--connect", router, "--expect", "3", "--duration", "90",
                              "--json"], capture_output=True, text=True, timeout=120)
        children = _children(fleet.pid)
        assert mon.returncode == 0, mon.stderr
        doc = json.loads(mon.stdout)
    finally:
        fleet.send_signal(signal.SIGINT)
        try:
            out, err = fleet.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            fleet.kill()
            out, err = fleet.communicate()
    robots = doc["robots"]
    assert set(ROBOTS) <= set(robots), robots.keys()
    for name in ROBOTS:
        r = robots[name]
        assert r["alive"] is True, (name, r)
        joints = r["joints"]
        assert joints is not None, (name, r)
        angles = {k: v for k, v in joints.items() if k != "t_s"}
        assert list(angles) == [f"j{k}" for k in range(1, 8)]
        assert all(math.isfinite(v["deg"]) and v["sigma_deg"] > 0 and v["flag"] for v in angles.values())
        assert r["heading"] is not None and math.isfinite(r["heading"]["deg"])
        assert {"drivers", "serve"} <= set(r["nodes"]), r["nodes"]
        # its status comes once a second: it may still say so from just before the first estimate
        assert r["nodes"]["serve"]["state"] in ("calibrating", "tracking"), r["nodes"]["serve"]
    assert doc["dropped"] == {}
    assert fleet.returncode == 0, err
    assert "fleet stopped" in out
    # the router and every chair's two processes: started, and gone after the stop
    assert len(children) == 7, children
    assert not [p for p in children if _alive(p)]
