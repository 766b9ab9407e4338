"""What the startup does when the data cannot choose a branch: the still poses of
``armfusion simulate --config wmra --scenario static-poses --seed 11`` with ideal sensors,
where two windows have rival branches 170 deg apart that predict every accelerometer within
a fraction of a milligram. No prior: `ambiguous`, every candidate, a move that separates
them; after the move, the truth. A saved pose is checked: a fresh one chooses, a stale one
is ignored and said to be; ``--assume-parked`` behaves as the ready-pose prior always did."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from armfusion.fusion.startup.solve import (
    StartupPrior,
    StillReadings,
    move_delta_rad,
    prior_after_move,
    readings_from_recording,
    solve_still,
)
from armfusion.fusion.startup.static import StaticDetectionSettings, find_static_segments
from armfusion.models.kinematics import gravity_in_sensors
from armfusion.models.rotations import DEG, up_from_tilt, wrap_angle
from armfusion.models.simulator import angle_truth, simulate


@pytest.fixture(scope="module")
def ideal(wmra):
    return dataclasses.replace(wmra, calibration=wmra.calibration.with_accel_floor(0.0))


@pytest.fixture(scope="module")
def seed11(ideal):
    rec, truth = simulate(ideal, "static-poses", 120.0, seed=11)
    segs = find_static_segments(rec, StaticDetectionSettings(window_s=1.0))
    q_true = angle_truth(rec.get("true_q"), truth, ideal.joint_names)
    base = rec.get("true_base")
    out = {}
    for seg in segs:
        readings, _ = readings_from_recording(ideal, rec, seg.t_start_s, seg.t_end_s, 1.0)
        k = int(np.searchsorted(q_true.t_s, seg.t_end_s)) - 1
        out[round(seg.t_start_s, 1)] = (readings, q_true.values[k], base.values[k])
    return out


def still_after(arm, q, roll_pitch, like: StillReadings, rng):
    """Still readings at ``q`` with the noise of ``like`` (the window before the move)."""
    up = up_from_tilt(*roll_pitch)
    f = gravity_in_sensors(arm, q, up)[0]
    names = [s.name for s in arm.link_accelerometers]
    means = {nm: f[i] + rng.normal(0, like.accel_sigma_g[nm]) for i, nm in enumerate(names)}
    return StillReadings(means, like.accel_sigma_g, up + rng.normal(0, like.imu_sigma_g), like.imu_sigma_g)


@pytest.mark.parametrize("t0", [45.4, 77.3])
def test_rival_branches_are_ambiguous_and_the_proposed_move_resolves_them(ideal, seed11, rng, t0):
    readings, q_true, base = seed11[t0]
    res = solve_still(ideal, readings, propose_unlock=False)
    by = {j.name: j for j in res.joints}
    # j3 and j4: two branches fit; no number, both candidates, the truth among them
    for name in ("j3", "j4"):
        j = ideal.joint_names.index(name)
        assert by[name].flag == "ambiguous", res.summary
        assert by[name].angle_rad is None and by[name].sigma_rad is None
        assert len(by[name].alternatives_rad) >= 2
        assert min(abs(wrap_angle(a - q_true[j])) for a in by[name].alternatives_rad) < 0.2 * DEG
    assert res.prior_used == "none"
    # nothing reported as a number is wrong beyond 4 of its sigmas
    for j, je in enumerate(res.joints):
        if je.angle_rad is not None:
            assert abs(wrap_angle(je.angle_rad - q_true[j])) < 4 * je.sigma_rad, je
    move = res.disambiguating_move
    assert move is not None and {"j3", "j4"} <= set(move.resolves)
    assert "tell the branches apart" in res.summary
    delta = move_delta_rad(move, ideal)
    assert np.abs(delta).max() <= 45 * DEG
    # every candidate stays inside the limits: the arm is on one of them
    assert np.all(ideal.within_limits(res.candidates_rad + delta))
    # the controller makes the move; the encoders count it; the arm is still again
    q2 = q_true + delta
    res2 = solve_still(ideal, still_after(ideal, q2, base[:2], readings, rng),
                       prior=prior_after_move(res, move, ideal), propose_unlock=False)
    for name in ("j3", "j4"):
        j = ideal.joint_names.index(name)
        je = res2.joints[j]
        assert je.flag == "ok", res2.summary
        assert abs(wrap_angle(je.angle_rad - q2[j])) < 4 * je.sigma_rad
    assert "carried through the encoder counts fits" in res2.notes[0]


def test_a_fresh_saved_pose_chooses_and_a_stale_one_is_ignored(ideal, seed11):
    readings, q_true, _ = seed11[45.4]
    saved = StartupPrior.saved_pose(q_true + 1.5 * DEG, source="saved.json")
    fresh = solve_still(ideal, readings, prior=saved, propose_unlock=False)
    assert fresh.prior_used == "saved.json"
    for j, je in enumerate(fresh.joints):
        assert je.flag != "ambiguous"
        if je.angle_rad is not None:
            assert abs(wrap_angle(je.angle_rad - q_true[j])) < 4 * je.sigma_rad
    # the arm was moved by hand while the power was off: the pose of another window
    _, q_other, _ = seed11[100.3]
    stale = solve_still(ideal, readings, prior=StartupPrior.saved_pose(q_other, source="saved.json"),
                        propose_unlock=False)
    assert stale.prior_used == "none"
    assert any("saved.json does not fit the still data" in n and "ignored" in n for n in stale.notes)
    alone = solve_still(ideal, readings, propose_unlock=False)
    assert [j.flag for j in stale.joints] == [j.flag for j in alone.joints]


def test_assume_parked_on_a_parked_arm_behaves_as_the_ready_pose_prior_did(wmra, rng):
    q = np.radians([90, 90, 0, 90, 90, 60, 0])  # the ready (park) pose
    up = up_from_tilt(0.3 * DEG, -0.4 * DEG)
    f = gravity_in_sensors(wmra, q, up)[0]
    sig = np.array([0.75, 0.75, 1.1]) / 256 / 10
    names = [s.name for s in wmra.link_accelerometers]
    r = StillReadings({nm: f[i] + rng.normal(0, sig) for i, nm in enumerate(names)},
                      {nm: sig for nm in names}, up, np.full(3, 3e-4))
    res = solve_still(wmra, r, prior=StartupPrior.assume_parked(wmra))
    flags = {j.name: j.flag for j in res.joints}
    assert flags["j3"] == "gimbal_lock" and flags["j6"] == "gimbal_lock"
    assert all(flags[n] == "ok" for n in ("j1", "j2", "j4", "j5", "j7"))
    assert res.unlock_move is not None
    assert res.prior_used.startswith("the arm assumed parked")
    assert any("rests on an assumption" in n for n in res.notes)
    for j, je in enumerate(res.joints):
        if je.angle_rad is not None:
            assert abs(wrap_angle(je.angle_rad - q[j])) < 4 * je.sigma_rad


def test_no_joint_is_given_a_number_with_a_sigma_past_45_degrees(wmra):
    """``simulate --scenario startup --duration 10 --seed 1 --realistic`` then `calibrate
    joints` gave j3 a sigma of 53,033,008 deg."""
    rec, _ = simulate(wmra, "startup", 10.0, seed=1, realistic=True)
    seg = find_static_segments(rec, StaticDetectionSettings(window_s=1.0))[0]
    readings, _ = readings_from_recording(wmra, rec, seg.t_start_s, seg.t_end_s, 1.0)
    res = solve_still(wmra, readings, propose_unlock=False)
    for j, je in enumerate(res.joints):
        if je.sigma_rad is not None:
            assert je.sigma_rad <= 45 * DEG * 1.0001, je
        if je.angle_rad is None and je.flag != "ambiguous":
            assert je.range_rad == (wmra.min_rad[j], wmra.max_rad[j])


def test_a_pose_just_past_a_limit_by_its_zero_offset_keeps_its_branch(ideal):
    """Limits are in the joint's numbering, branches in its geometric angle; the two differ by
    the joint's zero offset (1 deg typical). A pose 0.2 deg inside j4's -170 deg limit whose
    zero is 1 deg off reads as j4 = -170.8 deg: that branch must stay feasible, so its rival
    (j3 and j4 160-190 deg away, reading the same) makes them ambiguous. With the noise's 0.5
    deg margin alone, the true branch was dropped and the rival's j3 and j4 reported ok."""
    rng = np.random.default_rng(1)
    q = np.radians([176.5, 111.0, -83.7, -170.8, -38.8, 83.5, 106.4])
    up = up_from_tilt(*np.radians([1.0, -2.0]))
    f = gravity_in_sensors(ideal, q, up)[0]
    names = [s.name for s in ideal.link_accelerometers]
    sig = np.full(3, 0.0005)
    r = StillReadings({nm: f[i] + rng.normal(0, 0.0005, 3) for i, nm in enumerate(names)},
                      {nm: sig for nm in names}, up + rng.normal(0, 0.0005, 3), sig)
    res = solve_still(ideal, r, propose_unlock=False)
    for j, je in enumerate(res.joints):
        if je.flag == "ok":
            err = abs(wrap_angle(je.angle_rad - q[j]))
            assert err <= 4 * je.sigma_rad, (je.name, np.degrees(je.angle_rad))
    assert [res.joints[j].flag for j in (2, 3)] == ["ambiguous", "ambiguous"], res.summary
    cands = np.atleast_2d(res.candidates_rad)
    assert np.min(np.abs(wrap_angle(cands[:, 3] - q[3]))) < 0.5 * DEG  # the true branch is a candidate
