"""The monitor over a real Zenoh session on 127.0.0.1: robots appear with their messages and
liveliness tokens, a robot whose fusion node stops is shown gone, a bad payload is counted
and dropped; the table and the JSON show what a person needs. And the drivers' Zenoh
options are refused without --robot."""

from __future__ import annotations

import math
import time

from armfusion.fusion.cli.main import app
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.monitor import Monitor, render, snapshot_json
from armfusion.fusion.service.zenoh_config import open_session
from rich.console import Console
from service_helpers import wait_for
from typer.testing import CliRunner

NAMES = ("j1", "j2")


def _joints(robot: str, t_s: float, flags=("ok", "gimbal_lock")) -> bytes:
    return pl.encode(pl.JointState(robot, t_s, NAMES, (0.5, -1.0), (0.001, 0.5), flags))


def test_monitor_sees_robots_come_and_go(hub_settings):
    listener, connector = hub_settings
    with open_session(listener) as s_mon, open_session(connector) as s_pub:
        mon = Monitor(s_mon)
        token = s_pub.liveliness().declare_token(pl.status_key("chairA"))

        def serve_status_seen() -> bool:  # (once it is, the monitor's subscriptions reach s_pub)
            s_pub.put(pl.status_key("chairA"), pl.encode(pl.Status(
                "chairA", "serve", "tracking", time.time(), "tracking", (("samples", 900),))))
            return "chairA" in mon.snapshot() and "serve" in mon.snapshot()["chairA"].nodes

        assert wait_for(serve_status_seen, 10.0)
        s_pub.put(pl.status_key("chairA"), pl.encode(pl.Status("chairA", "drivers", "running", time.time(),
                                                                "", (("samples.acc1", 1000),))))
        s_pub.put(pl.joints_key("chairA"), _joints("chairA", 1.0))
        s_pub.put(pl.heading_key("chairA"), pl.encode(
            pl.Heading("chairA", 1.0, 0.25, 0.02, 0.0, 1e-3, 0.0, 1e-3, (0.0, 0.0, 0.0))))
        s_pub.put(pl.joints_key("chairB"), _joints("chairB", 2.0, ("ok", "ok")))
        s_pub.put(pl.joints_key("chairB"), b'{"v": 2, "type": "joints"}')  # a future version: dropped
        assert wait_for(lambda: mon.with_joints() == 2 and mon.snapshot()["chairA"].heading is not None
                        and len(mon.snapshot()["chairA"].nodes) == 2 and mon.dropped, 10.0)
        doc = snapshot_json(mon)
        a, b = doc["robots"]["chairA"], doc["robots"]["chairB"]
        assert a["alive"] is True and b["alive"] is None  # chairB has no fusion node's token
        assert a["joints"]["j1"] == {"deg": round(math.degrees(0.5), 4),
                                     "sigma_deg": round(math.degrees(0.001), 4), "flag": "ok"}
        assert a["joints"]["j2"]["flag"] == "gimbal_lock"
        assert a["heading"]["deg"] == round(math.degrees(0.25), 4)
        assert a["nodes"]["serve"]["state"] == "tracking" and a["nodes"]["drivers"]["counters"] == {
            "samples.acc1": 1000}
        assert 0 <= a["age_s"] < 10
        assert doc["dropped"] == {"unknown_version": 1}
        console = Console(width=160, record=True)
        console.print(render(mon))
        text = console.export_text()
        assert "2 robots" in text and "alive" in text and "gimbal_lock" in text
        assert "out 1000" in text and "in 900" in text and "unknown_version 1" in text
        token.undeclare()  # the fusion node stops
        assert wait_for(lambda: mon.snapshot()["chairA"].alive is False, 10.0)
        console = Console(width=160, record=True)
        console.print(render(mon))
        assert "gone" in console.export_text()
        mon.close()


def test_monitor_only_the_robots_asked_for(hub_settings):
    listener, connector = hub_settings
    with open_session(listener) as s_mon, open_session(connector) as s_pub:
        mon = Monitor(s_mon, robots=("chairB",))

        def both_published() -> bool:
            # (published again until heard: a put before the two sessions have met is lost)
            s_pub.put(pl.joints_key("chairA"), _joints("chairA", 1.0))
            s_pub.put(pl.joints_key("chairB"), _joints("chairB", 1.0))
            return mon.with_joints() == 1

        assert wait_for(both_published, 10.0)
        time.sleep(0.2)
        assert list(mon.snapshot()) == ["chairB"]
        mon.close()


def test_drivers_zenoh_options_need_robot():
    r = CliRunner().invoke(app, ["drivers", "--fake", "--connect", "tcp/127.0.0.1:7447"])
    assert r.exit_code == 2
    assert "--connect: only with --robot" in r.output


def test_monitor_refuses_bad_robot_name():
    r = CliRunner().invoke(app, ["monitor", "--robot", "bad/name", "--once", "--listen", "tcp/127.0.0.1:0"])
    assert r.exit_code == 2
    assert "'bad/name'" in r.output
