"""Stages 1-4 of a model's prediction for one motion state (:mod:`armfusion.models.effects.model`):
the joint effects, the mounts, the kinematics and the sensor effects, with each stream's
Jacobian w.r.t. the wanted parameter blocks accumulated forward through the same stages
(:class:`StreamJac`). The time stage and the counts are the model's own.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.effects.base import (
    Context,
    Effect,
    JointEffect,
    MountEffect,
    SensorEffect,
    TimeEffect,
)
from armfusion.models.motion import (
    MassModel,
    MotionState,
    link_motion,
    sensor_motion,
    specific_force_jacobian,
)
from armfusion.sensors.samples import link_gyro_stream


class Stages:
    """A model's effects sorted into the pipeline's stages (each stage's by rank), and the
    stages 1-4 run for one motion state."""

    def __init__(self, arm: ArmModel, effects: Sequence[Effect], masses: MassModel,
                 earth_field_W_ut: np.ndarray):
        self.arm = arm
        self.masses = masses
        self.earth_field_W_ut = earth_field_W_ut

        def ordered(cls):
            return sorted((e for e in effects if isinstance(e, cls)), key=lambda e: e.rank)

        self.joint_effects: list[JointEffect] = ordered(JointEffect)
        self.mount_effects: list[MountEffect] = ordered(MountEffect)
        self.sensor_effects: list[SensorEffect] = ordered(SensorEffect)
        self.time_effects: list[TimeEffect] = ordered(TimeEffect)

    def prepare(self, state: MotionState, th, streams, want):
        """Stages 1-3: joint effects, mounts, kinematics. Returns the context, the joint
        blocks' ``d q_geom[j] / dθ`` as ``{block: (j, (N, p))}`` and (when Jacobians are
        wanted) ``df/dq_geom``."""
        arm = self.arm
        ctx = Context(arm, state, self.masses, self.earth_field_W_ut)
        want_jac = want is not None
        # 1. joints
        # d q_geom / dθ per wanted joint block: (the joints it moves, (N, joints, p))
        Jq: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        link_acc = {s.name for s in arm.link_accelerometers}
        geometric = any(s in link_acc for s in streams) or "imu_mag" in streams
        joint_stage = bool(self.joint_effects) and geometric
        if joint_stage:
            Jq = apply_joint_effects(self.joint_effects, state, th, ctx, want)
        # 2. mounts, 3. kinematics
        sensors = [s for s in streams if s in link_acc]
        imu = arm.imu
        if imu is not None and any(s in ("imu_acc", "imu_gyro", "imu_mag") for s in streams):
            sensors.append(imu.name)
        dfdq = None
        if sensors:
            R_LS = np.stack([arm.sensor(s).R_LS for s in sensors])
            p_LS = np.stack([arm.sensor(s).p_L_m for s in sensors]).copy()
            for e in self.mount_effects:
                if e.target in sensors:
                    i = sensors.index(e.target)
                    R_LS[i], p_LS[i] = e.apply_mount(R_LS[i], p_LS[i], th[e.block_name])
            gstate = state.replace(q_rad=ctx.q_geom) if joint_stage else state
            ctx.lm = link_motion(arm, gstate)
            ctx.sm = sensor_motion(arm, gstate, sensors, R_LS, p_LS, lm=ctx.lm)
            ctx.sensor_index = {s: i for i, s in enumerate(sensors)}
            if want_jac and Jq and any(s in link_acc for s in sensors):
                dfdq = specific_force_jacobian(arm, gstate, sensors, ctx.lm, ctx.sm)
        return ctx, Jq, dfdq

    def blocks_reaching(self, s: str, want, Jq, time_block: str | None,
                         rate_block: str | None = None) -> list[tuple[str, int]]:
        """The wanted blocks that reach stream ``s``, in the order they enter the pipeline."""
        arm = self.arm
        link_acc = {m.name: m for m in arm.link_accelerometers}
        out: list[tuple[str, int]] = []
        sensor = s if s in link_acc else (arm.imu.name if s == "imu_acc" else None)
        disturbed = s == "imu_mag" and any(e.name == "mag_arm_disturbance" for e in self.sensor_effects)
        moved_by_q = (s in link_acc and link_acc[s].link > 0) or disturbed
        if moved_by_q:
            out += [(b, row.shape[-1]) for b, (_, row) in Jq.items()]
        if sensor is None and disturbed:
            sensor = arm.imu.name  # the IMU's position moves it relative to the arm's dipoles
        if sensor is not None:
            out += [(e.block_name, e.size) for e in self.mount_effects
                    if e.target == sensor and e.block_name in want]
        out += [(e.block_name, e.size) for e in self.sensor_effects
                if s in e.streams and e.block_name in want]
        if time_block is not None:
            out.append((time_block, 1))
        if rate_block is not None:
            out.append((rate_block, 1))
        return out

    def evaluate(self, state: MotionState, th, streams, q0, want, want_t=None, want_r=None):
        """Stages 1-4 for one state; physical values and (if ``want``) each stream's
        Jacobian as one array (a linear stage applies to all blocks at once)."""
        ctx, Jq, dfdq = self.prepare(state, th, streams, want)
        pred: dict[str, np.ndarray] = {}
        jac: dict[str, StreamJac] = {}
        for s in streams:
            y = self._kinematic_value(s, ctx, state, q0)
            J = None
            if want is not None:
                J = self._kinematic_jacobian(s, y, ctx, Jq, dfdq, want, (want_t or {}).get(s),
                                             (want_r or {}).get(s))
            pred[s] = self._sensor_stage(s, y, th, ctx, Jq, J, want)
            if J is not None:
                jac[s] = J
        return pred, jac

    def _kinematic_value(self, s: str, ctx: Context, state: MotionState, q0: np.ndarray) -> np.ndarray:
        """Stream ``s``'s physical value before the sensor effects (stage 3: specific force,
        angular rate, Earth's field in the sensor's axes, temperature; the encoders' angles
        from their power-up zero ``q0``)."""
        arm, imu = self.arm, self.arm.imu
        link_acc = {m.name for m in arm.link_accelerometers}
        link_gyro = {link_gyro_stream(m.name): m.name for m in arm.sensors if m.has_link_gyro}
        if s in link_acc or s == "imu_acc":
            return ctx.sm.specific_force_g[:, ctx.sensor(s if s in link_acc else imu.name)]
        if s == "imu_gyro":
            return ctx.sm.omega_S_rad_s[:, ctx.sensor(imu.name)]
        if s in link_gyro:  # a link sensor's gyroscope: its own rate (no effect of its own yet)
            return ctx.sm.omega_S_rad_s[:, ctx.sensor(link_gyro[s])]
        if s == "imu_mag":
            R_0I = ctx.sm.R_0S[:, ctx.sensor(imu.name)]
            return np.einsum("nji,nj->ni", R_0I, ctx.earth_field_0_ut)
        if s == "imu_temp":
            return np.array(state.temperature_c, dtype=float)[:, None]
        if s == "enc":
            return state.q_rad - q0
        raise KeyError(s)  # pragma: no cover - stream_names guards this

    def _kinematic_jacobian(self, s: str, y: np.ndarray, ctx: Context, Jq, dfdq, want,
                            time_block: str | None, rate_block: str | None) -> StreamJac:
        """Stream ``s``'s Jacobian after stage 3: its columns every wanted block that reaches
        it, the joint blocks' (through ``df/dq_geom``) and the mounts' filled."""
        arm = self.arm
        link_acc = {m.name for m in arm.link_accelerometers}
        J = StreamJac(y.shape[0], y.shape[1], self.blocks_reaching(s, want, Jq, time_block, rate_block))
        if s in link_acc and dfdq is not None and arm.sensor(s).link > 0:
            i = ctx.sensor(s)
            for b, (js, row) in Jq.items():
                J.set(b, np.einsum("nam,nmp->nap", dfdq[:, i][:, :, js], row))
        if s in link_acc or s == "imu_acc":
            name = s if s in link_acc else arm.imu.name
            for e in self.mount_effects:
                if e.target == name and e.block_name in want:
                    J.set(e.block_name, e.jac_params(ctx))
        return J

    def _sensor_stage(self, s: str, y: np.ndarray, th, ctx: Context, Jq, J: StreamJac | None,
                      want) -> np.ndarray:
        """Stage 4: stream ``s``'s value through its sensor effects by rank (``J`` carried
        through them, each effect's own block added)."""
        for e in self.sensor_effects:
            if s not in e.streams:
                continue
            t = th[e.block_name]
            if J is not None:
                A = e.jac_input(y, t, ctx, s)
                if A is not None:
                    J.map(A, e.input_is_diagonal)
                Q = e.jac_q(y, t, ctx, s) if Jq else None
                if Q is not None:
                    for b, (js, row) in Jq.items():
                        J.add(b, np.einsum("nam,nmp->nap", Q[:, :, js], row))
                if e.block_name in want:
                    J.add(e.block_name, e.jac_params(y, t, ctx, s))
                if s == "imu_mag" and e.name == "mag_arm_disturbance":
                    self._add_imu_position(J, e, y, t, ctx, want)
            y = e.apply(y, t, ctx, s)
        return y

    def _add_imu_position(self, J, e, y, theta, ctx, want) -> None:
        """The compass's dependence on the IMU's own position (a mount effect on the IMU
        moves it relative to the arm's dipoles): ``dy/dθ = R_0Iᵀ (dB/dr) R_0L``."""
        imu = self.arm.imu
        blocks = [m for m in self.mount_effects if m.target == imu.name and m.block_name in want
                  and m.block_name in J.cols]
        if not blocks:
            return
        dydp = e.jac_sensor_position(y, theta, ctx)  # (N, 3, 3): d reading / d p_0I
        R_0L = ctx.lm.R_0L[:, imu.link]
        for m in blocks:
            J.add(m.block_name, dydp @ R_0L)



