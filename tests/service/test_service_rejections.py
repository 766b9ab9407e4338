"""A sensor the tracker keeps rejecting is named on the status key, with why: a replay whose
acc1 reads 10 % high (a scale the calibrated config does not know) says so (the clean
replay of tests/service/test_service_health.py says nothing of the kind)."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.service.replay import ReplayPacing, replay
from service_helpers import Collected, cut, wait_for

from tools.bench_alarm import with_stream


@pytest.fixture(scope="module")
def daily(daily_use_110s):
    return cut(daily_use_110s, 0.0, 25.0)


def _last_status(fusion_node, hub_settings, arm, rec):
    listener, connector = hub_settings
    from armfusion.fusion.service.zenoh_config import open_session

    with fusion_node(listener, arm) as (node, _), open_session(connector) as s:
        got = Collected(s)
        report = replay(s, rec, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
        total = sum(report.samples.values())
        assert wait_for(lambda: node.report_samples() >= total, 120.0)
        assert wait_for(lambda: any(st.counters and dict(st.counters).get("samples", 0) >= total
                                    for st in got.snapshot()[1]), 10.0)
        return [st for st in got.snapshot()[1] if dict(st.counters).get("samples", 0) >= total][-1]


def test_a_sensor_rejected_most_of_the_time_is_named_on_the_status(fusion_node, hub_settings,
                                                                   calibrated_wmra_arm, daily):
    s = daily.get("acc1")
    high = with_stream(daily, "acc1", np.round(s.values.astype(float) * 1.1).astype(s.values.dtype))
    status = _last_status(fusion_node, hub_settings, calibrated_wmra_arm, high)
    assert "acc1: the gate rejected" in status.message, status.message
    assert "as the config gives it" in status.message
