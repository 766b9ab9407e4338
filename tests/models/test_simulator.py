"""The simulator: still poses read 1 g and match the kinematics, moving sensors match
finite differences of their positions, the truth replays, scenarios do what they say."""

from __future__ import annotations

import json

import numpy as np
import pytest
from armfusion.models.effects import model_from_entries
from armfusion.models.kinematics import gravity_in_sensors, joint_axis_angle_to_vertical, sensor_poses
from armfusion.models.motion import MotionState
from armfusion.models.rotations import GRAVITY_MPS2, R_from_rpy, up_from_tilt
from armfusion.models.sensor_models import stream_models
from armfusion.models.simulator import SimulationOptions, simulate
from armfusion.models.trajectories import RENK_RATES_DEG_S, SCENARIOS, RampDrive, make_scenario

ACCS = ("acc1", "acc2", "acc3", "acc4")


def _up(rec):
    rpy = rec.streams["true_base"].values
    return up_from_tilt(rpy[:, 0], rpy[:, 1])


def test_still_pose_reads_one_g_and_matches_the_kinematic_prediction(wmra):
    rec, truth = simulate(wmra, "startup", duration_s=10, seed=2)
    q = rec.streams["true_q"].values
    up = _up(rec)
    expect = gravity_in_sensors(wmra, q[:1], up[:1])[0]  # g, (S, 3)
    for s, name in enumerate(ACCS):
        v = rec.streams[name].values
        mean_g = v.mean(axis=0) / 256.0
        # 1000 samples of 0.75-1.1 LSB noise: the mean is good to ~0.04 LSB (0.15 mg)
        sem = np.array([0.75, 0.75, 1.1]) / np.sqrt(len(v)) / 256.0
        assert np.all(np.abs(mean_g - expect[s]) < 5 * sem + 1e-5), name
        assert abs(np.linalg.norm(mean_g) - 1.0) < 1e-3, name
        # and the spread is the datasheet's noise
        np.testing.assert_allclose(v.std(axis=0), np.sqrt([0.75**2 + 1 / 12] * 2 + [1.1**2 + 1 / 12]),
                                   rtol=0.15)
    imu = rec.streams["imu_acc"].values.mean(axis=0) / 16384.0
    np.testing.assert_allclose(imu, up[0], atol=5e-4)


def test_still_pose_with_realistic_effects_matches_the_model_with_the_true_effects(wmra):
    rec, truth = simulate(wmra, "startup", duration_s=10, seed=5, realistic=True)
    model = model_from_entries(wmra, truth["effects"])
    state = MotionState.static(rec.streams["true_q"].values[:1], *rec.streams["true_base"].values[0],
                               temperature_c=22.0)
    # temperature: the register says what the model needs
    T = rec.streams["imu_temp"].values[:, 0] / 340.0 + 35.0
    state = state.replace(temperature_c=np.array([T.mean()]))
    pred = model.predict(state)
    for name in ACCS + ("imu_acc",):
        v = rec.streams[name].values
        m = stream_models(wmra)[name]
        sem = m.sigma_counts / np.sqrt(len(v))
        # the temperature rises 0.13 °C in 10 s; the drift is at most ~0.003 g/°C
        assert np.all(np.abs(v.mean(axis=0) - pred[name][0]) < 5 * sem + 1e-3 * m.gain), name
        norm = np.linalg.norm(v.mean(axis=0) / m.gain)
        assert abs(norm - 1.0) < 0.25, name  # 1 g, within the drawn biases and scales
        assert abs(norm - 1.0) > 1e-3 or name == "imu_acc"  # and the effects are really there


