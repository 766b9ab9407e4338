"""Motion kinematics: the analytic specific force against finite differences of positions.

The reference here never uses ω, ω̇ or joint rates: it differentiates world positions of
the sensors twice (a 5-point stencil) and rotates into the sensor's axes. Agreement to
well under 1 mg means every centripetal, tangential, Coriolis and base term is right.
"""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.models.kinematics import gravity_in_sensors, gravity_jacobian, sensor_poses
from armfusion.models.motion import (
    MassModel,
    MotionState,
    body_rates_from_rpy,
    gravity_torques,
    lever_arm_jacobian,
    link_motion,
    sensor_motion,
    specific_force,
    specific_force_jacobian,
)
from armfusion.models.rotations import GRAVITY_MPS2, R_from_rpy, up_from_tilt
from armfusion.models.trajectories import make_scenario

from tests.conftest import random_poses

H = 1e-3  # s, finite-difference step


def d1(f, t):
    return (-f(t + 2 * H) + 8 * f(t + H) - 8 * f(t - H) + f(t - 2 * H)) / (12 * H)


def d2(f, t):
    return (-f(t + 2 * H) + 16 * f(t + H) - 30 * f(t) + 16 * f(t - H) - f(t - 2 * H)) / (12 * H * H)


def vee(W):
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], -1)


class ClosedForm:
    """Joints and base as closed-form functions of time: fast swings, a base that moves,
    tilts and turns (about 0.4 g of motion at the wrist)."""

    def __init__(self, arm):
        self.arm = arm
        self.k = np.arange(1, arm.n_joints + 1)

    def q(self, t):
        return self.arm.ready_pose_rad + 0.5 * np.sin(np.outer(t, 0.7 * self.k) + self.k)

    def P(self, t):
        return np.stack([0.3 * np.sin(0.9 * t), 0.2 * np.cos(1.3 * t), 0.05 * np.sin(2 * t)], -1)

    def R(self, t):
        return R_from_rpy(0.1 * np.sin(1.1 * t), 0.08 * np.cos(0.7 * t), 0.5 * t)

    def state_by_differences(self, t):
        """The motion state, every rate from finite differences (no analytic formula)."""
        R, Rd, Rdd = self.R(t), d1(self.R, t), d2(self.R, t)
        Rt = np.swapaxes(R, -1, -2)
        w = vee(Rt @ Rd)
        wd = vee(np.swapaxes(Rd, -1, -2) @ Rd + Rt @ Rdd)
        aB = np.einsum("nji,nj->ni", R, d2(self.P, t))
        return MotionState(t, self.q(t), d1(self.q, t), d2(self.q, t), R, w, wd, aB, 25.0)


def fd_specific_force(arm, q_of_t, R_of_t, P_of_t, t):
    """In g, (N, S, 3): second difference of world positions, rotated into sensor axes."""
    def pos(tt):
        _, p0S = sensor_poses(arm, q_of_t(tt))
        return P_of_t(tt)[:, None, :] + np.einsum("nij,nsj->nsi", R_of_t(tt), p0S)

    a_W = d2(pos, t)
    R0S, _ = sensor_poses(arm, q_of_t(t))
    R_WS = R_of_t(t)[:, None] @ R0S
    return np.einsum("nsji,nsj->nsi", R_WS, a_W + np.array([0, 0, GRAVITY_MPS2])) / GRAVITY_MPS2


@pytest.mark.parametrize("arm_name", ["wmra", "crs"])
def test_at_rest_the_reading_is_the_static_gravity_model(arm_name, request, rng):
    arm = request.getfixturevalue(arm_name)
    q = random_poses(arm, 50, rng)
    state = MotionState.static(q, rng.normal(0, 0.1, 50), rng.normal(0, 0.1, 50), rng.uniform(-3, 3, 50))
    np.testing.assert_allclose(specific_force(arm, state), gravity_in_sensors(arm, q, state.up_0), atol=1e-14)
    np.testing.assert_allclose(specific_force_jacobian(arm, state), gravity_jacobian(arm, q, state.up_0)[1],
                               atol=1e-14)


