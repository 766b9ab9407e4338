"""The fleet deployment of docs/service-deploy.md, its steps as written, every
node an ``armfusion`` process on loopback: ``armfusion deploy`` writes the certificates,
credentials and configs; the base station's router runs from its router.json5 alone (TLS,
mutual TLS, the access-control policy), each chair's router from its own; the fusion node,
the drivers, the base station's monitor and recalibrate from their credential files. Then
the attacks the docs name: a node whose user may not publish raw samples is told that nothing
it sent was admitted, a certificate the fleet's CA did not sign and plain TCP on the TLS
port are refused, a chair does not hear another.

The certificates are made by the openssl command line (as the deploy command makes them).
"""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
from armfusion.fusion.cli.main import app
from armfusion.fusion.service.processes import Children
from service_helpers import free_port
from typer.testing import CliRunner

CHAIRS = ("chair1", "chair2")


def _run(*args: str):
    """``armfusion ARGS`` in this process (the long-running nodes are processes); the result
    has ``exit_code``, ``stdout`` and ``stderr``."""
    return CliRunner(env={"COLUMNS": "200"}).invoke(app, list(args))


def _deploy(fleet: Path, base_port: int, chair_ports: dict[str, int]) -> None:
    """Step 1: one command per chair (each chair's own router port: they share this machine)."""
    for c in CHAIRS:
        r = _run("deploy", c, "--fleet", str(fleet), "--local", "--base-address", "127.0.0.1",
                 "--base-port", str(base_port), "--chair-port", str(chair_ports[c]), "--json")
        assert r.exit_code == 0, r.stderr
    assert json.loads(r.stdout)["base_router_admits"] == list(CHAIRS)
    # nothing overwritten without asking
    again = _run("deploy", "chair1", "--fleet", str(fleet), "--local")
    assert again.exit_code == 2 and "--force to replace" in again.stderr
    # secrets readable by their owner only
    for secret in ("ca/ca.key", "base/tls/router.key", "chair1/tls/chair1.key", "chair1/zenoh/chair1.users",
                   "chair1/zenoh/drivers.json5", "chair1/zenoh/serve.json5"):
        assert stat.S_IMODE((fleet / secret).stat().st_mode) == 0o600, secret
    users = dict(line.split(":", 1) for line in (fleet / "chair1/zenoh/chair1.users").read_text().split())
    assert sorted(users) == ["drivers", "monitor", "record", "serve"]
    assert len(set(users.values())) == 4  # one password each
    assert f'password: "{users["drivers"]}"' in (fleet / "chair1/zenoh/drivers.json5").read_text()