def test_moving_arm_on_a_driving_chair_matches_finite_differences_of_positions(wmra, rng):
    """daily-use, no noise: the counts are the finite-difference specific force, rounded."""
    sc = make_scenario(wmra, "daily-use", duration_s=120, seed=9)
    rec, _ = simulate(wmra, sc, options=SimulationOptions(noise=False), seed=9)
    idx = rng.choice(np.arange(1000, 11900), 400, replace=False)
    t = rec.streams["acc1"].t_s[idx]
    h = 1e-3

    def pos(tt):
        s = sc.state(tt)
        _, p0S = sensor_poses(wmra, s.q_rad)
        return sc.base_position_m(tt)[:, None, :] + np.einsum("nij,nsj->nsi", s.R_WB, p0S)

    a_W = (-pos(t + 2 * h) + 16 * pos(t + h) - 30 * pos(t) + 16 * pos(t - h) - pos(t - 2 * h)) / (12 * h * h)
    st = sc.state(t)
    R_WS = st.R_WB[:, None] @ sensor_poses(wmra, st.q_rad)[0]
    f_fd = np.einsum("nsji,nsj->nsi", R_WS, a_W + [0, 0, GRAVITY_MPS2]) / GRAVITY_MPS2
    moving = np.abs(f_fd - gravity_in_sensors(wmra, st.q_rad, st.up_0)).max()
    assert moving > 0.02  # g: the chair and the arm really move here
    for s, name in enumerate(ACCS):
        counts = rec.streams[name].values[idx]
        # within rounding (0.5 LSB) plus 1 mg
        assert np.abs(counts - f_fd[:, s] * 256.0).max() <= 0.5 + 1e-3 * 256.0, name


def test_truth_columns_and_sidecar(wmra):
    rec, truth = simulate(wmra, "static-poses", duration_s=30, seed=1, realistic=True)
    sc = make_scenario(wmra, "static-poses", duration_s=30, seed=1)
    t = rec.streams["true_q"].t_s
    np.testing.assert_allclose(rec.streams["true_q"].values, sc.state(t).q_rad)
    np.testing.assert_allclose(R_from_rpy(*rec.streams["true_base"].values.T), sc.state(t).R_WB, atol=1e-12)
    json.dumps(truth)  # JSON-ready as it is
    assert truth["format"] == "armfusion.truth/1" and truth["scenario"] == "static-poses"
    names = {f"{e['target']}.{e['effect']}" for e in truth["effects"]}
    assert {"acc3.mount_rotation", "j2.joint_offset", "imu.base_mount", "imu.mag_soft_iron",
            "acc1.time_offset", "j7.mag_arm_disturbance"} <= names
    assert rec.streams["enc"].values[0].tolist() == [0] * 7  # relative to power-up
    # encoders: counts per joint radian from the config, each joint's own scale error applied
    scale = {e["target"]: e["params"]["scale_error"][0] for e in truth["effects"]
             if e["effect"] == "encoder_scale"}
    j = 4
    dq = rec.streams["true_q"].values[:, j] - rec.streams["true_q"].values[0, j]
    toff = [e for e in truth["effects"] if e["effect"] == "time_offset" and e["target"] == "enc"]
    assert not toff  # the encoders are the time reference
    expect = np.rint(dq * wmra.counts_per_rad[j] * (1 + scale[f"j{j + 1}"]))
    np.testing.assert_array_equal(rec.streams["enc"].values[:, j], expect)


def test_replaying_the_truth_file_reproduces_the_recording(wmra):
    rec, truth = simulate(wmra, "daily-use", duration_s=20, seed=4, realistic=True)
    again, truth2 = simulate(wmra, "daily-use", duration_s=20, seed=4, effects=truth["effects"])
    for name, s in rec.raw().items():
        np.testing.assert_array_equal(again.streams[name].values, s.values, err_msg=name)
    assert truth2["effects"] == truth["effects"]
    # the same imperfect arm in another scenario: same effects, another motion
    other, truth3 = simulate(wmra, "startup", duration_s=5, seed=99, effects=truth["effects"])
    assert truth3["effects"] == truth["effects"]


def test_seeds(wmra):
    a, ta = simulate(wmra, "static-poses", duration_s=10, seed=1, realistic=True)
    b, tb = simulate(wmra, "static-poses", duration_s=10, seed=1, realistic=True)
    c, tc = simulate(wmra, "static-poses", duration_s=10, seed=2, realistic=True)
    np.testing.assert_array_equal(a.streams["acc2"].values, b.streams["acc2"].values)
    assert not np.array_equal(a.streams["acc2"].values, c.streams["acc2"].values)
    assert ta["effects"] == tb["effects"] != tc["effects"]
    # a longer recording of the same seed: the same arm
    d, td = simulate(wmra, "static-poses", duration_s=20, seed=1, realistic=True)
    assert td["effects"] == ta["effects"]


