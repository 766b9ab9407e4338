"""Batched forward kinematics and gravity Jacobians.

Every function takes joint angles ``q_rad`` of shape ``(N, n)`` (N samples or sigma
points; a single pose is N = 1). The chain and the sensors' poses and still readings are
the compiled one-pose equations of :mod:`armfusion.models.chain_kernels` and
:mod:`armfusion.models.sensor_kernels`, looped over N in compiled code; the rest is NumPy over N.

Conventions: frame 0 is the arm base. ``up_0`` is the world "up" direction expressed
in frame 0 (unit); at rest an accelerometer reads specific force ``f_S = R_0S^T up_0``
in g (it opposes gravity), so "gravity in the sensor frame" below is that reading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.chain_kernels import (
    chain_poses_batch,
    chain_table,
    kernel_input,
    mount_table,
    sensor_poses_batch,
)
from armfusion.models.gravity_kernels import propagate
from armfusion.models.rotations import skew
from armfusion.models.sensor_kernels import still_readings_batch


@dataclass(frozen=True)
class ChainPoses:
    """Every link frame in the base frame: ``R_0L (N, n+1, 3, 3)``, ``p_0L_m (N, n+1, 3)``,
    and every joint's axis and origin in the base frame: ``axis_0 (N, n, 3)``, ``origin_0_m``."""

    R_0L: np.ndarray
    p_0L_m: np.ndarray
    axis_0: np.ndarray
    origin_0_m: np.ndarray