class StreamJac:
    """One stream's Jacobian while it is built: every block that reaches the stream side
    by side in one array, in the order blocks enter the pipeline, so a linear stage maps
    all of them at once (and only the columns already filled). Stored ``(P, N, k)`` so
    that a stage's constant matrix is one contiguous matrix product."""

    def __init__(self, N: int, k: int, blocks: list[tuple[str, int]]):
        self.cols: dict[str, slice] = {}
        c = 0
        for b, p in blocks:
            self.cols[b] = slice(c, c + p)
            c += p
        self.arr = np.zeros((c, N, k))
        self.filled = 0

    def set(self, block: str, v: np.ndarray) -> None:
        """Block ``block`` := ``v (N, k, p)``."""
        sl = self.cols[block]
        self.arr[sl] = np.moveaxis(v, -1, 0)
        self.filled = max(self.filled, sl.stop)

    def add(self, block: str, v: np.ndarray) -> None:
        sl = self.cols[block]
        self.arr[sl] += np.moveaxis(v, -1, 0)
        self.filled = max(self.filled, sl.stop)

    def map(self, A: np.ndarray, diagonal: bool = False) -> None:
        """``J <- A J`` for ``A (N, k, k)``; one matrix product when A is the same for all N,
        a product of elements when A is diagonal."""
        f = self.filled
        if f == 0:
            return
        X = self.arr[:f]
        if diagonal:
            X *= np.einsum("nii->ni", A)
        elif A.ndim == 3 and A.strides[0] == 0:  # a broadcast constant matrix
            k = X.shape[-1]
            self.arr[:f] = (X.reshape(-1, k) @ A[0].T).reshape(X.shape)
        else:
            self.arr[:f] = np.einsum("nij,pnj->pni", A, X)

    def scale(self, g: np.ndarray) -> None:
        self.arr *= g

    def minus_time_derivative(self, tau: float, t: np.ndarray) -> None:
        """``J <- J - tau dJ/dt`` (the first-order time offset; ``tau`` a number or one per instant)."""
        if self.arr.shape[1] > 1:
            tau = np.asarray(tau, float)
            if tau.ndim:
                tau = tau.reshape((1, -1) + (1,) * (self.arr.ndim - 2))
            self.arr -= tau * np.gradient(self.arr, t, axis=1, edge_order=2 if len(t) > 2 else 1)

    def blocks(self) -> dict[str, np.ndarray]:
        """``{block: (N, k, p)}`` (views)."""
        return {b: np.moveaxis(self.arr[sl], 0, -1) for b, sl in self.cols.items()}