def test_time_offset_is_read_at_the_earlier_instant(wmra):
    """The simulator shifts by interpolation; the model re-evaluated at t - offset agrees."""
    sc = make_scenario(wmra, "excitation", duration_s=12, seed=3)
    entries = [{"effect": "time_offset", "target": "acc4", "value": [0.023]}]
    rec, _ = simulate(wmra, sc, options=SimulationOptions(noise=False), effects=entries)
    model = model_from_entries(wmra, entries)
    t = rec.streams["acc4"].t_s
    exact = model.predict(sc.state(t), streams=["acc4"], state_at=sc.state)["acc4"]
    assert np.abs(rec.streams["acc4"].values - exact).max() <= 0.5 + 1e-3
    plain = model.predict(sc.state(t), model.pack({"acc4.time_offset": [0.0]}), ["acc4"])["acc4"]
    assert np.abs(plain - exact).max() > 3  # counts: the offset is visible while moving


def test_devices_at_their_own_rates(wmra):
    rec, truth = simulate(wmra, "startup", duration_s=4, rate_hz=100,
                          options=SimulationOptions(rates_hz={"imu": 50, "acc1": 400}))
    assert len(rec.streams["imu_mag"]) == 200 and len(rec.streams["acc1"]) == 1600
    assert len(rec.streams["acc2"]) == 400 and len(rec.streams["true_q"]) == 400
    assert truth["streams"]["acc1"]["rate_hz"] == 400
    # faster sampling, more noise per sample (bandwidth = rate / 2)
    assert rec.streams["acc1"].values[:, 2].std() > 1.6 * rec.streams["acc2"].values[:, 2].std()
    with pytest.raises(ValueError, match="no device 'gps'"):
        simulate(wmra, "startup", duration_s=1, options=SimulationOptions(rates_hz={"gps": 10}))


def test_another_earth_field_is_what_the_compass_reads_and_the_truth_says(wmra):
    """Earth's field given in the options (here 30 µT north, 20 µT down) is the one the truth
    file records and the one the compass reads, in counts, without noise."""
    field_ut = np.array([30.0, 0.0, -20.0])
    here, truth = simulate(wmra, "startup", duration_s=1, seed=3,
                           options=SimulationOptions(noise=False, earth_field_ut=field_ut))
    tampa, _ = simulate(wmra, "startup", duration_s=1, seed=3, options=SimulationOptions(noise=False))
    assert truth["earth_field_world_ut"] == [30.0, 0.0, -20.0]
    assert not np.array_equal(here.streams["imu_mag"].values, tampa.streams["imu_mag"].values)
    np.testing.assert_array_equal(here.streams["acc1"].values, tampa.streams["acc1"].values)


def test_unknown_scenario_is_refused_with_the_list(wmra):
    with pytest.raises(ValueError, match="unknown scenario 'dayly-use'; known: startup, static-poses"):
        simulate(wmra, "dayly-use", duration_s=1)


# --------------------------------------------------------------------------------------
# scenarios
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_stays_inside_the_joint_limits_and_starts_still(wmra, crs, name):
    for arm in (wmra, crs):
        sc = make_scenario(arm, name, duration_s=min(SCENARIOS[name].default_duration_s, 300), seed=3)
        t = np.linspace(0, sc.duration_s, 20001)
        st = sc.state(t)
        assert np.all(arm.within_limits(st.q_rad)), name
        first = st.take(t < 1.0)
        assert np.abs(first.qd_rad_s).max() < 1e-9 and np.abs(first.accel_B_mps2).max() < 1e-9


def test_static_poses_hold_still_and_some_are_near_gimbal_lock(wmra):
    sc = make_scenario(wmra, "static-poses", duration_s=300, seed=1)
    holds = [e for e in sc.events if e["what"].startswith("still pose")]
    assert len(holds) >= 15
    near = [e for e in holds if e["min_axis_to_vertical_deg"] < 3.0]
    assert 0.15 <= len(near) / len(holds) <= 0.4
    for e in holds[:5]:
        st = sc.state(np.linspace(e["t_start_s"] + 0.01, e["t_end_s"] - 0.01, 50))
        assert np.abs(st.qd_rad_s).max() < 1e-12
        ang = np.degrees(joint_axis_angle_to_vertical(wmra, st.q_rad[:1], st.up_0[:1])).min()
        assert ang == pytest.approx(e["min_axis_to_vertical_deg"], abs=1e-6)
    peak = np.degrees(np.abs(sc.state(np.linspace(0, 300, 30001)).qd_rad_s).max())
    assert peak <= 30.0 + 1e-6  # deg/s: slow moves


