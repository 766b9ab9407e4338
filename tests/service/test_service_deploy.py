"""The deployment example (config/deploy/): chairs and a base station through a Zenoh router,
over mutual TLS, with an access-control policy that lets a chair publish only under its own
key. On loopback endpoints (tls/127.0.0.1), with a throwaway CA and certificates made by the
openssl command line at test time."""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh
from armfusion.fusion.service.zenoh_config import (
    DEPLOY_CONFIG_DIR,
    ZenohConfigError,
    ZenohSettings,
    endpoint_problem,
    load_config,
    open_session,
)
from service_helpers import free_port, wait_for


def _openssl(*args: str, cwd: Path) -> None:
    if shutil.which("openssl") is None:
        raise RuntimeError("the deployment test makes its certificates with the openssl command: install it")
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _certificates(d: Path, names: tuple[str, ...], ca: str = "ca") -> None:
    """A CA and, for each name, a key and a certificate it signed (CN = the name; valid for
    127.0.0.1, both as server and as client)."""
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")
    _openssl("req", "-x509", *ec, "-keyout", f"{ca}.key", "-out", f"{ca}.pem", "-days", "2",
             "-subj", f"/CN=armfusion test {ca}", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=d)
    for n in names:
        (d / f"{n}.ext").write_text("basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
                                    "extendedKeyUsage=serverAuth,clientAuth\n"
                                    f"subjectAltName=IP:127.0.0.1,DNS:{n}\n")
        _openssl("req", *ec, "-keyout", f"{n}.key", "-out", f"{n}.csr", "-subj", f"/CN={n}", cwd=d)
        _openssl("x509", "-req", "-in", f"{n}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
                 "-CAcreateserial", "-out", f"{n}.pem", "-days", "2", "-extfile", f"{n}.ext", cwd=d)


def _chair_acl() -> dict:
    config = load_config(ZenohSettings(DEPLOY_CONFIG_DIR / "chair.json5"))
    return json.loads(config.get_json("access_control"))


def _tls(d: Path, name: str, ca: str = "ca", listen: bool = False) -> dict:
    keys = {"root_ca_certificate": d / f"{ca}.pem", "connect_private_key": d / f"{name}.key",
            "connect_certificate": d / f"{name}.pem"}
    if listen:
        keys |= {"listen_private_key": d / f"{name}.key", "listen_certificate": d / f"{name}.pem"}
    return {f"transport/link/tls/{k}": str(v) for k, v in keys.items()}


PASSWORDS = {"drivers": "d-secret", "serve": "s-secret", "record": "r-secret", "monitor": "m-secret"}


def _users(d: Path) -> dict:
    """The chair router's user dictionary (one ``user:password`` line each), as ``extra``."""
    path = d / "chair.users"
    path.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    return {"transport/auth/usrpwd/dictionary_file": str(path)}


def _as(user: str, password: str | None = None) -> dict:
    """A chair node's credentials, as ``extra``."""
    return {"transport/auth/usrpwd/user": user,
            "transport/auth/usrpwd/password": PASSWORDS[user] if password is None else password}


def test_tls_loopback_endpoints_are_accepted_and_others_refused():
    assert endpoint_problem("tls/127.0.0.1:7448") is None
    assert endpoint_problem("tls/[::1]:7448") is None
    assert "not a loopback address" in endpoint_problem("tls/10.0.0.1:7447")
    with pytest.raises(ZenohConfigError, match=r"tls/192\.168\.1\.5:7447.*not a loopback address"):
        load_config(ZenohSettings(DEPLOY_CONFIG_DIR / "base.json5", connect=["tls/192.168.1.5:7447"]))
    # the deployment files as shipped are loopback-only, with scouting off
    for name in ("router", "chair", "base"):
        load_config(ZenohSettings(DEPLOY_CONFIG_DIR / f"{name}.json5"))


