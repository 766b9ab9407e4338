"""Motion of the arm and its base, and the specific force every sensor feels.

An accelerometer reads specific force, ``f_S = R_WS^T (a_S - g)``: gravity plus whatever
the sensor point accelerates with. Here ``a_S`` comes from an analytic velocity and
acceleration propagation along the chain (the outward pass of recursive Newton-Euler),
batched over N instants; no finite differences. It contains

- the base's own linear acceleration (the chair accelerating, braking, bumping),
- the base's rotation (ω, ω̇: the chair turning, tilting onto a ramp),
- every joint's rate and acceleration: the centripetal (ω × (ω × r)) and tangential
  (ω̇ × r) terms at each sensor's lever arm r, and the Coriolis coupling between joints.

Everything is expressed in the arm base frame 0 (whose attitude in the world is
``R_WB``), as inertial quantities: ``omega`` is the angular velocity of a frame relative
to the world, written in frame-0 axes. Point velocities are relative to a frame that
translates with the base origin (the base's own velocity never changes a reading).

:class:`MotionState` is the input every measurement model takes; the Jacobians here are
with respect to the joint angles (``df/dq``, for the estimators and for chaining effect
parameters that act on joint angles) and to a sensor's position on its link.

The gravity torque on each joint (for link sag and gearbox play) is here too, from a
simple :class:`MassModel` (the arm configs carry no masses).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.chain_kernels import (
    chain_table,
    kernel_input,
    link_motion_batch,
    mount_table,
    sensor_motion_batch,
)
from armfusion.models.kinematics import chain_poses, sensor_indices
from armfusion.models.rotations import GRAVITY_MPS2, R_from_rpy, rpy_from_R


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis, broadcasting (faster than ``np.cross`` for small batches)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _vecT(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R^T @ v``."""
    return np.einsum("...ji,...j->...i", R, v)


# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MotionState:
    """The arm and its base at N instants: everything the sensors respond to.

    ================================  =========  ==================================================
    field                             shape      meaning
    ================================  =========  ==================================================
    ``t_s``                           (N,)       time, s
    ``q_rad``                         (N, n)     joint angles as the controller counts them (the
                                                 encoder side; effects may bend the geometric ones)
    ``qd_rad_s``, ``qdd_rad_s2``      (N, n)     joint rates and accelerations
    ``R_WB``                          (N, 3, 3)  attitude of the arm base (frame 0) in the world
                                                 (z up): ``Rz(yaw) Ry(pitch) Rx(roll)``
    ``omega_B_rad_s``                 (N, 3)     base angular velocity, in base axes
    ``omega_dot_B_rad_s2``            (N, 3)     its time derivative, in base axes
    ``accel_B_mps2``                  (N, 3)     linear acceleration of the base origin (gravity
                                                 not included), in base axes
    ``temperature_c``                 (N,)       temperature of the electronics, °C
    ================================  =========  ==================================================
    """

    t_s: np.ndarray
    q_rad: np.ndarray
    qd_rad_s: np.ndarray
    qdd_rad_s2: np.ndarray
    R_WB: np.ndarray
    omega_B_rad_s: np.ndarray
    omega_dot_B_rad_s2: np.ndarray
    accel_B_mps2: np.ndarray
    temperature_c: np.ndarray

    def __post_init__(self) -> None:
        q = np.asarray(self.q_rad, dtype=float)
        if q.ndim == 1:
            q = q[None, :]
        if q.ndim != 2:
            raise ValueError(f"MotionState: q_rad must have shape (N, n), got {q.shape}")
        N, n = q.shape
        want = {
            "t_s": (N,), "qd_rad_s": (N, n), "qdd_rad_s2": (N, n), "R_WB": (N, 3, 3),
            "omega_B_rad_s": (N, 3), "omega_dot_B_rad_s2": (N, 3), "accel_B_mps2": (N, 3),
            "temperature_c": (N,),
        }
        object.__setattr__(self, "q_rad", q)
        for name, shape in want.items():
            a = np.asarray(getattr(self, name), dtype=float)
            try:
                a = np.broadcast_to(a, shape)
            except ValueError:
                raise ValueError(
                    f"MotionState: {name} must have shape {shape} (or broadcast to it), got {a.shape}"
                ) from None
            object.__setattr__(self, name, a)

    # -- views -------------------------------------------------------------------------
    @property
    def N(self) -> int:
        return int(self.q_rad.shape[0])

    @property
    def n_joints(self) -> int:
        return int(self.q_rad.shape[1])

    @property
    def up_0(self) -> np.ndarray:
        """World up expressed in the base frame, ``(N, 3)``: ``R_WB^T e_z``."""
        return self.R_WB[:, 2, :]

    @property
    def rpy_rad(self) -> np.ndarray:
        """Base roll, pitch, yaw ``(N, 3)``."""
        return rpy_from_R(self.R_WB)

    def take(self, idx) -> MotionState:
        """The instants ``idx`` (an index array or a slice)."""
        return MotionState(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    def replace(self, **changes) -> MotionState:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(changes)
        return MotionState(**d)

    @property
    def is_static(self) -> bool:
        return not (np.any(self.qd_rad_s) or np.any(self.qdd_rad_s2) or np.any(self.omega_B_rad_s)
                    or np.any(self.omega_dot_B_rad_s2) or np.any(self.accel_B_mps2))

    # -- constructors ------------------------------------------------------------------
    @classmethod
    def static(
        cls, q_rad, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, temperature_c=25.0, t_s=None
    ) -> MotionState:
        """Arm and base at rest: poses ``q_rad (N, n)``, base tilt per instant or shared."""
        q = np.asarray(q_rad, dtype=float)
        q = q[None, :] if q.ndim == 1 else q
        N = q.shape[0]
        R = R_from_rpy(*(np.broadcast_to(np.asarray(a, dtype=float), (N,))
                         for a in (roll_rad, pitch_rad, yaw_rad)))
        z = np.zeros_like(q)
        t = np.arange(N, dtype=float) if t_s is None else t_s
        return cls(t, q, z, z, R, np.zeros((N, 3)), np.zeros((N, 3)), np.zeros((N, 3)),
                   temperature_c)

    @classmethod
    def from_samples(
        cls, t_s, q_rad, rpy_rad=None, accel_B_mps2=0.0, temperature_c=25.0
    ) -> MotionState:
        """From sampled joint angles (and base attitude), rates by finite differences.

        For measured data (encoders, an attitude estimate): ``np.gradient`` gives joint
        rates and accelerations and the base's angular velocity; the base's linear
        acceleration must be given (zero by default).
        """
        t = np.asarray(t_s, dtype=float)
        q = np.asarray(q_rad, dtype=float)
        N = t.shape[0]
        qd = np.gradient(q, t, axis=0) if N > 2 else np.zeros_like(q)
        qdd = np.gradient(qd, t, axis=0) if N > 2 else np.zeros_like(q)
        rpy = np.zeros((N, 3)) if rpy_rad is None else np.broadcast_to(np.asarray(rpy_rad, float), (N, 3))
        R = R_from_rpy(rpy[:, 0], rpy[:, 1], rpy[:, 2])
        if N > 2:
            rpy_u = np.unwrap(rpy, axis=0)
            d1 = np.gradient(rpy_u, t, axis=0)
            d2 = np.gradient(d1, t, axis=0)
            w, wd = body_rates_from_rpy(rpy, d1, d2)
        else:
            w = wd = np.zeros((N, 3))
        return cls(t, q, qd, qdd, R, w, wd, accel_B_mps2, temperature_c)


def body_rates_from_rpy(rpy: np.ndarray, rpy_d: np.ndarray, rpy_dd: np.ndarray):
    """Body angular velocity and acceleration of ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    From the angles ``(N, 3)`` and their first and second time derivatives:
    ``ω_B = [φ' - ψ' sθ, θ' cφ + ψ' cθ sφ, -θ' sφ + ψ' cθ cφ]`` (φ roll, θ pitch, ψ yaw)
    and its exact time derivative. Returns ``(omega_B (N, 3), omega_dot_B (N, 3))``.
    """
    ph, th = rpy[..., 0], rpy[..., 1]
    dph, dth, dps = rpy_d[..., 0], rpy_d[..., 1], rpy_d[..., 2]
    ddph, ddth, ddps = rpy_dd[..., 0], rpy_dd[..., 1], rpy_dd[..., 2]
    sph, cph, sth, cth = np.sin(ph), np.cos(ph), np.sin(th), np.cos(th)
    w = np.stack([dph - dps * sth,
                  dth * cph + dps * cth * sph,
                  -dth * sph + dps * cth * cph], -1)
    wd = np.stack([
        ddph - ddps * sth - dps * cth * dth,
        ddth * cph - dth * sph * dph + ddps * cth * sph - dps * sth * dth * sph + dps * cth * cph * dph,
        -ddth * sph - dth * cph * dph + ddps * cth * cph - dps * sth * dth * cph - dps * cth * sph * dph,
    ], -1)
    return w, wd


# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LinkMotion:
    """Every link frame's pose and motion, in base axes, batched over N.

    Index 0 is the base (link 0), index k link k: ``R_0L (N, n+1, 3, 3)``,
    ``p_0L_m``, ``omega`` (angular velocity), ``alpha`` (angular acceleration),
    ``vel`` (velocity of the frame origin relative to the base origin's translation) and
    ``acc`` (inertial acceleration of the frame origin, without gravity), each
    ``(N, n+1, 3)``. Per joint j: ``axis_0``, ``origin_0_m`` and the velocity and
    acceleration of that origin (``vel_origin``, ``acc_origin``), ``(N, n, 3)``. Joint j's
    origin lies on its axis, fixed in both links it joins; link j+1 (index j+1) turns
    with ``omega[:, j+1]``.
    """

    R_0L: np.ndarray
    p_0L_m: np.ndarray
    omega: np.ndarray
    alpha: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    axis_0: np.ndarray
    origin_0_m: np.ndarray
    vel_origin: np.ndarray
    acc_origin: np.ndarray


def _as_state(arm: ArmModel, state: MotionState) -> MotionState:
    if state.n_joints != arm.n_joints:
        raise ValueError(
            f"joint angles must have shape (N, {arm.n_joints}) for arm {arm.name!r}, "
            f"got {state.q_rad.shape}"
        )
    return state


def link_motion(arm: ArmModel, state: MotionState) -> LinkMotion:
    """Outward recursion: pose, angular velocity and acceleration, and the linear velocity
    and acceleration of every link origin and joint origin, batched over N instants (the
    compiled :func:`armfusion.models.chain_kernels.pose_one` and :func:`armfusion.models.chain_kernels.motion_one`
    at each instant).

    For joint i with axis z (base axes) at origin o (fixed in link i-1):
    ``ω_i = ω_{i-1} + z q̇``, ``ω̇_i = ω̇_{i-1} + z q̈ + ω_{i-1} x z q̇``, and any point P
    fixed in a link at lever arm r from a point O of the same link:
    ``a_P = a_O + ω̇ x r + ω x (ω x r)``.
    """
    state = _as_state(arm, state)
    c = kernel_input
    R_0L, p_0L, om, al, ve, ac, axis_0, o_0, v_o, a_o = link_motion_batch(
        c(state.q_rad), c(state.qd_rad_s), c(state.qdd_rad_s2), c(state.omega_B_rad_s),
        c(state.omega_dot_B_rad_s2), c(state.accel_B_mps2), chain_table(arm), bool(arm.chain.axis_is_z))
    return LinkMotion(R_0L, p_0L, om, al, ve, ac, axis_0, o_0, v_o, a_o)


# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SensorMotion:
    """Each sensor's pose and motion, ``(N, S, ...)``, for the sensors ``names``.

    ``specific_force_mps2`` is what an ideal accelerometer there reads, in its own axes
    (m/s²): ``R_0S^T (a_S + g·up_0)``; ``omega_S_rad_s`` what an ideal gyro reads.
    ``acc_0_mps2`` and ``vel_0_mps`` are the sensor point's acceleration (without
    gravity) and relative velocity in base axes.
    """

    names: tuple[str, ...]
    links: np.ndarray  # (S,) link index of each sensor
    R_0S: np.ndarray
    p_0S_m: np.ndarray
    vel_0_mps: np.ndarray
    acc_0_mps2: np.ndarray
    specific_force_mps2: np.ndarray
    omega_S_rad_s: np.ndarray

    @property
    def specific_force_g(self) -> np.ndarray:
        return self.specific_force_mps2 / GRAVITY_MPS2


def _mounts(arm: ArmModel, idx: list[int], R_LS=None, p_LS_m=None):
    links = np.array([arm.sensors[i].link for i in idx], dtype=np.int64)
    R = np.stack([arm.sensors[i].R_LS for i in idx]) if R_LS is None else np.asarray(R_LS, float)
    p = np.stack([arm.sensors[i].p_L_m for i in idx]) if p_LS_m is None else np.asarray(p_LS_m, float)
    return links, R, p


def sensor_motion(
    arm: ArmModel,
    state: MotionState,
    names=None,
    R_LS: np.ndarray | None = None,
    p_LS_m: np.ndarray | None = None,
    lm: LinkMotion | None = None,
) -> SensorMotion:
    """Pose, motion and ideal readings of the sensors ``names`` (default: the link
    accelerometers, config order). ``R_LS (S, 3, 3)`` and ``p_LS_m (S, 3)`` override the
    configured mounts (an effect that moves or turns a sensor on its link). The compiled
    :func:`armfusion.models.chain_kernels.sensor_one` at each instant and sensor (its docstring and
    :func:`armfusion.models.sensor_kernels.specific_force_one` have the equations)."""
    lm = link_motion(arm, state) if lm is None else lm
    idx = sensor_indices(arm, names)
    names = tuple(arm.sensors[i].name for i in idx)
    links, R_LS, p_LS = _mounts(arm, idx, R_LS, p_LS_m)
    S, N = len(idx), state.N
    if R_LS.shape != (S, 3, 3) or p_LS.shape != (S, 3):
        raise ValueError(f"sensor_motion: mounts for {S} sensors must have shapes ({S}, 3, 3) and ({S}, 3), "
                         f"got {R_LS.shape} and {p_LS.shape}")
    if lm.R_0L.shape != (N, arm.n_joints + 1, 3, 3):
        raise ValueError(f"sensor_motion: the link motion is of {lm.R_0L.shape[0]} instants, "
                         f"the state of {N}")
    c = kernel_input
    R_0S, p_0S, vel, acc, f, om = sensor_motion_batch(
        c(lm.R_0L), c(lm.p_0L_m), c(lm.omega), c(lm.alpha), c(lm.vel), c(lm.acc), c(links, np.int64),
        mount_table(R_LS, p_LS), c(state.up_0), float(GRAVITY_MPS2))
    return SensorMotion(names, links, R_0S, p_0S, vel, acc, f, om)


def specific_force(arm: ArmModel, state: MotionState, names=None) -> np.ndarray:
    """What ideal accelerometers read, in g, ``(N, S, 3)``, motion included.

    For a state at rest this equals :func:`armfusion.models.kinematics.gravity_in_sensors`.
    """
    return sensor_motion(arm, state, names).specific_force_g


def specific_force_jacobian(
    arm: ArmModel, state: MotionState, names=None, lm: LinkMotion | None = None,
    sm: SensorMotion | None = None,
) -> np.ndarray:
    """Analytic ``df/dq`` of the sensors' specific force, in g per rad, ``(N, S, 3, n)``,
    motion terms included (joint rates and accelerations held fixed).

    Turning joint j by ε turns everything beyond it about its axis z_j through its origin
    o_j, together with the velocities and accelerations relative to link j; link j's own
    ω_j, ω̇_j and a(o_j) do not change. With ``r = P - o_j`` and the sensor's velocity
    ``v_rel`` and acceleration ``a_rel`` relative to link j,

        da_P/dq_j = ω̇_j x (z x r) + ω_j x (ω_j x (z x r)) + 2 ω_j x (z x v_rel) + z x a_rel
        df/dq_j   = R_0S^T (da_P/dq_j - z x (a_P + g·up_0)) / g

    which reduces to :func:`armfusion.models.kinematics.gravity_jacobian` at rest.
    """
    lm = link_motion(arm, state) if lm is None else lm
    sm = sensor_motion(arm, state, names, lm=lm) if sm is None else sm
    N, S = sm.p_0S_m.shape[:2]
    n = arm.n_joints
    J = np.zeros((N, S, 3, n))
    s_tot = sm.acc_0_mps2 + GRAVITY_MPS2 * state.up_0[:, None, :]  # (N, S, 3)
    for j in range(n):
        on = sm.links > j  # sensors beyond joint j
        if not np.any(on):
            continue
        z = lm.axis_0[:, j][:, None, :]
        o = lm.origin_0_m[:, j][:, None, :]
        w = lm.omega[:, j + 1][:, None, :]
        wd = lm.alpha[:, j + 1][:, None, :]
        vo = lm.vel_origin[:, j][:, None, :]
        ao = lm.acc_origin[:, j][:, None, :]
        P, vP, aP = sm.p_0S_m[:, on], sm.vel_0_mps[:, on], sm.acc_0_mps2[:, on]
        r = P - o
        wr = cross(w, r)
        v_rel = vP - vo - wr
        a_rel = aP - ao - cross(wd, r) - cross(w, wr) - 2.0 * cross(w, v_rel)
        zr = cross(z, r)
        da = cross(wd, zr) + cross(w, cross(w, zr)) + 2.0 * cross(w, cross(z, v_rel)) + cross(z, a_rel)
        ds = da - cross(z, s_tot[:, on])
        Jj = np.zeros((N, S, 3))
        Jj[:, on] = _vecT(sm.R_0S[:, on], ds)
        J[..., j] = Jj
    return J / GRAVITY_MPS2


def lever_arm_jacobian(sm: SensorMotion, lm: LinkMotion) -> np.ndarray:
    """``df/dp_LS``: how each sensor's reading (g) changes as it moves on its link (m),
    ``(N, S, 3, 3)`` = ``R_0S^T ([ω̇]x + [ω]x²) R_0L / g``. Zero when nothing turns."""
    R_0L = lm.R_0L[:, sm.links]
    w, wd = lm.omega[:, sm.links], lm.alpha[:, sm.links]
    # columns: the effect of a unit move along each link axis
    cols = np.swapaxes(R_0L, -1, -2)  # (N, S, 3 [col], 3 [vec])
    w_ = w[:, :, None, :]
    d = cross(wd[:, :, None, :], cols) + cross(w_, cross(w_, cols))  # (N, S, col, 3)
    out = np.einsum("nsji,nscj->nsic", sm.R_0S, d)
    return out / GRAVITY_MPS2


# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MassModel:
    """A nominal mass distribution, for gravity torques (link sag, gearbox play).

    The arm configs carry no masses, so the arm is modelled as: every link a uniform rod
    from its joint's origin to the next joint's origin (``link_kg_per_m``), a motor at
    every joint but the first (``motor_kg``, carried by the link before it), and a gripper
    and payload at the flange (``payload_kg``). The defaults give the WMRA about 14 kg.
    Effects that use the torque (``link_compliance``) estimate a stiffness per joint, so
    an error in the overall scale of these masses is absorbed by the estimate.
    """

    link_kg_per_m: float = 4.0
    motor_kg: float = 1.0
    payload_kg: float = 1.0

    def points(self, arm: ArmModel, lm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point masses: positions ``(N, M, 3)`` in base axes, masses ``(M,)`` kg, links ``(M,)``."""
        n = arm.n_joints
        pos, mass, link = [], [], []
        p_0L, o = lm.p_0L_m, lm.origin_0_m
        for k in range(1, n + 1):
            start = o[:, k - 1]
            end = o[:, k] if k < n else p_0L[:, n]
            length = float(np.linalg.norm(end[0] - start[0]))
            if length > 0:
                pos.append(0.5 * (start + end))
                mass.append(self.link_kg_per_m * length)
                link.append(k)
            if k < n and self.motor_kg > 0:
                pos.append(end)
                mass.append(self.motor_kg)
                link.append(k)
        if self.payload_kg > 0:
            pos.append(p_0L[:, n])
            mass.append(self.payload_kg)
            link.append(n)
        return np.stack(pos, 1), np.array(mass), np.array(link)


DEFAULT_MASSES = MassModel()


def gravity_torques(
    arm: ArmModel, q_rad: np.ndarray, up_0: np.ndarray | None = None,
    masses: MassModel = DEFAULT_MASSES, jacobian: bool = False,
):
    """Static gravity torque about every joint axis, N·m, ``(N, n)`` (and ``dτ/dq (N, n, n)``).

    ``τ_j = z_j · ((C_j - M_j o_j) x g)`` with ``C_j``, ``M_j`` the first moment and total of
    the masses beyond joint j. Positive τ turns the joint the positive way. Derivatives:
    for i <= j, turning joint i turns z_j, o_j and those masses together:
    ``dτ_j/dq_i = g · (z_i x (z_j x (C_j - M_j o_j)))``; for i > j only masses beyond i
    move: ``dτ_j/dq_i = z_j · ((z_i x (C_i - M_i o_i)) x g)``.
    """
    poses = chain_poses(arm, q_rad)
    N, n = poses.axis_0.shape[:2]
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0]) if up_0 is None else np.asarray(up_0, float), (N, 3))
    g = -GRAVITY_MPS2 * up
    pos, m, links = masses.points(arm, poses)
    C = np.empty((N, n, 3))
    Mtot = np.empty(n)
    for j in range(n):
        sel = links > j
        Mtot[j] = m[sel].sum()
        C[:, j] = np.einsum("nmi,m->ni", pos[:, sel], m[sel])
    z, o = poses.axis_0, poses.origin_0_m
    rel = C - Mtot[None, :, None] * o  # (N, n, 3)
    tau = np.einsum("nji,nji->nj", z, cross(rel, g[:, None, :]))
    if not jacobian:
        return tau
    dtau = np.zeros((N, n, n))
    for j in range(n):
        zj_rel = cross(z[:, j], rel[:, j])
        for i in range(n):
            if i <= j:
                dtau[:, j, i] = np.einsum("ni,ni->n", g, cross(z[:, i], zj_rel))
            else:
                dtau[:, j, i] = np.einsum("ni,ni->n", z[:, j], cross(cross(z[:, i], rel[:, i]), g))
    return tau, dtau