def test_the_fleet_deployment_runs_as_docs_service_md_writes_it(tmp_path, startup_recording):
    fleet = tmp_path / "fleet"
    base_port = free_port()
    chair_ports = {c: free_port() for c in CHAIRS}
    _deploy(fleet, base_port, chair_ports)
    base_dir, z1 = fleet / "base" / "zenoh", fleet / "chair1" / "zenoh"

    with Children(tmp_path / "nodes") as ch:
        # step 2: the base station's router, from its config file alone: TLS, on its port
        base = ch.start("base-router", ["router", "--zenoh-config", str(base_dir / "router.json5")])
        assert base.wait_for_line(f"listening on tls/127.0.0.1:{base_port} ({base_dir / 'router.json5'})",
                                  60.0), base.stderr_tail()
        # step 3: each chair's router (its nodes on loopback TCP; to the base over mutual TLS)
        for c in CHAIRS:
            r = ch.start(f"{c}-router", ["router", "--zenoh-config", str(fleet / c / "zenoh/router.json5")])
            assert r.wait_for_line(f"listening on tcp/127.0.0.1:{chair_ports[c]}", 60.0), r.stderr_tail()
            said = next(line for line in r.lines if "listening on" in line)
            assert f"connecting to tls/127.0.0.1:{base_port} ({fleet / c / 'zenoh/router.json5'})" in said
        serve = ch.start("serve", ["serve", "--robot", "chair1", "--zenoh-config", str(z1 / "serve.json5"),
                                   "--json"])

        # (while the fusion node starts) a certificate the fleet's CA did not sign, whatever its
        # name, is refused at the link; and plain TCP on the TLS port
        rogue = tmp_path / "rogue"
        assert _run("deploy", "chair1", "--fleet", str(rogue), "--local").exit_code == 0
        intruder = (rogue / "base/zenoh/base.json5").read_text()
        intruder = intruder.replace(str(rogue / "base/tls/ca.pem"), str(fleet / "base/tls/ca.pem"))
        intruder = intruder.replace('"tls/127.0.0.1:7448"', f'"tls/127.0.0.1:{base_port}"')
        (rogue / "intruder.json5").write_text(intruder)
        r = _run("monitor", "--zenoh-config", str(rogue / "intruder.json5"), "--once", "--duration", "1")
        assert r.exit_code == 2 and "cannot open the Zenoh session" in r.stderr
        r = _run("monitor", "--mode", "client", "--connect", f"tcp/127.0.0.1:{base_port}", "--once",
                 "--duration", "1")
        assert r.exit_code == 2 and "cannot open the Zenoh session" in r.stderr
        assert serve.wait_for_line("serving", 120.0), serve.stderr_tail()

        # a node the chair's policy forbids to publish raw samples sees a subscriber, sends, and is told
        r = _run("replay", str(startup_recording), "--speed", "max", "--robot", "chair1",
                 "--zenoh-config", str(z1 / "monitor.json5"), "--admitted-within", "3", "--json")
        assert r.exit_code == 1, r.stderr
        assert "admitted none of the samples" in r.stderr and "none reached it" in r.stderr
        told = json.loads(r.stdout)
        assert told["unmatched"] == [] and sum(told["samples"].values()) > 0
        assert told["admission"]["state"] == "refused"

        # the drivers (the one user allowed) publish; the base station watches and asks
        record = ch.start("record", ["record", str(tmp_path / "chair1.mcap"), "--robot", "chair1",
                                     "--zenoh-config", str(z1 / "record.json5"), "--json"])
        assert record.wait_for_line("recording armfusion/chair1/raw/*", 60.0), record.stderr_tail()
        drivers = ch.start("drivers", ["drivers", "--fake", "--realtime", "--scenario", "startup",
                                       "--duration", "6", "--robot", "chair1", "--zenoh-config",
                                       str(z1 / "drivers.json5"), "--wait", "60", "--json"])
        r = _run("monitor", "--zenoh-config", str(base_dir / "base.json5"), "--once", "--expect", "1",
                 "--duration", "60", "--json")
        assert r.exit_code == 0, r.stderr
        robots = json.loads(r.stdout)["robots"]
        assert set(robots) == {"chair1"} and robots["chair1"]["joints"] is not None
        r = _run("recalibrate", "--robot", "chair1", "--zenoh-config", str(base_dir / "base.json5"), "--json")
        assert r.exit_code in (0, 1), r.stderr  # a reply (calibrated, or refused: the arm moves)
        assert json.loads(r.stdout)["robot"] == "chair1"
        # chair2 does not hear chair1 (the base router lets only the base station hear every chair)
        r = _run("monitor", "--zenoh-config", str(fleet / "chair2/zenoh/monitor.json5"), "--once",
                 "--duration", "2", "--json")
        assert r.exit_code == 0, r.stderr
        assert json.loads(r.stdout)["robots"] == {}

        assert drivers.proc.wait(90) == 0, drivers.stderr_tail()
        ch.stop_all(children=[serve, record])
    published = json.loads(drivers.stdout_path.read_text())["published"]
    recorded = json.loads(record.stdout_path.read_text())
    assert 0 < sum(recorded["samples"].values()) <= sum(published["samples"].values())
    assert recorded["dropped"] == {}
    assert published["admission"]["state"] == "admitted"
    report = json.loads(serve.stdout_path.read_text())
    # what the fusion node took in came from the drivers (it stopped as their last batches came:
    # up to all of them), none from the forbidden replay
    assert 0 < report["samples"] <= sum(published["samples"].values())
    assert report["startup_t_s"] is not None and report["dropped"] == {}


