"""Gravity reads a revolute joint only modulo a turn: a joint whose limits hold its angle on
two turns (the UR5's ±360°) is reported with both, not silently on the middle one."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.startup.readings import StillReadings
from armfusion.fusion.startup.results import summary
from armfusion.fusion.startup.solve import solve_still, turn_branches
from armfusion.models.kinematics import gravity_in_sensors
from armfusion.models.rotations import DEG, up_from_tilt


def test_turn_branches_are_every_angle_inside_the_limits_a_turn_apart():
    np.testing.assert_allclose(np.degrees(turn_branches(172 * DEG, -360 * DEG, 360 * DEG)), [-188, 172])
    np.testing.assert_allclose(np.degrees(turn_branches(-10 * DEG, -360 * DEG, 360 * DEG)), [-10, 350])
    assert turn_branches(172 * DEG, -180 * DEG, 180 * DEG) == ()  # one turn alone fits
    # the WMRA's ±200°: 170° has a rival at -190°, 10° none
    assert len(turn_branches(170 * DEG, -200 * DEG, 200 * DEG)) == 2
    assert turn_branches(10 * DEG, -200 * DEG, 200 * DEG) == ()


def test_calibrate_joints_reports_both_turns_of_a_ur5_wrist():
    """The UR5 twin's wrist 1 stands at -188° (its ±360° limits hold that and +172°, which
    gravity reads alike): the startup lists both turns, the true one among them, and says
    so in its plain words."""
    arm = load_arm("ur5_two_imu")
    rng = np.random.default_rng(7)
    q = np.radians([20.0, -80.0, 70.0, -188.0, -90.0, 0.0])
    up = up_from_tilt(0.0, 0.0)
    f = gravity_in_sensors(arm, q, up)[0]
    names = [s.name for s in arm.link_accelerometers]
    sig = np.full(3, 0.002)
    r = StillReadings({nm: f[i] + rng.normal(0, 0.002, 3) for i, nm in enumerate(names)},
                      {nm: sig for nm in names}, None, None)
    res = solve_still(arm, r, propose_unlock=False)
    w = res.joints[arm.joint_names.index("wrist1")]
    assert w.angle_rad is not None and len(w.turns_rad) == 2
    assert abs(w.turns_rad[1] - w.turns_rad[0] - 2 * np.pi) < 1e-9
    assert min(abs(np.degrees(t) + 188.0) for t in w.turns_rad) < 3.0 * np.degrees(w.sigma_rad) + 0.5
    assert all(arm.min_rad[3] <= t <= arm.max_rad[3] for t in w.turns_rad)
    assert w.as_dict()["turns_rad"] == list(w.turns_rad)
    text = summary(res)
    assert "wrist1" in text and "turn" in text
    assert all(f"{np.degrees(t):.1f}" in text for t in w.turns_rad)
