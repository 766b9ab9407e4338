"""The Zenoh config: loopback only, scouting off, overrides applied."""

from __future__ import annotations

import json

import pytest
from armfusion.fusion.service.zenoh_config import (
    ZenohConfigError,
    ZenohSettings,
    endpoint_problem,
    load_config,
)


def test_default_config_is_peer_on_loopback_without_scouting():
    c = load_config()
    assert json.loads(c.get_json("mode")) == "peer"
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    assert json.loads(c.get_json("scouting/gossip/enabled")) is False


def test_overrides_replace_the_file():
    c = load_config(ZenohSettings(listen=["tcp/127.0.0.1:0"], connect=["tcp/127.0.0.1:7447"],
                                  mode="client"))
    assert json.loads(c.get_json("mode")) == "client"
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(c.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]


@pytest.mark.parametrize("endpoint", ["tcp/192.168.1.10:7447", "tcp/0.0.0.0:7447", "tcp/[::]:7447",
                                      "tcp/localhost:7447", "udp/10.0.0.1:7447"])
def test_a_non_loopback_endpoint_is_refused(endpoint):
    with pytest.raises(ZenohConfigError, match="refused, not loopback"):
        load_config(ZenohSettings(connect=[endpoint]))
    with pytest.raises(ZenohConfigError, match="refused, not loopback"):
        load_config(ZenohSettings(listen=["tcp/127.0.0.1:0", endpoint]))


def test_non_loopback_endpoint_in_the_file_is_refused(tmp_path):
    f = tmp_path / "zenoh.json5"
    f.write_text('{mode: "peer", listen: {endpoints: ["tcp/0.0.0.0:7447"]}, '
                 'scouting: {multicast: {enabled: true}}}')
    with pytest.raises(ZenohConfigError, match=r"listen/endpoints: refused, not loopback: "
                                               r"'tcp/0.0.0.0:7447': 0.0.0.0 is not a loopback"):
        load_config(ZenohSettings(config_path=f))


def test_file_scouting_is_switched_off(tmp_path):
    f = tmp_path / "zenoh.json5"
    f.write_text('{mode: "peer", listen: {endpoints: ["tcp/127.0.0.1:0"]}, '
                 'scouting: {multicast: {enabled: true}, gossip: {enabled: true}}}')
    c = load_config(ZenohSettings(config_path=f))
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    assert json.loads(c.get_json("scouting/gossip/enabled")) is False


def test_a_peer_must_listen_somewhere():
    with pytest.raises(ZenohConfigError, match="would listen on every interface"):
        load_config(ZenohSettings(listen=[]))


def test_loopback_endpoints_pass():
    for e in ("tcp/127.0.0.1:7447", "tcp/127.0.0.2:1", "tcp/[::1]:7447", "udp/127.0.0.1:9#x=1"):
        assert endpoint_problem(e) is None, e