def test_a_config_files_endpoints_hold_unless_an_option_replaces_them_and_the_node_says_whose():
    from armfusion.fusion.cli.nodes import zenoh_settings
    from armfusion.fusion.service.zenoh_config import DEPLOY_CONFIG_DIR, endpoints_line, load_config

    chair = DEPLOY_CONFIG_DIR / "chair.json5"
    kept = zenoh_settings(chair, None, None, "router")
    line = endpoints_line(load_config(kept), kept)
    assert line == (f"zenoh router: listening on tcp/127.0.0.1:7447 ({chair}); "
                    f"connecting to tls/127.0.0.1:7448 ({chair})")
    # --connect alone replaces the connect endpoints only; --listen the listen ones
    moved = zenoh_settings(chair, None, ["tls/127.0.0.1:9001"], "router")
    assert endpoints_line(load_config(moved), moved) == (
        f"zenoh router: listening on tcp/127.0.0.1:7447 ({chair}); "
        "connecting to tls/127.0.0.1:9001 (the command line)")
    moved = zenoh_settings(chair, ["tcp/127.0.0.1:9002"], None, None)
    assert endpoints_line(load_config(moved), moved).startswith(
        "zenoh router: listening on tcp/127.0.0.1:9002 (the command line); connecting to tls/127.0.0.1:7448")
    # without a file, --connect alone listens on an ephemeral port (not the default file's 7447)
    assert zenoh_settings(None, None, ["tcp/127.0.0.1:9003"], None).listen == ["tcp/127.0.0.1:0"]
    assert zenoh_settings(None, None, ["tcp/127.0.0.1:9003"], "client").listen == []


def test_deploy_adds_a_chair_to_the_base_policy_and_touches_no_other_chair(tmp_path):
    import zenoh
    from armfusion.fusion.service.zenoh_config import ZenohSettings, load_config

    fleet = tmp_path / "fleet"
    assert _run("deploy", "chair1", "--fleet", str(fleet), "--local").exit_code == 0
    before = {p: p.read_bytes() for p in (fleet / "chair1").rglob("*") if p.is_file()}
    ca = (fleet / "ca/ca.pem").read_bytes()
    r = _run("deploy", "chair3", "--fleet", str(fleet), "--local", "--chair-port", "7450")
    assert r.exit_code == 0, r.stderr
    assert "admits chair1, chair3" in r.stdout
    assert {p: p.read_bytes() for p in (fleet / "chair1").rglob("*") if p.is_file()} == before
    assert (fleet / "ca/ca.pem").read_bytes() == ca  # the same CA signs every chair
    base_router = zenoh.Config.from_file(str(fleet / "base/zenoh/router.json5"))
    acl = json.loads(base_router.get_json("access_control"))
    assert {s["id"]: s.get("cert_common_names") for s in acl["subjects"]} == {
        "base station": ["base"], "chair1": ["chair1"], "chair3": ["chair3"]}
    own = {r["id"]: r["key_exprs"] for r in acl["rules"] if r["id"].endswith("sends its own")}
    assert own == {"chair1 sends its own": ["armfusion/chair1/**"],
                   "chair3 sends its own": ["armfusion/chair3/**"]}
    chair3 = (fleet / "chair3/zenoh/router.json5").read_text()
    assert "chair1" not in chair3 and '"armfusion/chair3/raw/**"' in chair3
    assert f'"{fleet.resolve()}/chair3/tls/chair3.pem"' in chair3
    for f in ("base/zenoh/router.json5", "base/zenoh/base.json5", "chair3/zenoh/router.json5",
              "chair3/zenoh/serve.json5"):
        load_config(ZenohSettings(fleet / f))  # loopback, loadable
    # without --local the configs name /etc/armfusion; bad names and addresses are refused
    assert _run("deploy", "chair4", "--fleet", str(fleet)).exit_code == 0
    assert '"/etc/armfusion/tls/chair4.key"' in (fleet / "chair4/zenoh/router.json5").read_text()
    for args, says in ((["base"], "take these names"), (["chair 5"], "use 1 to 64 letters"),
                       (["chair5", "chair5"], "named twice"),
                       (["chair5", "--base-address", "base.local"], "literal IP address"),
                       (["chair5", "--base-port", "7449"], "made for tls/127.0.0.1:7448"),
                       (["chair5", "--base-address", "127.0.0.2"], "made for tls/127.0.0.1:7448")):
        r = _run("deploy", *args, "--fleet", str(fleet))
        assert r.exit_code == 2 and says in r.stderr, r.stderr
    assert not (fleet / "chair5").exists()
    # a chair retired: its folder removed, deploy with no chair drops it from the base policy
    import shutil

    shutil.rmtree(fleet / "chair1")
    r = _run("deploy", "--fleet", str(fleet), "--local", "--json")
    assert r.exit_code == 0, r.stderr
    assert json.loads(r.stdout)["base_router_admits"] == ["chair3", "chair4"]
    assert "chair1" not in (fleet / "base/zenoh/router.json5").read_text().split("access_control")[1]


