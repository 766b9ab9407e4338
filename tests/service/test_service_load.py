"""Load, CI-sized: four link accelerometers and the IMU (accelerometer, gyro, magnetometer,
temperature) and the encoders, all at 200 Hz, about one sample per message as a driver sends them,
in real time through Zenoh on 127.0.0.1 to the fusion node: no sample is lost, and every
instant after the startup calibration gives a joint state but those the node folded while
it was behind (its lateness policy), each counted. (Latency is measured by tools/soak.py,
not asserted here.)"""

from __future__ import annotations

import numpy as np
import pytest
from service_helpers import Collected, wait_for

from fusion.configfile import load_arm
from fusion.service.replay import replay
from fusion.service.zenoh_config import open_session
from models.simulator import simulate


@pytest.fixture(scope="module")
def at_200_hz():
    rec, _ = simulate(load_arm("wmra"), "startup", 2.5, 200.0, seed=21)
    return rec


def test_five_sensors_at_200_hz_lose_no_sample(hub_settings, fusion_node, at_200_hz):
    rec = at_200_hz
    raw = rec.raw()
    assert {"acc1", "acc2", "acc3", "acc4", "imu_acc", "imu_gyro", "imu_mag"} <= set(raw)
    assert all(s.rate_hz == pytest.approx(200.0) for s in raw.values())
    listener, connector = hub_settings
    # the startup calibration after 1 s of samples (not 2): more of the short run is tracking
    with fusion_node(listener, load_arm("wmra"), publish_hz=1000.0, min_data_s=1.0) as (node, result), \
            open_session(connector) as s:
        got = Collected(s)
        report = replay(s, rec, "chair1", speed=1.0, batch_s=0.005, wait_for_subscribers_s=5.0)
        published = sum(report.samples.values())
        assert published == sum(len(x) for x in raw.values())
        assert report.batches > 0.85 * published  # nearly one sample per message
        assert wait_for(lambda: node.report_samples() >= published, 30.0)
        t_last = float(raw["enc"].t_s[-1])
        # the reorder stage holds the newest instants until every sensor has sent them
        assert wait_for(lambda: got.snapshot()[0] and got.snapshot()[0][-1].t_s >= t_last - 0.11, 10.0)
    r = result["report"]
    assert r.samples == published and r.dropped == {} and r.out_of_order == 0, r
    assert r.missed_batches == 0
    assert r.startup_t_s is not None, r.message
    joints = got.snapshot()[0]
    t = np.array([j.t_s for j in joints])
    enc_t = raw["enc"].t_s
    # a joint state for every instant after the startup (bar the last ones the reorder stage
    # still held at the stop) but the folded ones, none twice, none out of order
    expected = enc_t[(enc_t > r.startup_t_s + 1e-9) & (enc_t <= t[-1] + 1e-9)]
    assert np.all(np.diff(t) > 0) and np.isin(t, expected).all()
    assert len(expected) - len(t) <= r.folded_instants  # (the last ones folded may come after t[-1])
    # folded or not, a joint state for every fold period of sample time at least
    fold_s = node.lateness.fold_period_s
    assert t[0] - r.startup_t_s <= fold_s + 1e-9 and np.diff(t).max() <= fold_s + 1e-9
    assert r.estimates >= len(t)
