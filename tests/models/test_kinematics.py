"""Batched kinematics against plain per-pose DH products, and analytic Jacobians."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from armfusion.models.arm import dh_transform
from armfusion.models.kinematics import (
    chain_poses,
    dependency_matrix,
    forward_kinematics,
    gravity_chain,
    gravity_in_sensors,
    gravity_jacobian,
    joint_axis_angle_to_vertical,
    sensor_poses,
)
from armfusion.models.rotations import up_from_tilt

from tests.conftest import random_poses


def _reference_fk(arm, q):
    """One pose, one 4x4 product per joint, straight from the DH formula."""
    dh = arm.dh
    T = np.eye(4)
    frames = [T.copy()]
    for i in range(arm.n_joints):
        T = T @ dh_transform(dh.convention, dh.alpha_rad[i], dh.a_m[i], dh.d_m[i],
                             q[i] + dh.offset_rad[i])
        frames.append(T.copy())
    return frames


@pytest.mark.parametrize("arm_name", ["wmra", "crs"])
def test_batched_fk_matches_the_dh_formula(arm_name, request, rng):
    arm = request.getfixturevalue(arm_name)
    q = random_poses(arm, 50, rng)
    poses = chain_poses(arm, q)
    for k in range(len(q)):
        ref = _reference_fk(arm, q[k])
        for i, T in enumerate(ref):
            np.testing.assert_allclose(poses.R_0L[k, i], T[:3, :3], atol=1e-12)
            np.testing.assert_allclose(poses.p_0L_m[k, i], T[:3, 3], atol=1e-12)
    R, p = forward_kinematics(arm, q)
    np.testing.assert_allclose(R, poses.R_0L[:, -1])
    np.testing.assert_allclose(p, poses.p_0L_m[:, -1])


def test_wmra_zero_pose_reach_is_the_sum_of_its_links(wmra):
    # all joints at zero: the offsets d stack up; the flange sits at a known point
    _, p = forward_kinematics(wmra, np.zeros((1, 7)))
    ref = _reference_fk(wmra, np.zeros(7))[-1][:3, 3]
    np.testing.assert_allclose(p[0], ref, atol=1e-12)
    assert np.linalg.norm(p[0]) > 0.5  # metres: the arm is about a metre long


def test_single_pose_is_a_batch_of_one(wmra):
    q = wmra.ready_pose_rad
    R1, p1 = forward_kinematics(wmra, q)
    R2, p2 = forward_kinematics(wmra, q[None, :])
    assert R1.shape == (1, 3, 3)
    np.testing.assert_array_equal(R1, R2)
    np.testing.assert_array_equal(p1, p2)


def test_wrong_joint_count_is_refused_with_the_shape(wmra):
    with pytest.raises(ValueError, match=r"shape \(N, 7\).*got \(3, 6\)"):
        forward_kinematics(wmra, np.zeros((3, 6)))


def test_sensor_frames_are_rotations_and_static_reading_is_one_g(wmra, rng):
    q = random_poses(wmra, 200, rng)
    R_0S, _ = sensor_poses(wmra, q)
    eye = np.broadcast_to(np.eye(3), R_0S.shape)
    np.testing.assert_allclose(np.swapaxes(R_0S, -1, -2) @ R_0S, eye, atol=1e-12)
    up = up_from_tilt(rng.normal(0, 0.1, 200), rng.normal(0, 0.1, 200))
    f = gravity_in_sensors(wmra, q, up)
    np.testing.assert_allclose(np.linalg.norm(f, axis=-1), 1.0, atol=1e-12)


@pytest.mark.parametrize("arm_name", ["wmra", "crs"])
def test_gravity_jacobian_matches_finite_differences(arm_name, request, rng):
    arm = request.getfixturevalue(arm_name)
    q = random_poses(arm, 20, rng)
    up = up_from_tilt(rng.normal(0, 0.2, 20), rng.normal(0, 0.2, 20))
    f, J = gravity_jacobian(arm, q, up)
    h = 1e-6
    for j in range(arm.n_joints):
        dq = np.zeros(arm.n_joints)
        dq[j] = h
        num = (gravity_in_sensors(arm, q + dq, up) - gravity_in_sensors(arm, q - dq, up)) / (2 * h)
        np.testing.assert_allclose(J[..., j], num, atol=1e-8)
    np.testing.assert_allclose(f, gravity_in_sensors(arm, q, up), atol=1e-14)


def _turned_axes(arm, rng):
    """The same arm with every joint axis expressed in a random frame (not z): the same
    kinematics, through the general-axis path."""
    from armfusion.models.rotations import exp_so3

    joints = []
    for j in arm.joints:
        Q = exp_so3(rng.normal(0, 1.0, 3))
        joints.append(dataclasses.replace(j, R_pre=j.R_pre @ Q.T, axis=Q @ j.axis,
                                          R_post=Q @ j.R_post))
    return dataclasses.replace(arm, joints=tuple(joints))


@pytest.mark.parametrize("arm_name", ["wmra", "crs", "wmra-turned-axes"])
def test_gravity_chain_gives_the_readings_and_jacobian_of_the_frames(arm_name, request, rng):
    arm = request.getfixturevalue(arm_name.removesuffix("-turned-axes"))
    if arm_name.endswith("-turned-axes"):
        arm = _turned_axes(arm, rng)
        assert not arm.chain.axis_is_z
    q = random_poses(arm, 20, rng)
    up = up_from_tilt(rng.normal(0, 0.2, 20), rng.normal(0, 0.2, 20))
    f, J, R_0S = gravity_jacobian(arm, q, up, with_frames=True)
    outer = rng.normal(size=(20, 3, 2))  # derivatives of up by two outer parameters
    gc = gravity_chain(arm)
    after = gc.propagate(q, np.concatenate([up[:, :, None], outer], 2))
    for s, k in enumerate(gc.links):
        G = gc.read_out[s] @ after[k]
        np.testing.assert_allclose(G[:, :, 0], f[:, s], atol=1e-14)
        np.testing.assert_allclose(G[:, :, 1:1 + arm.n_joints], J[:, s], atol=1e-14)
        np.testing.assert_allclose(G[:, :, 1 + arm.n_joints:],
                                   np.swapaxes(R_0S[:, s], -1, -2) @ outer, atol=1e-14)
    np.testing.assert_allclose(np.arccos(np.clip(np.abs(gc.axis_up_cos(q, up)), 0, 1)),
                               joint_axis_angle_to_vertical(arm, q, up), atol=1e-7)


def test_which_joints_each_wmra_accelerometer_sees(wmra, rng):
    """acc1 sees joints 1-2, acc2 1-4, acc3 1-6, acc4 all seven; never a joint beyond it."""
    expected = {"acc1": 2, "acc2": 4, "acc3": 6, "acc4": 7}
    dep = dependency_matrix(wmra)
    names = [s.name for s in wmra.link_accelerometers]
    for s, name in enumerate(names):
        assert list(np.flatnonzero(dep[s])) == list(range(expected[name]))
    # and the numbers agree: moving a joint beyond a sensor's link changes nothing there
    q = random_poses(wmra, 30, rng)
    f0 = gravity_in_sensors(wmra, q)
    for j in range(7):
        dq = np.zeros(7)
        dq[j] = 0.3
        moved = np.abs(gravity_in_sensors(wmra, q + dq) - f0).max(axis=(0, 2)) > 1e-9
        for s, name in enumerate(names):
            assert moved[s] == (j < expected[name]), (name, j)


def test_ready_pose_puts_joints_3_and_6_vertical(wmra):
    ang = np.degrees(joint_axis_angle_to_vertical(wmra, wmra.ready_pose_rad))[0]
    assert ang[2] < 1e-9 and ang[5] < 1e-9
    assert np.all(np.delete(ang, [2, 5]) > 30)
    # the thesis's modified ready pose (joint 1 at 45 deg): nothing vertical
    q = wmra.ready_pose_rad.copy()
    q[0] = np.radians(45)
    assert np.degrees(joint_axis_angle_to_vertical(wmra, q)).min() > 40


def test_thesis_failure_case_joint_3_axis_along_gravity(wmra):
    q = np.radians([90, 90, 0, 0, 0, 0, 0])
    ang = np.degrees(joint_axis_angle_to_vertical(wmra, q))[0]
    assert ang[2] < 1e-9


@pytest.mark.parametrize("config", ["imu_rig_roll", "imu_rig_yaw"])
def test_a_joints_rate_from_the_gyros_on_either_side_of_it(config):
    """The real rig's layout simulated without noise: the shaft's gyro less the frame's,
    about the joint's axis, is the encoder's rate (to the values' 0.01 deg/s rounding)."""
    from armfusion.fusion.configfile import load_arm
    from armfusion.models.kinematics import joint_rate_from_link_rates
    from armfusion.models.sensor_models import stream_models
    from armfusion.models.simulator import SimulationOptions, simulate

    arm = load_arm(config)
    rec, _ = simulate(arm, "excitation", 20.0, seed=4, options=SimulationOptions(noise=False))
    sm = stream_models(arm)
    shaft = sm["shaft_gyro"].from_counts(rec.get("shaft_gyro").values) @ arm.sensor("shaft").R_LS.T
    base = sm["imu_gyro"].from_counts(rec.get("imu_gyro").values) @ arm.imu.R_LS.T
    rate = joint_rate_from_link_rates(arm, 0, base, shaft)
    q = rec.get("true_q")
    truth = np.interp(rec.get("shaft_gyro").t_s, q.t_s, np.gradient(q.values[:, 0], q.t_s))
    assert np.degrees(np.sqrt(np.mean((rate - truth) ** 2))) < 0.02
    assert np.degrees(np.std(truth)) > 10.0  # the joint did turn