def test_a_chair_publishes_only_under_its_own_key_through_the_base_router(tmp_path):
    _certificates(tmp_path, ("router", "chair1", "chair2", "base"))
    rogue_dir = tmp_path / "rogue"
    rogue_dir.mkdir()
    _certificates(rogue_dir, ("chair1",), ca="rogue")  # CN=chair1, but not from the fleet's CA
    base_ep = f"tls/127.0.0.1:{free_port()}"
    chair_eps = {c: f"tcp/127.0.0.1:{free_port()}" for c in ("chair1", "chair2")}

    def chair_router(c: str) -> ZenohSettings:
        # (chair.json5 is chair1's; chair2's is the same file with chair2 for chair1)
        extra = _tls(tmp_path, c) | _users(tmp_path)
        if c != "chair1":
            extra["access_control"] = json.loads(json.dumps(_chair_acl()).replace("chair1", c))
        return ZenohSettings(DEPLOY_CONFIG_DIR / "chair.json5", listen=[chair_eps[c]], connect=[base_ep],
                             extra=extra)

    def chair_node(c: str) -> ZenohSettings:  # a node on the chair (serve here), plain peer
        return ZenohSettings(listen=["tcp/127.0.0.1:0"], connect=[chair_eps[c]], extra=_as("serve"))

    router = ZenohSettings(DEPLOY_CONFIG_DIR / "router.json5", listen=[base_ep],
                           extra=_tls(tmp_path, "router", listen=True))
    base = ZenohSettings(DEPLOY_CONFIG_DIR / "base.json5", connect=[base_ep], extra=_tls(tmp_path, "base"))
    heard: list[tuple[str, str]] = []
    lock = threading.Lock()

    def hear(sample: zenoh.Sample) -> None:
        with lock:
            heard.append((str(sample.key_expr), sample.payload.to_string()))

    def heard_from(text: str) -> list[str]:
        with lock:
            return [k for k, p in heard if p.startswith(text)]

    with open_session(router), open_session(chair_router("chair1")), open_session(chair_router("chair2")), \
            open_session(base) as station, open_session(chair_node("chair1")) as chair1, \
            open_session(chair_node("chair2")) as chair2:
        station.declare_subscriber("armfusion/**", hear)
        snooped: list[str] = []
        chair2.declare_subscriber("armfusion/chair1/**", lambda s: snooped.append(str(s.key_expr)))
        chair1.declare_queryable("armfusion/chair1/calibrate",
                                 lambda q: q.reply("armfusion/chair1/calibrate", "calibrated"))
        own = chair1.declare_publisher("armfusion/chair1/status")
        other = chair1.declare_publisher("armfusion/chair2/status")
        chair2_own = chair2.declare_publisher("armfusion/chair2/status")
        assert wait_for(lambda: own.matching_status.matching and chair2_own.matching_status.matching, 20.0)
        for i in range(20):
            own.put(f"chair1 own {i}")
            other.put(f"chair1 posing as chair2 {i}")
            chair1.put("elsewhere/chair1", f"chair1 elsewhere {i}")
            chair2_own.put(f"chair2 own {i}")
            time.sleep(0.01)
        assert wait_for(lambda: len(heard_from("chair1 own")) == len(heard_from("chair2 own")) == 20, 10.0)
        # the base station asks chair1 to recalibrate: the query goes through, the reply comes back
        replies = [r.ok.payload.to_string() for r in station.get("armfusion/chair1/calibrate", timeout=5.0)
                   if r.ok is not None]
        time.sleep(0.5)  # anything denied would have arrived by now
        assert replies == ["calibrated"]
        assert set(heard_from("chair1 own")) == {"armfusion/chair1/status"}
        assert set(heard_from("chair2 own")) == {"armfusion/chair2/status"}
        # chair1 cannot speak for chair2, nor outside armfusion/; chair2 cannot read chair1
        assert heard_from("chair1 posing") == [] and heard_from("chair1 elsewhere") == []
        assert snooped == []

        # a certificate the fleet's CA did not sign (whatever its name) is refused at the link
        rogue = ZenohSettings(DEPLOY_CONFIG_DIR / "base.json5", connect=[base_ep],
                              extra={**_tls(rogue_dir, "chair1", ca="rogue"),
                                     "transport/link/tls/root_ca_certificate": str(tmp_path / "ca.pem"),
                                     "connect/timeout_ms": 2000})
        with pytest.raises(zenoh.ZError), open_session(rogue):
            pass