def test_a_publisher_whose_batches_the_fusion_node_refuses_is_told_why(tmp_path, fusion_node, hub_settings,
                                                                        startup_recording):
    from armfusion.fusion.configfile import load_arm
    from armfusion.sensors.recording import read_recording, write_recording
    from armfusion.sensors.samples import Recording, Stream

    listener, connector = hub_settings
    acc = read_recording(startup_recording).get("acc1")
    bogus = tmp_path / "acc9.mcap"  # a sensor the WMRA does not have: every batch refused
    write_recording(Recording({"acc9": Stream("acc9", acc.kind, acc.t_s, acc.values, acc.channels)}), bogus)
    with fusion_node(listener, load_arm("wmra")):
        r = _run("replay", str(bogus), "--speed", "max", "--connect", connector.connect[0],
                 "--admitted-within", "2", "--json")
    assert r.exit_code == 1, r.stderr
    sent = json.loads(r.stdout)
    assert sent["admission"]["dropped"] == {"unknown_sensor": sent["batches"]}
    assert f"it dropped batches meanwhile: unknown_sensor {sent['batches']}" in r.stderr


def test_drivers_whose_user_the_chair_forbids_to_publish_stop_and_say_so(tmp_path, fusion_node):
    """On chair1's router as deployed, the drivers run with the monitor's credentials: the
    router takes the fusion node's subscription to them, and drops their raw samples."""
    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session

    fleet, port = tmp_path / "fleet", free_port()
    r = _run("deploy", "chair1", "--fleet", str(fleet), "--local", "--chair-port", str(port))
    assert r.exit_code == 0, r.stderr
    z1 = fleet / "chair1/zenoh"
    with open_session(ZenohSettings(z1 / "router.json5", connect=[])), \
            fusion_node(ZenohSettings(z1 / "serve.json5"), load_arm("wmra")) as (node, _):
        r = _run("drivers", "--fake", "--duration", "3", "--robot", "chair1", "--zenoh-config",
                 str(z1 / "monitor.json5"), "--wait", "10", "--admitted-within", "2", "--json")
        assert node.report_samples() == 0
    assert r.exit_code == 1, r.stderr
    assert "admitted none of the samples" in r.stderr and "none reached it" in r.stderr
    published = json.loads(r.stdout)["published"]
    assert sum(published["samples"].values()) > 0 and published["admission"]["state"] == "refused"