@pytest.mark.parametrize("arm_name", ["wmra", "crs"])
def test_moving_arm_on_moving_base_matches_finite_differences_of_positions(arm_name, request, rng):
    arm = request.getfixturevalue(arm_name)
    cf = ClosedForm(arm)
    t = rng.uniform(0.5, 20.0, 40)
    state = cf.state_by_differences(t)
    f = specific_force(arm, state)
    ref = fd_specific_force(arm, cf.q, cf.R, cf.P, t)
    moving = np.abs(f - gravity_in_sensors(arm, state.q_rad, state.up_0)).max()
    assert moving > 0.1  # g: the motion terms are large here, so the agreement means something
    assert np.abs(f - ref).max() < 1e-6  # g (1 µg; the issue asks for 1 mg)


def test_daily_use_scenario_matches_finite_differences_of_positions(wmra, rng):
    """The scenario's own rates (analytic) against its own positions (differenced)."""
    sc = make_scenario(wmra, "daily-use", duration_s=300, seed=7)
    t = rng.uniform(10, 299, 300)
    state = sc.state(t)

    def q(tt):
        return sc.state(tt).q_rad

    def R(tt):
        return sc.state(tt).R_WB

    ref = fd_specific_force(wmra, q, R, sc.base_position_m, t)
    f = specific_force(wmra, state)
    assert np.abs(f - gravity_in_sensors(wmra, state.q_rad, state.up_0)).max() > 0.02
    assert np.abs(f - ref).max() < 1e-3 / 10  # well inside 1 mg


def test_joint_jacobian_with_motion_matches_numerical(wmra, rng):
    cf = ClosedForm(wmra)
    state = cf.state_by_differences(rng.uniform(1, 10, 8))
    J = specific_force_jacobian(wmra, state)
    h = 1e-6
    for j in range(wmra.n_joints):
        dq = np.zeros(wmra.n_joints)
        dq[j] = h
        num = (specific_force(wmra, state.replace(q_rad=state.q_rad + dq))
               - specific_force(wmra, state.replace(q_rad=state.q_rad - dq))) / (2 * h)
        np.testing.assert_allclose(J[..., j], num, atol=1e-8)


def test_lever_arm_jacobian_matches_numerical(wmra, rng):
    cf = ClosedForm(wmra)
    state = cf.state_by_differences(rng.uniform(1, 10, 8))
    lm = link_motion(wmra, state)
    sm = sensor_motion(wmra, state, lm=lm)
    L = lever_arm_jacobian(sm, lm)
    p = np.stack([s.p_L_m for s in wmra.link_accelerometers])
    h = 1e-5
    for c in range(3):
        dp = np.zeros_like(p)
        dp[:, c] = h
        num = (sensor_motion(wmra, state, p_LS_m=p + dp).specific_force_g
               - sensor_motion(wmra, state, p_LS_m=p - dp).specific_force_g) / (2 * h)
        np.testing.assert_allclose(L[..., c], num, atol=1e-9)


def test_base_imu_reads_the_base_rate_and_acceleration(wmra, rng):
    """An IMU at the base origin, axes as the base: gyro = ω_B, accel = a_B + g·up."""
    cf = ClosedForm(wmra)
    state = cf.state_by_differences(rng.uniform(1, 10, 20))
    sm = sensor_motion(wmra, state, ["imu"])
    np.testing.assert_allclose(sm.omega_S_rad_s[:, 0], state.omega_B_rad_s, atol=1e-14)
    np.testing.assert_allclose(sm.specific_force_mps2[:, 0],
                               state.accel_B_mps2 + GRAVITY_MPS2 * state.up_0, atol=1e-12)