def apply_joint_effects(joint_effects, state: MotionState, th, ctx: Context, want) -> dict:
    """Stage 1 of :meth:`Stages.prepare`: every joint effect added to the controller's
    angles, giving ``ctx.q_geom``; returns (when Jacobians are wanted) each wanted joint
    block's ``d q_geom / dθ`` as ``{block: (the joints it moves, (N, joints, p))}``."""
    want_jac = want is not None
    Jq: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    q = np.array(state.q_rad, dtype=float, copy=True)
    # the zero offsets first: the torque-driven effects (sag, play) then see the
    # gravity torque where the links really stand. Evaluated at the controller's
    # angles instead, a joint's offset and the base's tilt about its axis would
    # change the torque differently, a difference a long fit takes for information
    # that separates them (it does not exist: a confident wrong encoder zero).
    # An offset then also moves every torque-driven joint's delta (its column carries
    # that chain: d q_geom[j] / d offset[k] = δjk + d delta_j / d q_k).
    order = sorted(joint_effects, key=lambda e: e.name != "joint_offset")
    offsets = [e for e in order if e.name == "joint_offset"]
    torque_set = False
    for e in order:
        if not torque_set and e.name != "joint_offset":
            if offsets:
                ctx.set_torque_angles(q.copy())
            torque_set = True
        t = th[e.block_name]
        q[:, e.j] += e.delta(state.q_rad, t, ctx)
        if want_jac and e.block_name in want:
            Jq[e.block_name] = (np.array([e.j]), e.delta_jac_params(state.q_rad, t, ctx)[:, None, :])
        if want_jac and offsets and e.name != "joint_offset":
            dq = e.delta_jac_q(state.q_rad, t, ctx)  # (N, n) at q_torque
            if dq is not None:
                for o in offsets:
                    if o.block_name in want and np.any(dq[:, o.j]):
                        js, R = Jq[o.block_name]
                        if e.j not in js:
                            js = np.append(js, e.j)
                            R = np.concatenate([R, np.zeros((R.shape[0], 1, R.shape[2]))], 1)
                        R[:, list(js).index(e.j), 0] += dq[:, o.j]
                        Jq[o.block_name] = (js, R)
    ctx.q_geom = q
    return Jq
