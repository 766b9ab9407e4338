"""The model-change alarm over Zenoh: a replayed recording whose acc4 board turns by 2 deg
raises one named alarm on ``armfusion/<robot>/health`` (and the status says so); the same
recording replayed without the turn raises none."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.lateness import Lateness
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.models.rotations import DEG
from service_helpers import Collected, cut, wait_for

from tools.bench_alarm import mount_turned

T_TURN_S = 45.0


@pytest.fixture(scope="module")
def arm(calibrated_wmra_arm):
    return calibrated_wmra_arm


@pytest.fixture(scope="module")
def daily(daily_use_110s):
    """The shared daily use's first 70 s."""
    return cut(daily_use_110s, 0.0, 70.0)


def _serve(fusion_node, hub_settings, arm, rec):
    """Replay ``rec`` as fast as it goes to a fusion node; the health payloads and the last
    status received once every sample was taken in."""
    listener, connector = hub_settings
    from armfusion.fusion.service.zenoh_config import open_session

    health, lock = [], threading.Lock()

    def on_health(sample) -> None:
        with lock:
            health.append(pl.decode(str(sample.key_expr), sample.payload.to_bytes()))

    # every instant fused one by one, however far behind the node falls: the replay goes as
    # fast as it can, and a node that falls behind folds its backlog by design (the lateness
    # policy, tested in test_service_load.py), which is not what the alarm's figures are about
    never_degraded = Lateness(degrade_after_s=3600.0)
    with fusion_node(listener, arm, lateness=never_degraded) as (node, _), open_session(connector) as s:
        s.declare_subscriber(pl.health_key("chair1"), on_health)
        got = Collected(s)
        report = replay(s, rec, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
        total = sum(report.samples.values())
        assert wait_for(lambda: node.report_samples() >= total, 120.0)
        assert wait_for(lambda: any(st.counters and dict(st.counters).get("samples", 0) >= total
                                    for st in got.snapshot()[1]), 10.0)
        status = [st for st in got.snapshot()[1] if dict(st.counters).get("samples", 0) >= total][-1]
    with lock:
        return list(health), status


def test_a_turned_board_raises_the_named_alarm_on_the_health_key(fusion_node, hub_settings, arm, daily):
    """The alarm is raised 4 s after the turn naming both effects it cannot yet tell apart (the
    arm holds its pose), and published again once the arm's motion has named the turn."""
    rec = mount_turned(daily, "acc4", T_TURN_S, np.array([0.6, -0.8, 0.0]) * 2.0 * DEG)
    health, status = _serve(fusion_node, hub_settings, arm, rec)
    assert [len(h.alarms) for h in health] == [1, 1], health
    first, last = health[0].alarms[0], health[-1].alarms[0]
    assert (first[0], set(first[7])) == ("acc4", {"mount_rotation", "bias_jump"})
    (sensor, effect, size, sigma, unit, since_s, raised_s, candidates) = last
    assert (sensor, effect, unit, candidates) == ("acc4", "mount_rotation", "deg", ("mount_rotation",))
    assert abs(since_s - T_TURN_S) <= 2.0 and T_TURN_S < raised_s <= T_TURN_S + 30.0
    assert raised_s == first[6] < health[-1].t_s
    assert abs(size - 2.0) < 3 * sigma and sigma < 1.0
    assert dict(status.counters)["model_alarms"] == 1
    assert "model changed: acc4 mount_rotation" in status.message


def test_a_clean_replay_raises_no_alarm(fusion_node, hub_settings, arm, daily):
    health, status = _serve(fusion_node, hub_settings, arm, cut(daily, 0.0, 60.0))
    assert health == []
    assert dict(status.counters).get("model_alarms", 0) == 0
    assert "model changed" not in status.message
    assert "the gate rejected" not in status.message and "implausible" not in status.message


def _health_bytes(**alarm) -> bytes:
    a = {"sensor": "acc4", "effect": "mount_rotation", "size": 1.5, "sigma": 0.8, "unit": "deg",
         "since_s": 45.0, "raised_s": 49.0, **alarm}
    return pl.encode(pl.Health("chair1", 49.0, ())).replace(b'"alarms":[]', b'"alarms":[' +
                                                               json.dumps(a).encode() + b"]")


def test_a_health_payload_round_trips():
    """Without ``candidates`` the effect is decided; with them, they come back in order."""
    h = pl.decode(pl.health_key("chair1"), _health_bytes())
    assert h.alarms == (("acc4", "mount_rotation", 1.5, 0.8, "deg", 45.0, 49.0, ("mount_rotation",)),)
    assert pl.decode(pl.health_key("chair1"), pl.encode(h)) == h
    h = pl.decode(pl.health_key("chair1"), _health_bytes(candidates=["mount_rotation", "bias_jump"]))
    assert h.alarms[0][7] == ("mount_rotation", "bias_jump")
    assert pl.decode(pl.health_key("chair1"), pl.encode(h)) == h


@pytest.mark.parametrize(("alarm", "message"), [
    ({"effect": "sagging"}, "alarm 0: effect 'sagging': expected one of mount_rotation"),
    ({"unit": "rad"}, "alarm 0: unit 'rad' for mount_rotation: expected 'deg'"),
    ({"sensor": "x" * 5000}, r"alarm 0: sensor 'x{20,60}'… \(5000 characters\): use 1 to 64"),
    ({"size": -1.0}, "alarm 0: a negative size or sigma"),
    ({"sigma": None}, "field 'sigma': NoneType is not the expected type"),
    ({"candidates": ["bias_jump"]}, r"alarm 0: candidates \['bias_jump'\]: the effect first, then others"),
    ({"candidates": ["mount_rotation", "mount_rotation"]}, "alarm 0: candidates .*each once"),
    ({"candidates": ["mount_rotation", "x" * 5000]},
     r"^alarm 0: candidates \['mount_rotation', 'x{5,40}… \(5022 characters\): the effect first"),
    ({"candidates": "mount_rotation"}, "field 'candidates': str is not the expected type"),
])
def test_a_bad_health_payload_is_refused_naming_what(alarm, message):
    with pytest.raises(pl.PayloadError, match=message):
        pl.decode(pl.health_key("chair1"), _health_bytes(**alarm))


def test_a_health_payload_with_too_many_alarms_is_refused():
    one = _health_bytes()
    many = one.replace(b'"alarms":[', b'"alarms":[' + b'{},' * 100)
    with pytest.raises(pl.PayloadError, match="field 'alarms': 101 alarms, at most 64"):
        pl.decode(pl.health_key("chair1"), many)