def _as_q(arm: ArmModel, q_rad: np.ndarray) -> np.ndarray:
    q = np.asarray(q_rad, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != arm.n_joints:
        raise ValueError(
            f"joint angles must have shape (N, {arm.n_joints}) for arm {arm.name!r}, got {q.shape}"
        )
    return q


def chain_poses(arm: ArmModel, q_rad: np.ndarray) -> ChainPoses:
    """Forward kinematics of every link frame, batched over N poses (the compiled
    :func:`armfusion.models.chain_kernels.pose_one` at each pose: its docstring has the equation)."""
    q = kernel_input(_as_q(arm, q_rad))
    return ChainPoses(*chain_poses_batch(q, chain_table(arm), bool(arm.chain.axis_is_z)))


def forward_kinematics(arm: ArmModel, q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the last link (flange): ``R_0n (N, 3, 3)``, ``p_0n_m (N, 3)``."""
    poses = chain_poses(arm, q_rad)
    return poses.R_0L[:, -1], poses.p_0L_m[:, -1]


def sensor_indices(arm: ArmModel, names: list[str] | tuple[str, ...] | None) -> list[int]:
    if names is None:
        return [i for i, s in enumerate(arm.sensors) if s.is_link_accelerometer]
    lookup = {s.name: i for i, s in enumerate(arm.sensors)}
    out = []
    for name in names:
        if name not in lookup:
            raise KeyError(f"arm {arm.name!r} has no sensor {name!r}; it has {list(lookup)}")
        out.append(lookup[name])
    return out


def _mount_arrays(arm: ArmModel, names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Links ``(S,)``, rotations ``R_LS (S, 3, 3)`` and positions ``(S, 3)`` of the named
    sensors, stacked once per arm and name list."""
    cache = arm.__dict__.setdefault("_mount_cache", {})
    key = None if names is None else tuple(names)
    hit = cache.get(key)
    if hit is None:
        idx = sensor_indices(arm, names)
        hit = (np.array([arm.sensors[i].link for i in idx], dtype=np.int64),
               np.stack([arm.sensors[i].R_LS for i in idx]),
               np.stack([arm.sensors[i].p_L_m for i in idx]))
        cache[key] = hit
    return hit


def _mount_table(arm: ArmModel, names, R_LS: np.ndarray, p_LS: np.ndarray) -> np.ndarray:
    """:func:`armfusion.models.chain_kernels.mount_table` of the named sensors, made once per arm and
    name list."""
    cache = arm.__dict__.setdefault("_mount_table_cache", {})
    key = None if names is None else tuple(names)
    hit = cache.get(key)
    if hit is None:
        hit = cache[key] = mount_table(R_LS, p_LS)
    return hit


def sensor_poses(
    arm: ArmModel, q_rad: np.ndarray, names=None, poses: ChainPoses | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Each sensor's rotation ``R_0S (N, S, 3, 3)`` and position ``p_0S_m (N, S, 3)``.

    ``names`` defaults to the link accelerometers, in config order.
    """
    poses = chain_poses(arm, q_rad) if poses is None else poses
    links, R_LS, p_LS = _mount_arrays(arm, names)
    mounts = _mount_table(arm, names, R_LS, p_LS)
    c = kernel_input
    return sensor_poses_batch(c(poses.R_0L), c(poses.p_0L_m), c(links, np.int64), mounts)


def gravity_in_sensors(
    arm: ArmModel, q_rad: np.ndarray, up_0: np.ndarray | None = None, names=None
) -> np.ndarray:
    """Static specific force each sensor reads, in g: ``f_S = R_0S^T up_0``, ``(N, S, 3)``
    (:func:`armfusion.models.sensor_kernels.still_readings_batch`).

    ``up_0`` is world-up in the base frame, shape ``(3,)`` or ``(N, 3)``; default level base.
    """
    R_0S, _ = sensor_poses(arm, q_rad, names)
    return still_readings_batch(kernel_input(R_0S), _as_up(up_0, R_0S.shape[0]))


def _as_up(up_0, N: int) -> np.ndarray:
    """World-up ``(N, 3)``, a kernel input: ``up_0`` of shape ``(3,)``, ``(1, 3)`` or ``(N, 3)``
    (anything else is refused by the broadcast), default z."""
    up = np.array([0.0, 0.0, 1.0]) if up_0 is None else np.asarray(up_0, dtype=float)
    return kernel_input(np.broadcast_to(up, (N, 3)))


def gravity_jacobian(
    arm: ArmModel, q_rad: np.ndarray, up_0: np.ndarray | None = None, names=None,
    with_frames: bool = False,
):
    """Static specific force ``f (N, S, 3)`` and its analytic Jacobian ``df/dq (N, S, 3, n)``
    (and the sensor rotations ``R_0S (N, S, 3, 3)`` with ``with_frames``).

    Turning joint j rotates every frame after it about the joint axis ``a_j`` (base frame):
    ``dR_0S/dq_j = [a_j]x R_0S``, hence ``df_S/dq_j = R_0S^T (up_0 x a_j)`` for joints on
    the sensor's side of the chain and zero for joints beyond its link.
    """
    poses = chain_poses(arm, q_rad)
    R_0S, _ = sensor_poses(arm, q_rad, names, poses=poses)
    N, S = R_0S.shape[:2]
    up = _as_up(up_0, N)
    f = still_readings_batch(kernel_input(R_0S), up)
    a = poses.axis_0
    u = up[:, None, :]
    cross = np.stack([u[..., 1] * a[..., 2] - u[..., 2] * a[..., 1],
                      u[..., 2] * a[..., 0] - u[..., 0] * a[..., 2],
                      u[..., 0] * a[..., 1] - u[..., 1] * a[..., 0]], -1)  # (N, n, 3): up x a_j
    J = np.einsum("nsji,nkj->nsik", R_0S, cross)  # (N, S, 3, n)
    links = _mount_arrays(arm, names)[0]
    mask = np.arange(arm.n_joints)[None, :] < links[:, None]  # (S, n)
    J = J * mask[None, :, None, :]
    return (f, J, R_0S) if with_frames else (f, J)


def joint_axis_angle_to_vertical(arm: ArmModel, q_rad: np.ndarray, up_0=None) -> np.ndarray:
    """Angle in rad between each joint axis and the vertical, folded to [0, pi/2]: ``(N, n)``.

    Zero means the axis is parallel to gravity: turning that joint does not change what
    any accelerometer reads (gimbal lock for that joint).
    """
    poses = chain_poses(arm, q_rad)
    up = _as_up(up_0, poses.axis_0.shape[0])
    c = np.abs(np.einsum("nkj,nj->nk", poses.axis_0, up))
    return np.arccos(np.clip(c, 0.0, 1.0))


def dependency_matrix(arm: ArmModel, names=None) -> np.ndarray:
    """Boolean ``(S, n)``: which joints each sensor's reading depends on."""
    idx = sensor_indices(arm, names)
    links = np.array([arm.sensors[i].link for i in idx])
    return np.arange(arm.n_joints)[None, :] < links[:, None]


# --------------------------------------------------------------------------------------
# gravity carried down the chain: readings and Jacobian for many still poses at once
def _z_onto(axis: np.ndarray) -> np.ndarray:
    """A rotation ``P`` with ``P @ z = axis`` (unit axis)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    c = float(a[2])
    if c < -1.0 + 1e-12:  # a = -z: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    k = np.array([-a[1], a[0], 0.0])  # z x a, of length sin(angle)
    K = skew(k)
    return np.eye(3) + K + K @ K / (1.0 + c)


@dataclass(frozen=True)
class GravityChain:
    """The constant frame changes that carry world-up from the base to every sensor.

    Only rotations matter to what a still accelerometer reads. Each joint turns about its
    own axis; a constant change of frame ``P_i`` (``P_i z = axis_i``) makes that axis z,
    so going through joint i is ``v <- Rz(theta_i)^T C_i v`` with a constant ``C_i``, and
    ``v`` is world-up in joint i's axis frame after its turn. The sensor on link k reads
    ``D_s v`` with ``v`` taken after joint k-1 (``D_s`` constant; up itself for link 0).

    Turning joint i changes ``v`` there by ``v x z``; every later step is linear in ``v``,
    so a derivative column is carried by the same steps as ``v`` itself. One pass gives the
    readings and their exact Jacobian (the same as :func:`gravity_jacobian`'s).
    """

    step_in: np.ndarray  # (n, 3, 3) C_i: previous joint's axis frame -> joint i's, before its turn
    read_out: np.ndarray  # (S, 3, 3) D_s: the axis frame of joint link_s - 1 -> the sensor frame
    links: np.ndarray  # (S,) the link each sensor is on (0: the base)
    offset_rad: np.ndarray  # (n,)

    @property
    def n(self) -> int:
        return len(self.offset_rad)

    def propagate(self, q_rad: np.ndarray, seed: np.ndarray, upto_joint: int | None = None):
        """Carry ``seed (N, 3, E)`` (up in the base frame, then its derivatives by E - 1 outer
        parameters) through the joints: ``V (N, 3, 1 + n + E - 1)`` before joint 0 (index 0)
        and after each joint i (index i + 1), columns [up, d/dq_0..q_{n-1}, outer]; stacked,
        ``(last + 2, N, 3, n + E)``. ``upto_joint``: stop after that joint (``last``;
        default the last joint). The compiled core is :func:`armfusion.models.gravity_kernels.propagate`."""
        q = np.ascontiguousarray(q_rad, dtype=float)
        last = q.shape[1] - 1 if upto_joint is None else upto_joint
        return propagate(q, np.ascontiguousarray(seed, dtype=float), self.step_in,
                         self.offset_rad, int(last))

    def axis_up_cos(self, q_rad: np.ndarray, up_0: np.ndarray) -> np.ndarray:
        """Cosine of the angle between every joint's axis and up: ``(N, n)`` (z of up in the
        joint's axis frame)."""
        q = np.ascontiguousarray(q_rad, dtype=float)
        up = np.broadcast_to(np.asarray(up_0, float), (len(q), 3))[:, :, None]
        return self.propagate(q, up)[1:, :, 2, 0].T


def gravity_chain(arm: ArmModel, names=None) -> GravityChain:
    """The :class:`GravityChain` of the named sensors (default: the link accelerometers),
    built once per arm and name list."""
    cache = arm.__dict__.setdefault("_gravity_chain_cache", {})
    key = None if names is None else tuple(names)
    hit = cache.get(key)
    if hit is None:
        ch = arm.chain
        n = arm.n_joints
        P = np.stack([_z_onto(ch.axis[i]) for i in range(n)])
        # frame before joint i's turn, in joint i-1's axis frame after its turn:
        # R_pre_0 P_0 from the base; P_{i-1}^T R_post_{i-1} R_pre_i P_i after
        K = np.empty((n, 3, 3))
        K[0] = ch.R_pre[0] @ P[0]
        for i in range(1, n):
            K[i] = P[i - 1].T @ ch.R_post[i - 1] @ ch.R_pre[i] @ P[i]
        links, R_LS, _ = _mount_arrays(arm, names)
        D = np.empty((len(links), 3, 3))
        for s_, k in enumerate(links):
            D[s_] = R_LS[s_].T if k == 0 else (P[k - 1].T @ ch.R_post[k - 1] @ R_LS[s_]).T
        hit = GravityChain(np.ascontiguousarray(np.swapaxes(K, -1, -2)), D, links.copy(),
                           np.asarray(ch.offset_rad, float).copy())
        cache[key] = hit
    return hit


def joint_rate_from_link_rates(arm: ArmModel, joint: int, omega_before: np.ndarray,
                               omega_after: np.ndarray) -> np.ndarray:
    """The rate (rad/s) of joint ``joint`` (0-based) from the angular rates of the links on
    either side of it, each in its own frame (``(N, 3)`` rad/s: link ``joint`` before it,
    link ``joint + 1`` after it; link 0 is the base): what a gyroscope on each side gives
    where an encoder is not trusted. With ``T_pre·Rot(axis, q)·T_post`` the joint's transform,
    ``ω_after = R^T ω_before + q̇ R_post^T axis``, so ``q̇ = axis·(R_post ω_after −
    R_pre^T ω_before)``, whatever the joint's angle."""
    j = arm.joints[joint]
    a = np.asarray(j.axis, float)
    return (np.asarray(omega_after, float) @ j.R_post.T - np.asarray(omega_before, float) @ j.R_pre) @ a
