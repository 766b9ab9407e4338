"""Joints the startup cannot choose a branch for, in the running service: with no
saved pose the fusion node does not track them as known (flag `ambiguous`, the status names
the candidates and the move that would tell them apart); after the controller makes that
move and the arm is still again, the node solves again with the candidates carried through
the encoder counts and tracks the true branch."""

from __future__ import annotations

import dataclasses

import numpy as np
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service.replay import ReplayPacing, replay
from armfusion.fusion.service.zenoh_config import open_session
from armfusion.fusion.startup.solve import move_delta_rad, readings_from_recording, solve_still
from armfusion.fusion.startup.static import StaticDetectionSettings, find_static_segments
from armfusion.models.rotations import DEG
from armfusion.models.simulator import simulate
from armfusion.models.trajectories import ParkedBase, Scenario, StepsBuilder, WaypointPath, warm_up
from service_helpers import Collected, cut, wait_for

# the still pose at t = 45.4 s of `simulate --config wmra --scenario static-poses --seed 11`:
# the twins of the j3-j4 pair both lie inside the limits and read the same
POSE_DEG = [7.129, 37.724, 89.371, -109.451, -20.84, -54.735, -76.267]


def _scenario(arm, pose, delta, base):
    b = StepsBuilder(pose).hold(4.0)
    if delta is not None:
        b.move(pose + delta, 2.0).hold(5.0)
    return Scenario("ambiguous-then-move", arm, b.t, WaypointPath(b.build()), base, warm_up())


def test_ambiguous_joints_are_not_tracked_as_known_until_the_proposed_move_resolves_them(
        hub_settings, fusion_node):
    arm = load_arm("wmra")
    arm = dataclasses.replace(arm, calibration=arm.calibration.with_accel_floor(0.0))
    pose = np.radians(POSE_DEG)
    base = ParkedBase(0.6 * DEG, -0.9 * DEG, 0.3)
    # what the startup will say on the still pose, and the move it proposes
    first, _ = simulate(arm, _scenario(arm, pose, None, base), seed=4)
    seg = find_static_segments(first, StaticDetectionSettings(window_s=1.0))[0]
    res = solve_still(arm, readings_from_recording(arm, first, seg.t_start_s, seg.t_end_s)[0])
    amb = {j.name for j in res.joints if j.flag == "ambiguous"}
    assert {"j3", "j4"} <= amb and res.disambiguating_move is not None
    delta = move_delta_rad(res.disambiguating_move, arm)
    rec, truth = simulate(arm, _scenario(arm, pose, delta, base), seed=4)
    true_q = rec.truth()["true_q"]

    listener, connector = hub_settings
    with fusion_node(listener, arm, publish_hz=50.0) as (node, result), open_session(connector) as s:
        got = Collected(s)
        replay(s, cut(rec, 0.0, 5.0), "chair1", ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
        assert wait_for(lambda: node.tracker is not None and got.snapshot()[0], 20.0)
        # still at the pose: tracked, but j3 and j4 are not known
        assert set(node.tracker.ambiguity()) >= {"j3", "j4"}
        js = got.snapshot()[0][-1]
        flags = dict(zip(js.joint_names, js.flags, strict=True))
        assert flags["j3"] == "ambiguous" and flags["j4"] == "ambiguous"
        # (the status follows the first joint state within its 0.1 s pacing)
        assert wait_for(lambda: any("ambiguous" in st.message and "to tell them apart: move" in st.message
                                    for st in got.snapshot()[1]), 5.0)
        # the controller makes the proposed move; the arm is still again
        replay(s, cut(rec, 5.0, rec.t_end_s + 1.0), "chair1",
               ReplayPacing(speed=None, wait_for_subscribers_s=5.0))
        assert wait_for(lambda: node.tracker is not None and not node.tracker.ambiguity(), 30.0)
        assert wait_for(lambda: got.snapshot()[0][-1].t_s > rec.t_end_s - 0.5, 20.0)
    last = got.snapshot()[0][-1]
    assert "ambiguous" not in last.flags
    q_true = np.array([np.interp(last.t_s, true_q.t_s, true_q.values[:, j]) for j in range(arm.n_joints)])
    for j in (2, 3):  # j3, j4: the true branch, within their sigma
        err = abs((last.q_rad[j] - q_true[j] + np.pi) % (2 * np.pi) - np.pi)
        assert err < 4 * last.sigma_rad[j], (arm.joint_names[j], np.degrees(err),
                                             np.degrees(last.sigma_rad[j]))
    assert any("told apart" in st.message for st in got.snapshot()[1])
