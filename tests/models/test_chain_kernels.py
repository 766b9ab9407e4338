"""The compiled chain (armfusion.models.chain_kernels) and sensor equations (armfusion.models.sensor_kernels)
against the NumPy forms they replaced.

The references below are the batched NumPy code that ``chain_poses``, ``link_motion`` and
``sensor_motion`` ran before the equations were written once, compiled: the same
products and sums, vectorised over N. The compiled forms must give their numbers (they
drive the simulator, so every seeded benchmark figure), for both shipped arms, a moving
arm on a moving base, mounts moved by an effect, and joint axes that are not z.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from armfusion.models.kinematics import chain_poses, gravity_in_sensors, sensor_poses
from armfusion.models.motion import MotionState, cross, link_motion, sensor_motion
from armfusion.models.rotations import GRAVITY_MPS2, R_from_rpy, exp_so3, up_from_tilt
from armfusion.models.sensor_kernels import magnetic_heading_one, specific_force_one, tilt_up

from tests.conftest import random_poses

# the former NumPy forms reached the compiled ones' numbers to the bit on this machine;
# a BLAS built another way may round a 3-term sum differently, hence a few ulp of slack
ATOL = 1e-13


def reference_chain(arm, q):
    """Forward kinematics as the batched NumPy form wrote it."""
    N, n = q.shape
    ch = arm.chain
    theta = q + ch.offset_rad
    R_0L, p_0L = np.empty((N, n + 1, 3, 3)), np.empty((N, n + 1, 3))
    axis_0, origin_0 = np.empty((N, n, 3)), np.empty((N, n, 3))
    R, p = np.broadcast_to(np.eye(3), (N, 3, 3)).copy(), np.zeros((N, 3))
    R_0L[:, 0], p_0L[:, 0] = R, p
    for i in range(n):
        p = p + R @ ch.p_pre_m[i]
        R = R @ ch.R_pre[i]
        axis_0[:, i], origin_0[:, i] = R @ ch.axis[i], p
        R = R @ exp_so3(ch.axis[i] * theta[:, i, None])
        p = p + R @ ch.p_post_m[i]
        R = R @ ch.R_post[i]
        R_0L[:, i + 1], p_0L[:, i + 1] = R, p
    return R_0L, p_0L, axis_0, origin_0


def reference_motion(arm, st):
    """The outward recursion as the batched NumPy form wrote it: link ω, ω̇, v, a."""
    R_0L, p_0L, axis_0, o_0 = reference_chain(arm, st.q_rad)
    w, wd, a = st.omega_B_rad_s.copy(), st.omega_dot_B_rad_s2.copy(), st.accel_B_mps2.copy()
    v = np.zeros_like(w)
    out = [(w, wd, v, a)]
    for i in range(arm.n_joints):
        r = o_0[:, i] - p_0L[:, i]
        wr = cross(w, r)
        v, a = v + wr, a + cross(wd, r) + cross(w, wr)
        z = axis_0[:, i]
        zqd = z * st.qd_rad_s[:, i, None]
        wd = wd + z * st.qdd_rad_s2[:, i, None] + cross(w, zqd)
        w = w + zqd
        r2 = p_0L[:, i + 1] - o_0[:, i]
        wr2 = cross(w, r2)
        v, a = v + wr2, a + cross(wd, r2) + cross(w, wr2)
        out.append((w, wd, v, a))
    om, al, ve, ac = (np.stack([o[k] for o in out], 1) for k in range(4))
    return R_0L, p_0L, om, al, ve, ac


def moving_state(arm, rng, N=300):
    """A moving arm on a turning, tilted, accelerating base."""
    n = arm.n_joints
    return MotionState(np.arange(N) * 0.01, random_poses(arm, N, rng), rng.normal(0, 1, (N, n)),
                       rng.normal(0, 3, (N, n)), R_from_rpy(*rng.normal(0, 0.2, (3, N))),
                       rng.normal(0, 0.5, (N, 3)), rng.normal(0, 2, (N, 3)), rng.normal(0, 1, (N, 3)), 25.0)


def tilted_axes(arm, rng):
    axes = [np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.3, 3) for _ in arm.joints]
    return replace(arm, joints=tuple(replace(j, axis=a / np.linalg.norm(a))
                                     for j, a in zip(arm.joints, axes, strict=True)))


@pytest.mark.parametrize("arm_name", ["wmra", "crs", "wmra-tilted-axes"])
def test_the_compiled_chain_gives_the_numpy_chain_s_frames(arm_name, request, rng):
    arm = request.getfixturevalue(arm_name.split("-")[0])
    if arm_name.endswith("tilted-axes"):
        arm = tilted_axes(arm, rng)
        assert not arm.chain.axis_is_z
    q = random_poses(arm, 300, rng)
    got = chain_poses(arm, q)
    for name, a, b in zip(("R_0L", "p_0L_m", "axis_0", "origin_0_m"),
                          (got.R_0L, got.p_0L_m, got.axis_0, got.origin_0_m), reference_chain(arm, q),
                          strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=ATOL, err_msg=name)


@pytest.mark.parametrize("arm_name", ["wmra", "crs"])
def test_the_compiled_recursion_and_sensors_give_the_numpy_motion(arm_name, request, rng):
    arm = request.getfixturevalue(arm_name)
    st = moving_state(arm, rng)
    lm = link_motion(arm, st)
    R_0L, p_0L, om, al, ve, ac = reference_motion(arm, st)
    for name, a, b in (("omega", lm.omega, om), ("alpha", lm.alpha, al), ("vel", lm.vel, ve),
                       ("acc", lm.acc, ac)):
        np.testing.assert_allclose(a, b, rtol=0, atol=ATOL, err_msg=name)
    # every sensor, on mounts an effect moved and turned
    names = list(arm.sensor_names)
    R_LS = np.stack([arm.sensor(s).R_LS for s in names]) @ R_from_rpy(0.1, -0.2, 0.3)
    p_LS = np.stack([arm.sensor(s).p_L_m for s in names]) + 0.01
    sm = sensor_motion(arm, st, names, R_LS, p_LS, lm=lm)
    links = np.array([arm.sensor(s).link for s in names])
    R_0S = R_0L[:, links] @ R_LS
    r = np.einsum("nsij,sj->nsi", R_0L[:, links], p_LS)
    w, wd = om[:, links], al[:, links]
    acc = ac[:, links] + cross(wd, r) + cross(w, cross(w, r))
    f = np.einsum("nsji,nsj->nsi", R_0S, acc + GRAVITY_MPS2 * st.up_0[:, None, :])
    for name, a, b in (("R_0S", sm.R_0S, R_0S), ("p_0S_m", sm.p_0S_m, p_0L[:, links] + r),
                       ("acc_0_mps2", sm.acc_0_mps2, acc), ("specific_force_mps2", sm.specific_force_mps2, f),
                       ("omega_S_rad_s", sm.omega_S_rad_s, np.einsum("nsji,nsj->nsi", R_0S, w))):
        np.testing.assert_allclose(a, b, rtol=0, atol=ATOL, err_msg=name)
    # the poses alone (no motion) are the same numbers as the poses of the motion
    R2, p2 = sensor_poses(arm, st.q_rad)
    sm_default = sensor_motion(arm, st, lm=lm)
    np.testing.assert_array_equal(R2, sm_default.R_0S)
    np.testing.assert_array_equal(p2, sm_default.p_0S_m)


def test_the_accelerometer_and_compass_equations(rng):
    """f = R^T (a + g up) with up from the tilt, and the compass's de-tilted heading, against
    the NumPy helpers of armfusion.models.rotations and a rotation built from the angles."""
    for roll, pitch, yaw in rng.uniform(-1.2, 1.2, (20, 3)):
        sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
        up = np.array(tilt_up(sr, cr, sp, cp))
        np.testing.assert_array_equal(up, up_from_tilt(roll, pitch))
        R = R_from_rpy(*rng.uniform(-3, 3, 3))
        a = rng.normal(0, 2, 3)
        f = np.array(specific_force_one(R, *a, *up, GRAVITY_MPS2))
        np.testing.assert_allclose(f, R.T @ (a + GRAVITY_MPS2 * up), rtol=0, atol=1e-14)
        # a field seen from a base at (roll, pitch, yaw) gives back that yaw
        B_W = np.array([24.0, 0.0, -39.0])
        m_B = R_from_rpy(roll, pitch, yaw).T @ B_W
        heading = magnetic_heading_one(*m_B, sr, cr, sp, cp)
        assert abs((heading - yaw + np.pi) % (2 * np.pi) - np.pi) < 1e-12


def test_mismatched_inputs_are_refused_with_their_shapes(wmra, rng):
    """The compiled loops index without bounds checks: what does not fit is refused first."""
    st = moving_state(wmra, rng, N=5)
    with pytest.raises(ValueError, match=r"mounts for 4 sensors must have shapes \(4, 3, 3\) and \(4, 3\), "
                                         r"got \(3, 3, 3\) and \(4, 3\)"):
        sensor_motion(wmra, st, R_LS=np.stack([np.eye(3)] * 3))
    with pytest.raises(ValueError, match="the link motion is of 5 instants, the state of 2"):
        sensor_motion(wmra, st.take(slice(0, 2)), lm=link_motion(wmra, st))
    with pytest.raises(ValueError, match="broadcast"):
        gravity_in_sensors(wmra, random_poses(wmra, 4, rng), up_0=np.ones((3, 3)))