def test_a_retired_chair_reaches_the_base_router_and_is_heard_no_more(tmp_path):
    """chair2's folder removed from the fleet and deploy run with no chair: its certificate
    still passes the TLS handshake, and the base router's policy drops what it sends."""
    import shutil
    import threading
    import time

    from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session
    from service_helpers import wait_for

    fleet, base_port = tmp_path / "fleet", free_port()
    ports = {c: free_port() for c in CHAIRS}
    for c in CHAIRS:
        assert _run("deploy", c, "--fleet", str(fleet), "--local", "--base-port", str(base_port),
                    "--chair-port", str(ports[c])).exit_code == 0
    retired = tmp_path / "chair2-retired"  # (as it is still on chair2)
    shutil.move(fleet / "chair2", retired)
    for f in retired.glob("zenoh/*.json5"):
        f.write_text(f.read_text().replace(str((fleet / "chair2").resolve()), str(retired.resolve())))
    assert json.loads(_run("deploy", "--fleet", str(fleet), "--local", "--json").stdout)[
        "base_router_admits"] == ["chair1"]

    heard: list[str] = []
    lock = threading.Lock()

    def hear(sample) -> None:
        with lock:
            heard.append(str(sample.key_expr))

    z = {"chair1": fleet / "chair1/zenoh", "chair2": retired / "zenoh"}
    with open_session(ZenohSettings(fleet / "base/zenoh/router.json5")) as base_router, \
            open_session(ZenohSettings(fleet / "base/zenoh/base.json5")) as station, \
            open_session(ZenohSettings(z["chair1"] / "router.json5")), \
            open_session(ZenohSettings(z["chair2"] / "router.json5")) as chair2_router, \
            open_session(ZenohSettings(z["chair1"] / "serve.json5")) as chair1, \
            open_session(ZenohSettings(z["chair2"] / "serve.json5")) as chair2:
        station.declare_subscriber("armfusion/**", hear)
        pubs = {c: s.declare_publisher(f"armfusion/{c}/status") for c, s in (("chair1", chair1),
                                                                                ("chair2", chair2))}
        assert wait_for(lambda: pubs["chair1"].matching_status.matching, 20.0)
        for _ in range(20):
            for p in pubs.values():
                p.put("status")
            time.sleep(0.01)
        assert wait_for(lambda: heard.count("armfusion/chair1/status") == 20, 10.0)
        time.sleep(0.5)  # anything denied would have arrived by now
        with lock:
            assert "armfusion/chair2/status" not in heard
        # the retired chair's link is up: its router reached the base router over TLS
        assert str(base_router.zid()) in {str(r) for r in chair2_router.info.routers_zid()}


def test_a_client_refuses_a_base_router_whose_certificate_names_another_address(tmp_path):
    """A base router whose certificate names 127.0.0.2 (--base-address), listening on
    127.0.0.1: a base-station node connecting to 127.0.0.1 refuses it (verify_name_on_connect);
    the same router with a certificate that names 127.0.0.1 (the default) is reached. Nothing
    listens on or connects to any address but 127.0.0.1."""
    import zenoh
    from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session

    port = free_port()
    here = [f"tls/127.0.0.1:{port}"]
    for name, address, reached in (("named-elsewhere", "127.0.0.2", False),
                                   ("named-here", "127.0.0.1", True)):
        fleet = tmp_path / name
        r = _run("deploy", "chair1", "--fleet", str(fleet), "--local", "--base-address", address,
                 "--base-port", str(port))
        assert r.exit_code == 0, r.stderr
        base = fleet / "base/zenoh"
        with open_session(ZenohSettings(base / "router.json5", listen=here)):
            client = ZenohSettings(base / "base.json5", connect=here)
            if reached:
                with open_session(client) as s:
                    assert len(list(s.info.routers_zid())) == 1
            else:
                with pytest.raises(zenoh.ZError), open_session(client):
                    pass