def test_body_rates_from_euler_angles_match_the_rotation_matrices(rng):
    def rpy(t):
        return np.stack([0.1 * np.sin(1.1 * t), 0.08 * np.cos(0.7 * t), 0.5 * t + 0.3 * np.sin(t)], -1)

    def R(t):
        return R_from_rpy(*rpy(t).T)

    t = rng.uniform(0, 10, 20)
    w, wd = body_rates_from_rpy(rpy(t), d1(rpy, t), d2(rpy, t))
    Rt = np.swapaxes(R(t), -1, -2)
    np.testing.assert_allclose(w, vee(Rt @ d1(R, t)), atol=1e-10)
    np.testing.assert_allclose(wd, vee(np.swapaxes(d1(R, t), -1, -2) @ d1(R, t) + Rt @ d2(R, t)), atol=1e-7)


def test_gravity_torque_jacobian_matches_numerical(wmra, rng):
    q = random_poses(wmra, 10, rng)
    up = up_from_tilt(rng.normal(0, 0.1, 10), rng.normal(0, 0.1, 10))
    tau, dtau = gravity_torques(wmra, q, up, jacobian=True)
    h = 1e-6
    for i in range(wmra.n_joints):
        dq = np.zeros(wmra.n_joints)
        dq[i] = h
        num = (gravity_torques(wmra, q + dq, up) - gravity_torques(wmra, q - dq, up)) / (2 * h)
        np.testing.assert_allclose(dtau[..., i], num, atol=1e-6)


def test_gravity_torque_is_the_weight_times_the_horizontal_reach(wmra):
    """A single joint carrying everything: τ = -(total mass) g (horizontal lever) about it.

    Checked against an independent sum over the point masses for joint 2 of the WMRA."""
    masses = MassModel()
    q = np.radians([[90, 30, 0, 60, 0, 20, 0]])
    tau = gravity_torques(wmra, q)[0]
    lm = link_motion(wmra, MotionState.static(q))
    pos, m, links = masses.points(wmra, lm)
    z, o = lm.axis_0[0, 1], lm.origin_0_m[0, 1]
    g = np.array([0, 0, -GRAVITY_MPS2])
    ref = sum(np.dot(z, np.cross(pos[0, k] - o, m[k] * g)) for k in range(len(m)) if links[k] > 1)
    assert tau[1] == pytest.approx(ref, rel=1e-12)
    assert 10.0 < m.sum() < 20.0  # kg: the nominal WMRA mass model
    # the last joint (tool roll) carries its payload on its axis: no torque
    assert abs(tau[-1]) < 1e-9


def test_motion_state_checks_its_shapes(wmra):
    with pytest.raises(ValueError, match=r"qd_rad_s must have shape \(2, 7\)"):
        MotionState(np.zeros(2), np.zeros((2, 7)), np.zeros((3, 7)), 0.0, np.eye(3), 0.0, 0.0, 0.0, 25.0)
    with pytest.raises(ValueError, match=r"shape \(N, 7\).*got \(1, 6\)"):
        specific_force(wmra, MotionState.static(np.zeros(6)))


def test_motion_state_from_sampled_angles(wmra):
    """Rates from samples (as an estimator gets them from encoders and an attitude) agree
    with the scenario's exact ones to a fraction of the motion's own size."""
    sc = make_scenario(wmra, "daily-use", duration_s=120, seed=4)
    t = np.arange(0, 120, 0.01)
    exact = sc.state(t)
    est = MotionState.from_samples(t, exact.q_rad, exact.rpy_rad, exact.accel_B_mps2)
    inner = slice(2, -2)
    assert np.abs(est.qd_rad_s - exact.qd_rad_s)[inner].max() < 1e-3 * np.abs(exact.qd_rad_s).max() + 1e-6
    assert np.abs(est.omega_B_rad_s - exact.omega_B_rad_s)[inner].max() < 0.01 * np.abs(
        exact.omega_B_rad_s).max()
    f_est, f_exact = specific_force(wmra, est.take(inner)), specific_force(wmra, exact.take(inner))
    # second differences at 100 Hz round off the jerk steps at the ends of moves: a few mg
    # there, nothing elsewhere
    err = np.abs(f_est - f_exact)
    assert err.max() < 5e-3 and np.median(err) < 1e-5  # g