def test_renk_maneuver_has_the_articles_rates(wmra):
    sc = make_scenario(wmra, "renk-maneuver", seed=0)
    assert sc.duration_s == pytest.approx(27.74 * 60)
    t = np.arange(30.0, sc.duration_s, 0.25)
    mean_rate = np.degrees(np.abs(sc.state(t).qd_rad_s).mean(axis=0))
    assert mean_rate[0] == pytest.approx(RENK_RATES_DEG_S["yaw"], rel=0.05)
    assert mean_rate[-1] == pytest.approx(RENK_RATES_DEG_S["roll"], rel=0.05)
    assert mean_rate[1] == pytest.approx(RENK_RATES_DEG_S["pitch"], rel=0.1)
    # slow enough that gravity dominates (the article's assumption): motion terms < 5 mg
    rec, _ = simulate(wmra, sc, duration_s=300, options=SimulationOptions(noise=False), seed=0)
    for name in ACCS:
        norm = np.linalg.norm(rec.streams[name].values / 256.0, axis=1)
        assert np.abs(norm - 1).max() < 0.02


def test_renk_maneuver_on_the_articles_own_arm(crs):
    """Joints 1, 5, 6 move (yaw, pitch, roll) at the article's rates; 2-4 stay locked."""
    sc = make_scenario(crs, "renk-maneuver", seed=0, joints=["j1", "j5", "j6"])
    t = np.arange(30.0, sc.duration_s, 0.25)
    st = sc.state(t)
    np.testing.assert_allclose(np.degrees(st.q_rad[:, 1:4]), np.broadcast_to([90, -180, 0], (len(t), 3)),
                               atol=1e-9)
    rate = np.degrees(np.abs(st.qd_rad_s).mean(axis=0))
    np.testing.assert_allclose(rate[[0, 4, 5]], [3.1, 0.87, 13.9], rtol=0.1)


def test_renk_ramp_parks_the_chair_level_then_up_down_and_across_a_ramp(wmra):
    """The calibration maneuver on a ramp: the chair stands still in each stance at the 1:12
    slope's tilt (up, down, across both ways; the ground a few tenths off), moves only in the
    transitions (rolling onto the slope, turning on the spot), and the arm sweeps as in
    renk-maneuver throughout."""
    sc = make_scenario(wmra, "renk-ramp", 300.0, seed=4)
    parked = [e for e in sc.events if e.get("parked")]
    assert [e["what"] for e in parked] == [
        "parked: level", "parked: ramp facing up", "parked: ramp facing down",
        "parked: across the ramp, right side low", "parked: across the ramp, left side low"]
    slope_deg = np.degrees(np.arctan(1 / 12))
    nominal = [(0, 0), (0, -slope_deg), (0, slope_deg), (slope_deg, 0), (-slope_deg, 0)]
    for e, want in zip(parked, nominal, strict=True):
        assert e["t_end_s"] - e["t_start_s"] > 40.0
        t = np.linspace(e["t_start_s"], e["t_end_s"], 200)
        st = sc.state(t)
        tilt = np.degrees(st.rpy_rad[:, :2])
        np.testing.assert_allclose(tilt, np.broadcast_to(e["tilt_deg"], tilt.shape), atol=1e-3)  # rounded
        assert np.abs(tilt[0] - want).max() < 1.0  # uneven ground: tenths of a degree
        assert np.abs(st.omega_B_rad_s).max() < 1e-12 and np.abs(st.accel_B_mps2).max() < 1e-12  # parked
    moves = [e for e in sc.events if e["what"].startswith("the chair moves")]
    assert len(moves) == 4
    for e in moves:
        st = sc.state(np.linspace(e["t_start_s"], e["t_end_s"], 2000))
        rate = np.degrees(np.abs(st.omega_B_rad_s).max(0))
        assert 1.0 < rate[:2].max() < 10.0 and 30.0 < rate[2] <= 45.0 + 1e-6  # rolls on, turns
        assert np.linalg.norm(st.accel_B_mps2, axis=1).max() < 1.0  # m/s²: a slow technician's drive
    # the arm sweeps as in renk-maneuver (same seed, same joints)
    t = np.arange(0.0, 300.0, 0.5)
    parked_sweep = make_scenario(wmra, "renk-maneuver", 300.0, seed=4)
    np.testing.assert_allclose(sc.state(t).q_rad, parked_sweep.state(t).q_rad)
    with pytest.raises(ValueError, match="too short"):
        make_scenario(wmra, "renk-ramp", 60.0)


