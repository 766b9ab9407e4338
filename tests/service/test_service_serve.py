"""replay -> serve -> a consumer, over Zenoh on 127.0.0.1: the startup calibration on the
first still window, then joint states and headings that match the simulator's truth."""

from __future__ import annotations

import threading
import time

import numpy as np
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.node import BoundedReceiver
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.fusion.service.serve import FusionNode
from armfusion.fusion.service.zenoh_config import open_session
from armfusion.sensors.recording import read_recording


def test_serve_calibrates_then_tracks_and_publishes(hub_settings, startup_recording):
    rec = read_recording(startup_recording)
    listener, connector = hub_settings
    stop = threading.Event()
    result = {}
    with open_session(listener) as s_serve:
        node = FusionNode(s_serve, load_arm("wmra"), "chair1")
        th = threading.Thread(target=lambda: result.setdefault("r", node.run(stop)))
        th.start()
        try:
            assert node.ready.wait(5.0)
            with open_session(connector) as s:
                joints, heading = BoundedReceiver(), BoundedReceiver()
                s.declare_subscriber(pl.joints_key("chair1"), joints)
                s.declare_subscriber(pl.heading_key("chair1"), heading)
                report = replay(s, rec, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
                assert report.unmatched == ()
                deadline = time.monotonic() + 20.0
                while node.report_samples() < sum(report.samples.values()) and time.monotonic() < deadline:
                    time.sleep(0.05)
                time.sleep(0.3)
                got_j = [pl.decode(m.key, m.data) for m in iter(joints.get_nowait, None)]
                got_h = [pl.decode(m.key, m.data) for m in iter(heading.get_nowait, None)]
        finally:
            stop.set()
            th.join(20.0)
    r = result["r"]
    assert r.state == "stopping" and r.startup_t_s is not None, r.message
    assert r.dropped == {} and r.out_of_order == 0
    assert len(got_j) >= 20 and len(got_h) == len(got_j)
    truth = rec.truth()["true_q"]
    last = got_j[-1]
    k = int(np.searchsorted(truth.t_s, last.t_s)) - 1
    err_deg = np.degrees(np.abs(np.asarray(last.q_rad) - truth.values[k]))
    locked = np.array([f == "gimbal_lock" for f in last.flags])
    # the WMRA's startup pose has two joint axes along gravity: flagged, held at the prior
    assert locked.sum() == 2, last.flags
    # the others from ~2 s of still, noisy gravity then 2 s of tracking: well under a degree
    # (the ill-conditioned ones are the worst, about 0.3 deg)
    assert np.all(err_deg[~locked] < 0.5), (err_deg, last.flags)
    assert all(np.isfinite(h.heading_rad) for h in got_h)
    # the heading payload carries the base's tilt too, as the truth has it
    base = rec.truth()["true_base"]
    h = got_h[-1]
    kb = int(np.searchsorted(base.t_s, h.t_s)) - 1
    tilt_err_deg = np.degrees(np.abs(np.array([h.roll_rad, h.pitch_rad]) - base.values[kb, :2]))
    assert np.all(tilt_err_deg < 0.2), tilt_err_deg
    # its sigma no better than the config's 45 mg lasting floors on four links and the IMU
    # allow (45 mg / sqrt(5): 1.15°), and no wider than that
    floor = np.arcsin(0.045 / np.sqrt(5.0))
    for s in (h.roll_sigma_rad, h.pitch_sigma_rad):
        assert 0.99 * floor <= s < 1.5 * floor, (s, floor)
    assert h.heading_sigma_rad > 0
    assert last.axis_to_vertical_deg is not None and np.all(np.array(last.axis_to_vertical_deg)[locked] < 10)
