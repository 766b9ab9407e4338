"""A model: the arm's sensors as the datasheets describe them, plus an ordered set of effects.

The parameters of all effects live in one flat vector ``x`` (what scipy's
``least_squares`` wants) with a name -> slice map (``Model.index``); the API talks in
block names (``"acc3.mount_rotation"``): ``pack`` / ``unpack`` convert.

A prediction runs the stages in physical order, whatever order the effects were listed in
(the list order fixes only the layout of ``x``):

1. joints: ``q_geom = q + Σ delta_e(q)`` (joint offsets, sag, play);
2. mounts: sensors moved on their links (lever arms);
3. kinematics (:mod:`armfusion.models.motion`): specific force, angular rate, Earth's field and
   temperature in each sensor's axes; the encoders see the controller's ``q``;
4. sensor: each stream's value through its effects by rank (frame 10, axes 20, scale 30,
   bias 40, drift 50; the arm's magnetic disturbance 5, before the IMU frame);
5. time: a device's samples taken ``offset`` before their stamps;
6. counts: nominal gain and zero (:mod:`armfusion.models.sensor_models`).

The Jacobian w.r.t. the parameters is accumulated forward through the same stages, as a
dict ``{stream: {block: (N, k, p)}}`` holding only the blocks that reach that stream.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.effects.base import (
    Context,
    Effect,
    JointEffect,
    MountEffect,
    ParamBlock,
    SensorEffect,
    TimeEffect,
    device_streams,
)
from armfusion.models.motion import (
    DEFAULT_MASSES,
    MassModel,
    MotionState,
    link_motion,
    sensor_motion,
    specific_force_jacobian,
)
from armfusion.models.sensor_models import EARTH_FIELD_TAMPA_UT, StreamModel, stream_models
from armfusion.sensors.samples import link_gyro_stream

StateAt = Callable[[np.ndarray], MotionState]
Jacobian = dict[str, dict[str, np.ndarray]]


def _gradient_t(a: np.ndarray, t: np.ndarray) -> np.ndarray:
    if a.shape[0] < 2:
        return np.zeros_like(a)
    return np.gradient(a, t, axis=0, edge_order=2 if a.shape[0] > 2 else 1)


class Model:
    """The arm's measurement model with an ordered set of effects (immutable).

    ``values`` (block name -> array) are the current parameter estimates (default: zero,
    the identity) and ``sigmas`` their uncertainties (default: each effect's
    datasheet-typical magnitude); both become the prior a refit starts from.
    """

    def __init__(
        self,
        arm: ArmModel,
        effects: Sequence[Effect] = (),
        values: Mapping[str, np.ndarray] | None = None,
        sigmas: Mapping[str, np.ndarray] | None = None,
        earth_field_W_ut: np.ndarray = EARTH_FIELD_TAMPA_UT,
        masses: MassModel = DEFAULT_MASSES,
    ):
        self.arm = arm
        self.effects: tuple[Effect, ...] = tuple(effects)
        seen: dict[str, int] = {}
        for k, e in enumerate(self.effects):
            if e.arm is not arm and (e.arm.name != arm.name or e.arm.n_joints != arm.n_joints):
                raise ValueError(f"effect {e.block_name} was built for another arm")
            if e.block_name in seen:
                raise ValueError(f"effect {e.block_name} is listed twice "
                                 f"(positions {seen[e.block_name]} and {k})")
            seen[e.block_name] = k
        sigmas = dict(sigmas or {})
        unknown = set(sigmas) - set(seen)
        if unknown:
            raise KeyError(f"sigma given for unknown blocks {sorted(unknown)}")
        self.blocks: tuple[ParamBlock, ...] = tuple(e.block(sigmas.get(e.block_name)) for e in self.effects)
        self.index: dict[str, slice] = {}
        i = 0
        for b in self.blocks:
            self.index[b.name] = slice(i, i + b.size)
            i += b.size
        self.size = i
        self._by_name = {e.block_name: e for e in self.effects}
        self.earth_field_W_ut = np.asarray(earth_field_W_ut, dtype=float)
        self.masses = masses
        self.x0 = self.pack(values or {}, base=np.zeros(self.size))
        self.x0.setflags(write=False)
        self._stream_models = stream_models(arm)
        self.stream_names: tuple[str, ...] = tuple(self._stream_models)

        def ordered(cls):
            return sorted((e for e in self.effects if isinstance(e, cls)), key=lambda e: e.rank)

        self._joint = ordered(JointEffect)
        self._mount = ordered(MountEffect)
        self._sensor = ordered(SensorEffect)
        self._time = ordered(TimeEffect)

    # -- parameters --------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.effects)

    def __repr__(self) -> str:
        return f"Model({self.arm.name}: {', '.join(e.block_name for e in self.effects) or 'no effects'})"

    def effect(self, block_name: str) -> Effect:
        try:
            return self._by_name[block_name]
        except KeyError:
            raise KeyError(f"no effect {block_name!r} in the model; it has "
                           f"{list(self._by_name)}") from None

    def block(self, block_name: str) -> ParamBlock:
        return self.blocks[self.effects.index(self.effect(block_name))]

    @property
    def prior_mean(self) -> np.ndarray:
        return self.x0

    @property
    def prior_sigma(self) -> np.ndarray:
        return np.concatenate([b.prior_sigma for b in self.blocks]) if self.blocks else np.zeros(0)

    @property
    def lower(self) -> np.ndarray:
        return np.concatenate([b.lower for b in self.blocks]) if self.blocks else np.zeros(0)

    @property
    def upper(self) -> np.ndarray:
        return np.concatenate([b.upper for b in self.blocks]) if self.blocks else np.zeros(0)

    def element_names(self) -> list[str]:
        return [n for b in self.blocks for n in b.element_names()]

    def pack(self, values: Mapping[str, np.ndarray], base: np.ndarray | None = None) -> np.ndarray:
        """A flat vector from named blocks; blocks not named keep ``base`` (default ``x0``)."""
        x = np.array(self.x0 if base is None else base, dtype=float, copy=True)
        for name, v in values.items():
            b = self.block(name)
            a = np.asarray(v, dtype=float)
            if a.size != b.size:
                raise ValueError(f"{name}: expected {b.size} values {b.shape}, got shape {a.shape}")
            x[self.index[name]] = a.reshape(-1)
        return x

    def unpack(self, x: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Named blocks (shaped) from a flat vector (default ``x0``)."""
        x = self.x0 if x is None else np.asarray(x, dtype=float)
        if x.shape != (self.size,):
            raise ValueError(f"parameter vector must have shape ({self.size},), got {x.shape}")
        return {b.name: x[self.index[b.name]].reshape(b.shape) for b in self.blocks}

    def with_effects(self, effects: Iterable[Effect], values: Mapping[str, np.ndarray] | None = None,
                     sigmas: Mapping[str, np.ndarray] | None = None) -> Model:
        """This model plus more effects (their blocks appended); current values are kept."""
        current = self.unpack()
        current.update(values or {})
        s = {b.name: b.prior_sigma for b in self.blocks}
        s.update(sigmas or {})
        return Model(self.arm, self.effects + tuple(effects), current, s, self.earth_field_W_ut,
                     self.masses)

    def with_values(self, values: Mapping[str, np.ndarray] | np.ndarray) -> Model:
        """The same effects with new current values (named blocks or a full flat vector)."""
        v = self.unpack(values) if isinstance(values, np.ndarray) else dict(values)
        return Model(self.arm, self.effects, {**self.unpack(), **v},
                     {b.name: b.prior_sigma for b in self.blocks}, self.earth_field_W_ut, self.masses)

    def without(self, block_names: Iterable[str]) -> Model:
        drop = set(block_names)
        keep = [e for e in self.effects if e.block_name not in drop]
        vals = {k: v for k, v in self.unpack().items() if k not in drop}
        return Model(self.arm, keep, vals, {b.name: b.prior_sigma for b in self.blocks
                                            if b.name not in drop}, self.earth_field_W_ut, self.masses)

    def stream_models(self, rate_hz: float | dict[str, float] = 100.0) -> dict[str, StreamModel]:
        return stream_models(self.arm, rate_hz)

    def time_offsets_s(self, x: np.ndarray | None = None) -> dict[str, float]:
        """Each device's time offset (s), for devices that have one."""
        th = self.unpack(x)
        return {e.target: float(th[e.block_name][0]) for e in self._time if e.name == "time_offset"}

    def time_drifts(self, x: np.ndarray | None = None) -> dict[str, float]:
        """Each device's time offset's drift (s per s of the recording), for devices that have one."""
        th = self.unpack(x)
        return {e.target: float(th[e.block_name][0]) for e in self._time if e.name == "time_drift"}

    # -- prediction ----------------------------------------------------------------------
    def predict(
        self, state: MotionState, x: np.ndarray | None = None, streams: Sequence[str] | None = None,
        state_at: StateAt | None = None, encoder_zero_rad: np.ndarray | None = None,
        units: str = "counts",
    ) -> dict[str, np.ndarray]:
        """Predicted readings ``{stream: (N, k)}``, float counts (``units="counts"``) or the
        physical values in each sensor's axes (``"physical"``: g, rad/s, µT, °C, rad).

        ``state_at`` (a function of time giving a MotionState) makes time offsets exact
        (the state is re-evaluated at ``t - offset``); without it they are first order,
        ``y(t) - offset·dy/dt`` with ``dy/dt`` from the samples themselves.
        ``encoder_zero_rad``: the joint angles at power-up (default: the first sample's).
        """
        pred, _ = self._predict(state, x, streams, state_at, encoder_zero_rad, units, None)
        return pred

    def predict_with_jacobian(
        self, state: MotionState, x: np.ndarray | None = None, streams: Sequence[str] | None = None,
        state_at: StateAt | None = None, encoder_zero_rad: np.ndarray | None = None,
        units: str = "counts", blocks: Iterable[str] | None = None,
    ) -> tuple[dict[str, np.ndarray], Jacobian]:
        """Predictions and ``{stream: {block: d prediction / d block (N, k, p)}}``.

        ``blocks`` limits the Jacobian to those blocks (default: all).
        """
        want = set(self.index) if blocks is None else set(blocks)
        unknown = want - set(self.index)
        if unknown:
            raise KeyError(f"no such blocks in the model: {sorted(unknown)}")
        return self._predict(state, x, streams, state_at, encoder_zero_rad, units, want)

    def dense_jacobian(self, jac: Jacobian, pred: Mapping[str, np.ndarray],
                       blocks: Sequence[str] | None = None) -> np.ndarray:
        """Stack a Jacobian dict into ``(M, P)``: rows stream by stream (in ``pred``'s order),
        each ``(N, k)`` row-major as ``pred[s].ravel()``; columns the ``blocks`` (default:
        all, in ``x`` order) concatenated."""
        blocks = list(self.index) if blocks is None else list(blocks)
        sizes = [self.block(b).size for b in blocks]
        rows = []
        for s, y in pred.items():
            N, k = y.shape
            R = np.zeros((N * k, sum(sizes)))
            c = 0
            for b, sz in zip(blocks, sizes, strict=True):
                if b in jac.get(s, {}):
                    R[:, c:c + sz] = jac[s][b].reshape(N * k, sz)
                c += sz
            rows.append(R)
        return np.concatenate(rows, axis=0) if rows else np.zeros((0, sum(sizes)))

    # -- the pipeline --------------------------------------------------------------------
    def _predict(self, state, x, streams, state_at, q0, units, want):
        if units not in ("counts", "physical"):
            raise ValueError(f"units must be 'counts' or 'physical', not {units!r}")
        streams = self.stream_names if streams is None else tuple(streams)
        bad = [s for s in streams if s not in self.stream_names]
        if bad:
            raise KeyError(f"no stream {bad[0]!r} for arm {self.arm.name!r}; "
                           f"it has {list(self.stream_names)}")
        if state.n_joints != self.arm.n_joints:
            raise ValueError(f"joint angles must have shape (N, {self.arm.n_joints}) for arm "
                             f"{self.arm.name!r}, got {state.q_rad.shape}")
        th = self.unpack(x)
        q0 = state.q_rad[0] if q0 is None else np.asarray(q0, dtype=float)
        # time offsets per stream
        offset = {s: 0.0 for s in streams}
        rate = {s: 0.0 for s in streams}
        tblock: dict[str, str] = {}
        rblock: dict[str, str] = {}
        for e in self._time:
            for s in device_streams(self.arm, e.target):
                if s in offset:
                    if e.name == "time_drift":
                        rate[s] = float(th[e.block_name][0])
                        rblock[s] = e.block_name
                    else:
                        offset[s] = float(th[e.block_name][0])
                        tblock[s] = e.block_name
        want_t = {s: b for s, b in tblock.items() if want is not None and b in want}
        want_r = {s: b for s, b in rblock.items() if want is not None and b in want}
        pred: dict[str, np.ndarray] = {}
        jac: dict[str, _StreamJac] = {}
        if state_at is None:
            p, j = self._evaluate(state, th, streams, q0, want, want_t, want_r)
            for s in streams:
                y, J = p[s], j.get(s)
                timed = s in tblock or s in rblock
                if timed and (offset[s] != 0.0 or rate[s] != 0.0 or s in want_t or s in want_r):
                    # stamped t, true at t - tau(t): tau = offset + rate t (first order)
                    tau = offset[s] + rate[s] * np.asarray(state.t_s, float) if rate[s] != 0.0 else offset[s]
                    ydot = _gradient_t(y, state.t_s)
                    if J is not None:
                        if np.any(tau != 0.0):
                            J.minus_time_derivative(tau, state.t_s)
                        if s in want_t:
                            J.set(want_t[s], -ydot[..., None])
                        if s in want_r:
                            J.set(want_r[s], -(np.asarray(state.t_s, float)[:, None] * ydot)[..., None])
                    y = y - (tau[:, None] if np.ndim(tau) else tau) * ydot
                pred[s] = y
                if J is not None:
                    jac[s] = J
        else:
            groups: dict[tuple[float, float], list[str]] = {}
            for s in streams:
                groups.setdefault((offset[s], rate[s]), []).append(s)
            for (tau, r), ss in groups.items():
                st = state if tau == 0.0 and r == 0.0 else state_at(state.t_s - tau - r * state.t_s)
                p, j = self._evaluate(st, th, tuple(ss), q0, want, want_t, want_r)
                for s in ss:
                    J = j.get(s)
                    if J is not None and s in want_t:
                        J.set(want_t[s], -_gradient_t(p[s], state.t_s)[..., None])
                    if J is not None and s in want_r:
                        J.set(want_r[s], -(state.t_s[:, None] * _gradient_t(p[s], state.t_s))[..., None])
                    pred[s] = p[s]
                    if J is not None:
                        jac[s] = J
        pred = {s: pred[s] for s in streams}
        if units == "counts":
            sm = self._stream_models
            for s in streams:
                g, z = sm[s].gain, sm[s].zero
                pred[s] = pred[s] * g + z
                if s in jac:
                    jac[s].scale(g)
        if want is None:
            return pred, {}
        return pred, {s: (jac[s].blocks() if s in jac else {}) for s in streams}

    def context(self, state: MotionState, x: np.ndarray | None = None,
                streams: Sequence[str] | None = None) -> Context:
        """The context effects see for ``state`` (joint stage and kinematics done): for
        checking an effect on its own, or for an estimator that needs the kinematics."""
        streams = self.stream_names if streams is None else tuple(streams)
        ctx, _, _ = self._prepare(state, self.unpack(x), streams, None)
        return ctx

    def _prepare(self, state: MotionState, th, streams, want):
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
        joint_stage = bool(self._joint) and geometric
        if joint_stage:
            Jq = _apply_joint_effects(self._joint, state, th, ctx, want)
        # 2. mounts, 3. kinematics
        sensors = [s for s in streams if s in link_acc]
        imu = arm.imu
        if imu is not None and any(s in ("imu_acc", "imu_gyro", "imu_mag") for s in streams):
            sensors.append(imu.name)
        dfdq = None
        if sensors:
            R_LS = np.stack([arm.sensor(s).R_LS for s in sensors])
            p_LS = np.stack([arm.sensor(s).p_L_m for s in sensors]).copy()
            for e in self._mount:
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

    def _blocks_reaching(self, s: str, want, Jq, time_block: str | None,
                         rate_block: str | None = None) -> list[tuple[str, int]]:
        """The wanted blocks that reach stream ``s``, in the order they enter the pipeline."""
        arm = self.arm
        link_acc = {m.name: m for m in arm.link_accelerometers}
        out: list[tuple[str, int]] = []
        sensor = s if s in link_acc else (arm.imu.name if s == "imu_acc" else None)
        moved_by_q = (s in link_acc and link_acc[s].link > 0) or (
            s == "imu_mag" and any(e.name == "mag_arm_disturbance" for e in self._sensor))
        if moved_by_q:
            out += [(b, row.shape[-1]) for b, (_, row) in Jq.items()]
        if sensor is None and s == "imu_mag" and any(e.name == "mag_arm_disturbance" for e in self._sensor):
            sensor = arm.imu.name  # the IMU's position moves it relative to the arm's dipoles
        if sensor is not None:
            out += [(e.block_name, e.size) for e in self._mount
                    if e.target == sensor and e.block_name in want]
        out += [(e.block_name, e.size) for e in self._sensor
                if s in e.streams and e.block_name in want]
        if time_block is not None:
            out.append((time_block, 1))
        if rate_block is not None:
            out.append((rate_block, 1))
        return out

    def _evaluate(self, state: MotionState, th, streams, q0, want, want_t=None, want_r=None):
        """Stages 1-4 for one state; physical values and (if ``want``) each stream's
        Jacobian as one array (a linear stage applies to all blocks at once)."""
        arm = self.arm
        imu = arm.imu
        want_jac = want is not None
        link_acc = {s.name for s in arm.link_accelerometers}
        link_gyro = {link_gyro_stream(s.name): s.name for s in arm.sensors if s.has_link_gyro}
        ctx, Jq, dfdq = self._prepare(state, th, streams, want)
        N = state.N
        pred: dict[str, np.ndarray] = {}
        jac: dict[str, _StreamJac] = {}
        for s in streams:
            J = None
            if s in link_acc or s == "imu_acc":
                name = s if s in link_acc else imu.name
                i = ctx.sensor(name)
                y = ctx.sm.specific_force_g[:, i]
            elif s == "imu_gyro":
                y = ctx.sm.omega_S_rad_s[:, ctx.sensor(imu.name)]
            elif s in link_gyro:  # a link sensor's gyroscope: its own rate (no effect of its own yet)
                y = ctx.sm.omega_S_rad_s[:, ctx.sensor(link_gyro[s])]
            elif s == "imu_mag":
                R_0I = ctx.sm.R_0S[:, ctx.sensor(imu.name)]
                y = np.einsum("nji,nj->ni", R_0I, ctx.earth_field_0_ut)
            elif s == "imu_temp":
                y = np.array(state.temperature_c, dtype=float)[:, None]
            elif s == "enc":
                y = state.q_rad - q0
            else:  # pragma: no cover - stream_names guards this
                raise KeyError(s)
            if want_jac:
                J = _StreamJac(N, y.shape[1], self._blocks_reaching(s, want, Jq, (want_t or {}).get(s),
                                                                     (want_r or {}).get(s)))
                if s in link_acc and dfdq is not None and arm.sensor(s).link > 0:
                    i = ctx.sensor(s)
                    for b, (js, row) in Jq.items():
                        J.set(b, np.einsum("nam,nmp->nap", dfdq[:, i][:, :, js], row))
                if s in link_acc or s == "imu_acc":
                    name = s if s in link_acc else imu.name
                    for e in self._mount:
                        if e.target == name and e.block_name in want:
                            J.set(e.block_name, e.jac_params(ctx))
            # 4. sensor effects, by rank
            for e in self._sensor:
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
            pred[s] = y
            if J is not None:
                jac[s] = J
        return pred, jac

    def _add_imu_position(self, J, e, y, theta, ctx, want) -> None:
        """The compass's dependence on the IMU's own position (a mount effect on the IMU
        moves it relative to the arm's dipoles): ``dy/dθ = R_0Iᵀ (dB/dr) R_0L``."""
        imu = self.arm.imu
        blocks = [m for m in self._mount if m.target == imu.name and m.block_name in want
                  and m.block_name in J.cols]
        if not blocks:
            return
        dydp = e.jac_sensor_position(y, theta, ctx)  # (N, 3, 3): d reading / d p_0I
        R_0L = ctx.lm.R_0L[:, imu.link]
        for m in blocks:
            J.add(m.block_name, dydp @ R_0L)


class _StreamJac:
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


def _apply_joint_effects(joint_effects, state: MotionState, th, ctx: Context, want) -> dict:
    """Stage 1 of :meth:`Model._prepare`: every joint effect added to the controller's
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