def test_renk_ramp_takes_a_steeper_ramp_and_refuses_one_no_chair_climbs(wmra):
    """A ramp of 1:8 parks the chair at its 7.1°; a slope of 0.5 (27°) or a chair that does
    not move is refused, saying which."""
    sc = make_scenario(wmra, "renk-ramp", 300.0, seed=4, ramp=RampDrive(slope=1 / 8))
    up = next(e for e in sc.events if e["what"] == "parked: ramp facing up")
    assert abs(up["tilt_deg"][1] + np.degrees(np.arctan(1 / 8))) < 1.0
    with pytest.raises(ValueError, match=r"slope must be in \(0, 0.3\] \(rise over run\), got 0.5"):
        make_scenario(wmra, "renk-ramp", 300.0, ramp=RampDrive(slope=0.5))
    with pytest.raises(ValueError, match="drive speed and turn rate must be positive"):
        make_scenario(wmra, "renk-ramp", 300.0, ramp=RampDrive(drive_speed_mps=0.0))


def test_daily_use_drives_turns_and_climbs_ramps_like_a_wheelchair(wmra):
    sc = make_scenario(wmra, "daily-use", duration_s=1200, seed=2)
    t = np.arange(0, 1200, 0.02)
    st = sc.state(t)
    a = np.linalg.norm(st.accel_B_mps2, axis=1) / GRAVITY_MPS2
    yaw_rate = np.degrees(np.abs(st.omega_B_rad_s[:, 2]))
    pitch = np.degrees(np.abs(st.rpy_rad[:, 1]))
    assert 0.05 < a.max() < 0.2  # g: starts, stops and turns
    assert 30 < yaw_rate.max() <= 60.5  # deg/s
    assert 2.0 < pitch.max() <= np.degrees(np.arctan(1 / 12)) + 0.05  # ramps up to 1:12
    assert np.abs(st.qd_rad_s).max(axis=0).min() > 0  # every joint reaches
    assert np.degrees(np.abs(st.qd_rad_s).max()) <= 25.0 + 1e-6
    whats = " ".join(e["what"] for e in sc.events)
    assert "ramp" in whats and "turn" in whats and "arm reaches" in whats


def test_the_plot_script_draws_a_simulated_recording(wmra, tmp_path):
    from tools.plot_recording import plot_recording

    rec, truth = simulate(wmra, "daily-use", duration_s=40, seed=6, realistic=True)
    out = plot_recording(rec, tmp_path / "rec.png", wmra, truth)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 50_000


def test_the_compass_turn_turns_the_chair_once_on_the_spot_while_the_arm_stays_parked(wmra):
    """``compass-turn``: every heading seen once (360 deg), no drive, the arm at its ready pose
    and still, the chair still before and after the turn."""
    sc = make_scenario(wmra, "compass-turn", seed=2)
    assert sc.duration_s == pytest.approx(14.8)
    t = np.linspace(0.0, sc.duration_s, 3001)
    st = sc.state(t)
    assert np.allclose(st.q_rad, wmra.ready_pose_rad) and np.abs(st.qd_rad_s).max() == 0.0
    turned = sc.base.yaw_rate.integral(np.array([sc.duration_s]))[0, 0]
    assert np.degrees(turned) == pytest.approx(360.0, abs=1e-6)
    assert np.abs(sc.base.speed(t)[0]).max() == 0.0
    still = (t < 3.0) | (t > sc.duration_s - 3.0)
    assert np.abs(st.omega_B_rad_s[still]).max() < 1e-12
    assert np.degrees(np.abs(st.omega_B_rad_s[:, 2]).max()) == pytest.approx(45.0, rel=1e-6)
