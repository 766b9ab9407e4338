"""The calibrate queryable over Zenoh on 127.0.0.1: ``armfusion/<robot>/calibrate`` re-runs
the startup calibration on a still arm and replies with the result; it refuses, saying why,
before any sample and while the arm moves. Also through ``armfusion recalibrate``."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.fusion.service.requests import NoReplyError, request_calibration
from armfusion.fusion.service.zenoh_config import open_session
from armfusion.fusion.tracking.tracker import TrackerSettings
from service_helpers import Collected, cut, wait_for


def _replay_all(session, node, rec) -> None:
    before = node.report_samples()
    report = replay(session, rec, "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
    total = sum(report.samples.values())
    assert wait_for(lambda: node.report_samples() >= before + total, 30.0)


def test_calibrate_on_request_replies_with_the_result_and_refuses_while_the_arm_moves(
        hub_settings, fusion_node, renk_recording):
    arm = load_arm("wmra")
    listener, connector = hub_settings
    port = listener.listen[0].rsplit(":", 1)[1]
    with fusion_node(listener, arm, publish_hz=100.0) as (node, result), open_session(connector) as s:
        got = Collected(s)
        first = request_calibration(s, "chair1")
        assert not first.ok and first.message == "no samples received yet"

        # still until 5 s: the startup calibration runs there; then a request re-runs it on
        # the latest still stretch, and the tracker goes on from it
        _replay_all(s, node, cut(renk_recording, 0.0, 4.0))
        assert wait_for(lambda: node.tracker is not None, 5.0)
        reply = request_calibration(s, "chair1")
        assert reply.ok, reply.message
        # the stretch's last settle_s go to the tracker (TrackerSettings.settle_s)
        settle = TrackerSettings().settle_s
        assert reply.t_end_s == pytest.approx(4.0 - settle, abs=0.1)
        assert reply.t_end_s - reply.t_start_s >= 1.0
        assert reply.joint_names == arm.joint_names
        truth = renk_recording.truth()["true_q"].between(0.0, 4.0).values[-1]
        read = np.array([q is not None for q in reply.q_rad])
        # the renk pose has joint axes along gravity, and with no saved pose the branches of
        # the pairs behind them cannot be told apart: flagged, no angle (JSON null)
        assert {f for f, r in zip(reply.flags, read, strict=True) if not r} <= {"gimbal_lock", "ambiguous"}
        assert read.sum() >= 3
        err_deg = np.degrees(np.abs(np.array([q for q in reply.q_rad if q is not None]) - truth[read]))
        sig_deg = np.degrees(np.array([x for x in reply.sigma_rad if x is not None]))
        assert np.all(err_deg < np.maximum(4.0 * sig_deg, 0.2)), (err_deg, sig_deg)
        _replay_all(s, node, cut(renk_recording, 4.0, 4.5))
        assert wait_for(lambda: got.snapshot()[0] and got.snapshot()[0][-1].t_s > 4.4, 5.0)
        assert wait_for(lambda: any(dict(st.counters).get("calibrations") == 1 for st in got.snapshot()[1]),
                        5.0)

        # the sweep begins at 5.1 s: by 7 s the arm moves, and a request is refused
        _replay_all(s, node, cut(renk_recording, 4.5, 7.0))
        moving = request_calibration(s, "chair1")
        assert not moving.ok and moving.message.startswith("the arm moves: it was last still"), moving.message
        assert moving.q_rad == () and moving.flags == ()

        # the command line says the same and exits 1
        out = subprocess.run([sys.executable, "-m", "armfusion.fusion.cli", "recalibrate", "--json",
                              "--connect", f"tcp/127.0.0.1:{port}"],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 1, out.stderr
        doc = json.loads(out.stdout)
        assert doc["type"] == "calibration" and doc["ok"] is False
        assert doc["message"].startswith("the arm moves")
    assert result["report"].calibrations == 1
    # the node keeps tracking through the refusal
    assert got.snapshot()[0][-1].t_s > 6.9


def test_a_request_to_a_robot_nobody_serves_says_so(hub_settings):
    _, connector = hub_settings
    with open_session(connector) as s, pytest.raises(NoReplyError, match="no fusion node answered"):
        request_calibration(s, "chair9", timeout_s=0.5)


def test_the_calibration_reply_is_a_versioned_payload():
    reply = pl.Calibration("chair1", True, "ok", 1.0, 2.5, ("j1", "j2"), (0.1, None), (0.001, None),
                           ("ok", "gimbal_lock"), 0.01, -0.02)
    data = pl.encode(reply)
    assert json.loads(data)["v"] == pl.VERSIONS["calibration"] == 1
    assert pl.decode(pl.calibrate_key("chair1"), data) == reply
    with pytest.raises(pl.PayloadError, match="expected 2 numbers or nulls"):
        pl.decode(pl.calibrate_key("chair1"), data.replace(b'"q_rad":[0.1,null]', b'"q_rad":[0.1]'))
