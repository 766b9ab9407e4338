"""The chair turns about its drive wheels' axle, and the arm's base sits off that point: the
config's ``chair.base_from_turning_centre_mm`` lets the tracker predict what the chair's
rotation adds to the base's acceleration (``ω̇ x ρ + ω x (ω x ρ)``, from the gyro), where
its acceleration state would otherwise chase it (the IMU's innovations then followed each
turn's onset: ``diagnose`` called clean drives "not white")."""

from __future__ import annotations

import copy
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.frame_kernels import FrameConstants
from armfusion.fusion.tracking.frames import BaseTurn, JointMotion, make_frames
from armfusion.fusion.tracking.tracker import start_from_recording
from armfusion.models.arm_config import ConfigError, build_arm
from armfusion.models.simulator import simulate
from armfusion.models.trajectories import make_scenario

WMRA_YAML = Path(__file__).resolve().parents[2] / "config" / "wmra.yaml"


def _problems(data) -> list[str]:
    with pytest.raises(ConfigError) as e:
        build_arm(data, "arm.yaml")
    return [str(p) for p in e.value.problems]


def test_the_wmra_states_where_its_chair_turns_and_a_bad_statement_is_refused_by_key():
    arm = load_arm("wmra")
    np.testing.assert_allclose(arm.base_from_turning_centre_m, [0.25, -0.35, 0.45])
    data = yaml.safe_load(WMRA_YAML.read_text())
    short = copy.deepcopy(data)
    short["chair"]["base_from_turning_centre_mm"] = [250, -350]
    (p,) = _problems(short)
    assert "chair.base_from_turning_centre_mm" in p and "a position has 3 entries, not 2" in p
    far = copy.deepcopy(data)
    far["chair"]["base_from_turning_centre_mm"] = [250, -350, 1e12]
    (p,) = _problems(far)
    assert "chair.base_from_turning_centre_mm" in p and "within ±5000" in p
    with pytest.raises(ConfigError, match=r"chair\.wheelbase_mm"):
        build_arm({**data, "chair": {"base_from_turning_centre_mm": [0, 0, 0], "wheelbase_mm": 5}},
                  "arm.yaml")
    del data["chair"]
    assert build_arm(data, "arm.yaml").base_from_turning_centre_m is None


def test_a_turning_chair_swings_every_sensor_about_its_turning_centre():
    """The compiled frame and its NumPy reference agree; the IMU, at the base origin, moves
    with the lever's tangential and centripetal acceleration (and without a chair block, as
    before, not at all); the differentiated gyro's error is weighed by the distance from
    the turning centre."""
    arm = load_arm("wmra")
    rho = np.array([0.25, -0.35, 0.45])
    names = tuple(s.name for s in arm.link_accelerometers) + ("imu",)
    rng = np.random.default_rng(3)
    enc = np.stack([arm.ready_pose_rad, rng.normal(0, 0.1, 7), rng.normal(0, 0.2, 7)])
    w, wd = np.array([0.02, -0.03, 0.8]), np.array([0.1, 0.05, 1.5])
    f = FrameConstants(arm, names).fields(enc, np.zeros(7), w, wd)
    ref = make_frames(arm, names, JointMotion(enc[0][None], enc[1][None], enc[2][None]), np.zeros(7),
                      BaseTurn(w[None], wd[None])).take(0)
    np.testing.assert_allclose(f[3], ref.motion_mps2, atol=1e-12)
    np.testing.assert_allclose(f[9], ref.dist2_m2, atol=1e-12)
    np.testing.assert_allclose(f[3][-1], np.cross(wd, rho) + np.cross(w, np.cross(w, rho)), atol=1e-12)
    assert f[9][-1] == pytest.approx(rho @ rho)
    bare = replace(arm, base_from_turning_centre_m=None)
    g = FrameConstants(bare, names).fields(enc, np.zeros(7), w, wd)
    np.testing.assert_allclose(g[3][-1], 0.0, atol=1e-15)
    np.testing.assert_allclose(g[3][:-1] + (np.cross(wd, rho) + np.cross(w, np.cross(w, rho))), f[3][:-1],
                               atol=1e-12)
    # no motion compensation: nothing moves, the lever's term included
    np.testing.assert_allclose(FrameConstants(arm, names).fields(enc, np.zeros(7), w, wd, False)[3], 0.0,
                               atol=1e-15)


def _imu_block_means(arm, rec, block_s=0.25):
    """The tracker over ``rec``: the IMU accelerometer's innovations (g), averaged over blocks."""
    tr, _ = start_from_recording(arm, rec)
    tr.run(rec, truth=False)
    lg = tr.innovations("imu_acc")
    ok = np.all(np.isfinite(lg.innovation), 1)
    t, nu = lg.t_s[ok], lg.innovation[ok]
    n = int(round(block_s / np.median(np.diff(t))))
    m = len(t) // n
    return t[: m * n].reshape(m, n).mean(1), nu[: m * n].reshape(m, n, 3).mean(1)


def test_a_turn_on_the_spot_leaves_the_imus_innovations_at_their_noise():
    """One turn on the spot (360° at 45 °/s): the chair's centre does not accelerate, the
    arm's base does (up to 0.6 m/s² as the turn starts and stops, 0.26 m/s² centripetal).
    Told where the chair turns, the tracker predicts it and the IMU's innovations stay at
    their noise through the turn's onset and end; without it, its acceleration state
    chases the swing and the innovations follow each onset."""
    arm = load_arm("wmra")
    rec, _ = simulate(arm, "compass-turn", seed=4)
    sc = make_scenario(arm, "compass-turn", seed=4)
    assert np.linalg.norm(sc.base(np.arange(0, 14.8, 0.01)).accel_B, axis=1).max() > 0.5
    _, told = _imu_block_means(arm, rec)
    _, blind = _imu_block_means(replace(arm, base_from_turning_centre_m=None), rec)
    # the vertical axis, which no turn on level ground reaches, is the noise's yardstick
    # (seed 4: told x 1.05, y 1.14 times it; blind x 2.5 times)
    rms_told, rms_blind = np.sqrt((told**2).mean(0)), np.sqrt((blind**2).mean(0))
    assert rms_told[0] < 1.3 * rms_told[2] and rms_told[1] < 1.3 * rms_told[2]
    assert rms_blind[0] > 1.8 * rms_blind[2]