def test_only_the_drivers_may_publish_raw_samples_on_a_chair_and_the_node_checks_what_they_send(
        tmp_path, fusion_node, renk_recording):
    """Both layers on chair1's router (config/deploy/chair.json5, its access-control policy
    as shipped, its users from a dictionary made here): the router drops a raw sample put by
    any chair node but the drivers, and refuses a node without the password; what the
    drivers (allowed) send is still checked by the fusion node, which refuses a hostile
    batch and counts it."""
    import numpy as np
    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.service import payloads as pl
    from armfusion.fusion.service.replay import ReplayPacing, replay
    from armfusion.sensors.samples import Stream

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = ZenohSettings(DEPLOY_CONFIG_DIR / "chair.json5", listen=[endpoint], connect=[],
                           extra=_users(tmp_path))

    def node(user: str, password: str | None = None) -> ZenohSettings:
        return ZenohSettings(mode="client", listen=[], connect=[endpoint],
                             extra=_as(user, password) | {"connect/timeout_ms": 2000})

    heard: list[str] = []
    arm = load_arm("wmra")
    with open_session(router), open_session(node("record")) as recorder:
        recorder.declare_subscriber("armfusion/chair1/raw/*", lambda s: heard.append(s.payload.to_string()))
        sessions = {u: open_session(node(u)) for u in ("drivers", "serve", "monitor")}
        try:
            pubs = {u: cm.__enter__().declare_publisher("armfusion/chair1/raw/acc1")
                    for u, cm in sessions.items()}
            # every publisher sees the recorder's subscription (interest flows to all)...
            assert wait_for(lambda: all(p.matching_status.matching for p in pubs.values()), 10.0)
            for i in range(10):
                for u, p in pubs.items():
                    p.put(f"{u} {i}")
            assert wait_for(lambda: len(heard) >= 10, 5.0)
            time.sleep(0.5)  # anything denied would have arrived by now
            # ...but only the drivers' samples get through
            assert sorted(heard) == sorted(f"drivers {i}" for i in range(10))
        finally:
            for cm in sessions.values():
                cm.__exit__(None, None, None)
        # a node with a wrong password, or none, is refused at the link
        with pytest.raises(zenoh.ZError), open_session(node("drivers", "guess")):
            pass
        with pytest.raises(zenoh.ZError), open_session(ZenohSettings(
                mode="client", listen=[], connect=[endpoint], extra={"connect/timeout_ms": 2000})):
            pass

        # the second layer: the drivers are allowed, and a batch of theirs is still checked
        with fusion_node(node("serve"), arm, publish_hz=100.0) as (fnode, result), \
                open_session(node("drivers")) as drivers:
            rec = renk_recording
            part = type(rec)({k: s.between(0.0, 3.0) for k, s in rec.streams.items()})
            sent = replay(drivers, part, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=10.0))
            total = sum(sent.samples.values())
            assert wait_for(lambda: fnode.report_samples() >= total, 30.0)
            enc = part.get("enc")
            bogus = Stream("enc", "encoder", np.array([float(enc.t_s[-1]) + 0.001]),
                           np.full((1, 7), 2**63 - 1), enc.channels)
            drivers.put(pl.raw_key("chair1", "enc"), pl.encode(pl.RawBatch("chair1", bogus, 10**6)))
            assert wait_for(lambda: fnode.refused().get("out_of_range") == 1, 10.0)
        r = result["report"]
    assert r.samples == total and r.dropped == {"out_of_range": 1}
    assert r.startup_t_s is not None and r.errors == 0
