"""The planned self-calibration maneuver (``armfusion plan-maneuver``): safe to play, better
than random poses on its own criterion, and its predicted σ those the fit then reports."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.calibrate_sensors import build_model
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.planner import (
    PlanSettings,
    maneuver_problems,
    move_durations_s,
    plan_maneuver,
    predicted_identification,
)
from armfusion.fusion.startup.moves import moves_within_limits
from armfusion.models.kinematics import chain_poses
from armfusion.models.trajectories.planned import PlannedManeuver, planned_scenario
from armfusion.models.trajectories.scenario import margin_limits

EFFECTS = "accel_bias,accel_scale,mount_rotation"
FAST = dict(candidates=48, pool_poses=120)


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


@pytest.fixture(scope="module")
def model(arm):
    return build_model(arm, EFFECTS)


@pytest.fixture(scope="module")
def plan(model):
    return plan_maneuver(model, PlanSettings(duration_s=30.0, **FAST))


def test_a_planned_maneuver_stays_inside_the_limits_and_moves_as_the_unlock_move_may(arm, plan):
    m = plan.maneuver
    assert m.duration_s == pytest.approx(30.0)
    assert len(m.poses_rad) >= 4
    assert np.all((m.poses_rad >= arm.min_rad) & (m.poses_rad <= arm.max_rad))
    # the unlock move's checks, move by move: inside the limits, at most 45 deg per joint
    assert moves_within_limits(arm, m.poses_rad[:-1], m.poses_rad[1:]).all()
    assert np.degrees(np.abs(np.diff(m.poses_rad, axis=0))).max() <= 45.0 + 1e-9
    # a person beside the arm: no joint peaks above 20 deg/s, no link origin above 0.25 m/s
    # (checked here on a fine grid of the played scenario, not by the planner's own formula)
    sc = planned_scenario(arm, m, np.random.default_rng(0))
    t = np.arange(0.0, m.duration_s, 0.01)
    q, qd, _ = sc.joints(t)
    assert np.degrees(np.abs(qd)).max() <= 20.0 * 1.001
    p = chain_poses(arm, q).p_0L_m
    v = np.linalg.norm(np.diff(p, axis=0), axis=-1).max() / 0.01
    assert v <= 0.25 * 1.01
    assert maneuver_problems(arm, m) == []
    # the first pose is the ready pose, held still for the startup's still second
    assert np.allclose(m.poses_rad[0], arm.ready_pose_rad) and m.dwell_s[0] >= 5.0


def test_the_plan_knows_more_than_random_safe_poses_of_the_same_timing(arm, model, plan):
    """Its own criterion (log det of the information, prior units, the gauges left out) beats
    the same schedule through random poses that pass the same checks."""
    from armfusion.fusion.identification.planner import _rows_per_pose, _static_problem

    st = PlanSettings(duration_s=30.0, **FAST)
    m = plan.maneuver
    rng = np.random.default_rng(3)
    lo, hi = margin_limits(arm)

    def logdet(poses):
        pb = _static_problem(model, poses, st, poses[0])
        cols = [i for i, n in enumerate(pb.names) if n not in set(plan.gauges)]
        J = _rows_per_pose(pb)[:, :, cols] * pb.sigma0[cols]
        w = m.dwell_s * st.rate_hz / st.window
        A = np.eye(len(cols)) + np.einsum("k,kri,krj->ij", w, J, J)
        return np.linalg.slogdet(A)[1]

    planned = logdet(m.poses_rad)
    random_ones = []
    for _ in range(5):
        poses = [m.poses_rad[0]]
        while len(poses) < len(m.poses_rad):
            c = np.clip(poses[-1] + rng.uniform(-1, 1, arm.n_joints) * np.radians(45.0), lo, hi)
            if moves_within_limits(arm, poses[-1], c[None])[0]:
                poses.append(c)
        random_ones.append(logdet(np.array(poses)))
    assert planned > max(random_ones) + 5.0, (planned, random_ones)


def test_a_maneuver_that_is_not_safe_is_refused_naming_the_pose_the_move_and_the_joint(arm, plan):
    m = plan.maneuver
    poses = m.poses_rad.copy()
    poses[2, 1] = np.radians(130.0)  # j2's limit is 120 deg
    moves = m.move_s.copy()
    moves[2] = 0.5  # the move 2 -> 3 in half a second
    bad = PlannedManeuver(m.joint_names, poses, m.dwell_s, moves)
    text = "\n".join(maneuver_problems(arm, bad))
    assert "pose 2: j2 at 130.0° is outside its limits [-15°, 120°]" in text
    assert "move 2 -> 3:" in text and "°/s, over 20°/s" in text
    far = poses.copy()
    far[1, 0] = far[0, 0] + np.radians(60.0)
    text = "\n".join(maneuver_problems(arm, PlannedManeuver(m.joint_names, far, m.dwell_s, m.move_s)))
    assert "move 0 -> 1: j1 moves 60.0°, more than the unlock move's 45°" in text


def test_the_maneuver_file_round_trips_and_a_malformed_one_is_refused_by_key(plan):
    m = plan.maneuver
    back = PlannedManeuver.from_dict(yaml.safe_load(yaml.safe_dump(m.as_dict())))
    assert np.allclose(back.poses_rad, m.poses_rad, atol=1e-5)
    assert np.all(back.move_s >= m.move_s - 1e-12)  # rounded up: never faster than planned
    assert back.duration_s == pytest.approx(m.duration_s, abs=0.01)
    d = m.as_dict()
    d["poses"][1]["pose_deg"][3] = "x" * 500
    with pytest.raises(ValueError,
                       match=r"M.yaml: poses\[1\]\.pose_deg: expected a finite number, got 'x{29}…$"):
        PlannedManeuver.from_dict(d, "M.yaml")
    d = m.as_dict()
    d["poses"][2]["move_s"] = 0
    with pytest.raises(ValueError, match=r"poses\[2\]\.move_s: a move takes a positive time"):
        PlannedManeuver.from_dict(d)
    with pytest.raises(ValueError, match="expected a mapping with 'joints'"):
        PlannedManeuver.from_dict([1, 2, 3])


def test_the_predicted_sigma_are_the_fitted_ones_within_30_percent(arm, model, plan):
    """A plan's prediction against the fit on a simulated recording of it (datasheet-typical
    accelerometer errors, joint zeros): each element both estimate, σ within 30 % (within 4x
    beside a held gauge); the estimates within 4σ of the truth."""
    from armfusion.fusion.identification.identify import compare_with_truth

    from tests.fusion.test_identify import _drawn_effects
    from tools.bench_calibrated import calibrate

    pred = predicted_identification(model, plan.maneuver)
    rng = np.random.default_rng(21)
    truth_entries = _drawn_effects(arm, rng, {s: tuple(EFFECTS.split(","))
                                              for s in ("acc1", "acc2", "acc3", "acc4")})
    sc = planned_scenario(arm, plan.maneuver, np.random.default_rng(4))
    res, truth, _ = calibrate(arm, 4, plan.maneuver.duration_s, true_effects=truth_entries,
                              fit_effects=EFFECTS, scenario=sc)
    both = ~pred.held & ~res.held
    assert both.sum() >= 40
    assert set(np.array(pred.names)[pred.held]) == set(np.array(res.names)[res.held])
    names = np.array(res.names)
    # an element of a block with a held element (acc4's mount about x and y beside the held
    # gauge about j7's axis) trades with it through the consider covariance, which depends on
    # where the fit lands (the held mount's truth is 1-2 deg off its prior): known only roughly
    gauged = np.array([n.split("[")[0] in {h.split("[")[0] for h in names[res.held]} for n in names])
    ratio = res.sigma / pred.sigma
    plain = both & ~gauged
    assert plain.sum() >= 40
    worst = np.argmax(np.where(plain, np.abs(np.log(ratio)), 0))
    assert np.all(np.abs(ratio[plain] - 1) <= 0.3), (names[worst], ratio[worst])
    assert np.all(np.abs(np.log(ratio[both & gauged])) <= np.log(4.0)), ratio[both & gauged]
    z = np.array([r["z"] for r in compare_with_truth(res, truth)])
    assert np.all(np.abs(z) < 4.0), z.round(1)


def test_plan_maneuver_writes_a_file_that_simulate_plays(tmp_path: Path, arm):
    from armfusion.fusion.cli.main import app
    from armfusion.fusion.cli.plan_maneuver import run_plan
    from typer.testing import CliRunner

    doc = run_plan("wmra", PlanSettings(duration_s=20.0, candidates=24), EFFECTS, startup_poses=8)
    assert [p["pose_deg"] for p in doc["poses"]][0] == pytest.approx(np.degrees(arm.ready_pose_rad).tolist())
    assert {"name", "sigma", "prior_sigma", "held"} <= set(doc["predicted"]["elements"][0])
    assert [s["joint"] for s in doc["predicted"]["startup"]] == list(arm.joint_names)
    m = tmp_path / "M.yaml"
    m.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    r = CliRunner().invoke(app, ["simulate", "--maneuver", str(m), "-o", str(tmp_path / "rec.csv"),
                                 "--no-noise", "--json"])
    assert r.exit_code == 0, r.output
    truth = yaml.safe_load((tmp_path / "rec.truth.json").read_text())
    assert truth["scenario"] == "planned"
    assert truth["duration_s"] == pytest.approx(doc["duration_s"], abs=0.01)
    # made unsafe by hand: refused before anything is written
    doc["poses"][1]["pose_deg"][1] = 130.0
    m.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    r = CliRunner().invoke(app, ["simulate", "--maneuver", str(m), "-o", str(tmp_path / "bad.csv")])
    assert r.exit_code == 2
    assert "not safe to play on WMRA-II: pose 1: j2 at 130.0° is outside its limits" in r.output
    assert not (tmp_path / "bad.csv").exists()
    r = CliRunner().invoke(app, ["simulate", "-o", str(tmp_path / "none.csv")])
    assert r.exit_code == 2 and "give one of --scenario NAME or --maneuver M.yaml" in r.output


def test_move_durations_keep_the_peak_rate(arm):
    st = PlanSettings()
    q0 = np.zeros(arm.n_joints)
    q1 = q0.copy()
    q1[3] = np.radians(40.0)
    T = move_durations_s(st, q0, q1[None])[0]
    assert 1.875 * 40.0 / T == pytest.approx(20.0)


def test_plan_maneuver_refuses_a_bad_option_before_planning(tmp_path: Path):
    from armfusion.fusion.cli.main import app
    from typer.testing import CliRunner

    r = CliRunner().invoke(app, ["plan-maneuver", "--criterion", "A-optimal" * 20])
    assert r.exit_code == 2
    assert "--criterion must be one of D, E, startup, not 'A-optimalA-optimalA-'" in r.output
    r = CliRunner().invoke(app, ["plan-maneuver", "--out", str(tmp_path / "M.csv")])
    assert r.exit_code == 2 and "unsupported suffix '.csv'; expected .yaml or .yml" in r.output
    r = CliRunner().invoke(app, ["plan-maneuver", "--duration", "3"])
    assert r.exit_code == 2
    assert "duration_s: 3 s leaves no time for a move after the 5 s still start" in r.output
    assert not list(tmp_path.iterdir())


def test_the_fit_reads_a_planned_moves_joint_accelerations_from_the_encoders_to_2_percent(arm):
    # a 25 deg move of every joint in 2.3 s (peak 0.46 rad/s^2, as the planner's moves), played
    # and read as the fit reads a recording: the joints' accelerations at the window nodes
    # against the scenario's exact ones. Differencing the nodes themselves (0.125 s apart,
    # twice) missed them by 7.5 % here (14 % on a 60 s plan's shorter moves), and the fit took
    # the missing tangential acceleration for lever-arm errors (acc4.motion_acceleration[z]
    # 7-10 sigma off on an error-free arm)
    from armfusion.fusion.identification.data import data_from_recording, encoder_motion
    from armfusion.models.simulator import SimulationOptions, simulate

    q0 = np.asarray(arm.ready_pose_rad, float)
    lo, hi = margin_limits(arm)
    q1 = np.clip(q0 + np.radians(25.0) * np.where(q0 + np.radians(25) < hi, 1, -1), lo, hi)
    m = PlannedManeuver(tuple(arm.joint_names), np.array([q0, q1]), np.array([2.0, 2.0]),
                        move_durations_s(PlanSettings(), q0, q1))
    sc = planned_scenario(arm, m, np.random.default_rng(0), 0.0)
    rec, _ = simulate(arm, sc, options=SimulationOptions(noise=False))
    data = data_from_recording(arm, rec, 25, nodes=2)
    exact = sc.state(data.state.t_s)
    peak = np.abs(exact.qdd_rad_s2).max()
    assert peak > 0.3
    err = np.abs(data.state.qdd_rad_s2 - exact.qdd_rad_s2).max(axis=0)
    assert err.max() < 0.02 * peak, np.round(err / peak, 4)  # 0.7 % here
    assert np.abs(data.state.qd_rad_s - exact.qd_rad_s).max() < 1e-3 * np.abs(exact.qd_rad_s).max()
    # what the fit did before: np.gradient twice over the nodes
    tn = data.state.t_s
    qd_old = np.gradient(data.state.q_rad, tn, axis=0)
    assert np.abs(np.gradient(qd_old, tn, axis=0) - exact.qdd_rad_s2).max() > 0.05 * peak  # 7.5 % here
    # too few samples for a polynomial: angles, and zero rates rather than a failure
    q, qd, qdd = encoder_motion(np.array([0.0, 0.01]), np.array([[0.0], [1e-3]]), np.array([0.005]))
    assert q[0, 0] == pytest.approx(5e-4) and qd[0, 0] == 0.0 and qdd[0, 0] == 0.0


def test_a_startup_plan_keeps_the_checks_and_beats_random_poses_on_the_worst_joints_startup(arm, model):
    """``criterion="startup"``: the startup's σ per joint (linearised at random still poses,
    the joints a held gauge partners left out), the log of their variances' product. The plan keeps the
    unlock move's checks, holds each pose one of the dwells offered, and its worst joint's
    startup σ beats the same number of random safe poses held as long, and the D-optimal plan
    of the same settings."""
    from armfusion.fusion.identification.planner import (
        _rows_per_pose,
        _startup_rows,
        _startup_value,
        _static_problem,
    )

    st = PlanSettings(duration_s=30.0, criterion="startup", dwell_choices_s=(1.0, 2.0, 3.0), **FAST)
    plan = plan_maneuver(model, st)
    m = plan.maneuver
    assert not maneuver_problems(arm, m, st)
    assert m.duration_s == pytest.approx(30.0)
    assert set(np.round(m.dwell_s[1:-1], 6)) <= {1.0, 2.0, 3.0} and m.dwell_s[-1] >= 1.0
    # j7 cannot be answered: acc4's mount about its axis is a held gauge (the accelerometers'
    # effects only: no IMU mount here to hold j1 too)
    assert plan.startup_joints == ("j1", "j2", "j3", "j4", "j5", "j6")
    cols = np.array([i for i, n in enumerate(plan.names) if n not in set(plan.gauges)])
    G, noise, joint, _ = _startup_rows(model, st, m.poses_rad[0], cols, {"j7"},
                                       np.random.default_rng([st.seed, 0x57A]))

    def worst_deg(poses, dwell_s):
        pb = _static_problem(model, poses, st, poses[0])
        J = _rows_per_pose(pb)[:, :, cols] * pb.sigma0[cols]
        A = np.eye(len(cols)) + np.einsum("k,kri,krj->ij", dwell_s * st.rate_hz / st.window, J, J)
        v = noise + np.einsum("Rp,pq,Rq->R", G, np.linalg.inv(A), G)
        per = [np.sqrt(v[joint == j].mean()) for j in np.unique(joint)]
        assert _startup_value(v, joint, arm.n_joints) == pytest.approx(2 * np.sum(np.log(per)))
        return np.degrees(max(per))

    rng = np.random.default_rng(4)
    lo, hi = margin_limits(arm)
    planned, random_ones = worst_deg(m.poses_rad, m.dwell_s), []
    for _ in range(4):
        poses = [m.poses_rad[0]]
        while len(poses) < len(m.poses_rad):
            c = np.clip(poses[-1] + rng.uniform(-1, 1, arm.n_joints) * np.radians(45.0), lo, hi)
            if moves_within_limits(arm, poses[-1], c[None])[0]:
                poses.append(c)
        random_ones.append(worst_deg(np.array(poses), m.dwell_s))
    assert planned < 0.95 * min(random_ones), (planned, random_ones)  # 0.154 against 0.166-0.368
    d_plan = plan_maneuver(model, PlanSettings(**{**st.__dict__, "criterion": "D"})).maneuver
    assert planned < 0.9 * worst_deg(d_plan.poses_rad, d_plan.dwell_s), planned  # D: 0.20


def test_plan_settings_refuse_bad_dwell_choices_and_startup_poses():
    with pytest.raises(ValueError, match=r"dwell_choices_s: at most 8 dwells, each 0.5 to 60 s, "
                                         r"got \(0.1,\)$"):
        PlanSettings(dwell_choices_s=(0.1,)).check()
    with pytest.raises(ValueError, match="startup_poses must be in 1..256, not 0"):
        PlanSettings(startup_poses=0).check()
    with pytest.raises(ValueError, match="criterion must be one of D, E, startup, not 'A'"):
        PlanSettings(criterion="A").check()


def test_plan_maneuver_refuses_bad_dwells_by_option():
    from armfusion.fusion.cli.main import app
    from typer.testing import CliRunner

    r = CliRunner().invoke(app, ["plan-maneuver", "--dwells", "1,x" * 30])
    assert r.exit_code == 2
    assert "--dwells: expected seconds separated by commas, got '1,x1,x1,x1,x1,x1,x1,x1,x1,x1,x'" in r.output


def test_a_maneuver_file_that_is_not_one_is_refused_in_its_own_words(tmp_path: Path) -> None:
    # before: /dev/zero or a FIFO was "maneuver file not found" (it is there), and the loader's
    # refusals of the YAML itself were headed "1 problem in arm config"
    import os

    from armfusion.fusion.identification.planner import load_maneuver

    os.mkfifo(tmp_path / "m.yaml")
    (tmp_path / "twice.yaml").write_text("joints: [j1]\njoints: [j2]\n")
    for p, said in [(Path("/dev/zero"), "/dev/zero: (file): not a regular file (a device, a FIFO, a dir"),
                    (tmp_path / "m.yaml", "m.yaml: (file): not a regular file"),
                    (tmp_path / "twice.yaml", "twice.yaml: line 2: the key 'joints' is given twice")]:
        with pytest.raises(ValueError) as e:
            load_maneuver(p)
        assert str(e.value).startswith("maneuver file ") and said in str(e.value)
        assert "arm config" not in str(e.value)
    with pytest.raises(FileNotFoundError, match="maneuver file not found"):
        load_maneuver(tmp_path / "none.yaml")
