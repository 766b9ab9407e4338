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

The Jacobian w.r.t. the parameters is accumulated forward through the same stages
(stages 1-4: :mod:`armfusion.models.effects.stages`), as a dict
``{stream: {block: (N, k, p)}}`` holding only the blocks that reach that stream.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.effects.base import (
    Context,
    Effect,
    ParamBlock,
    TimeEffect,
    device_streams,
)
from armfusion.models.effects.stages import Stages, StreamJac
from armfusion.models.motion import DEFAULT_MASSES, MassModel, MotionState
from armfusion.models.sensor_models import EARTH_FIELD_TAMPA_UT, StreamModel, stream_models

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

        self._stages = Stages(arm, self.effects, masses, self.earth_field_W_ut)

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
        return {e.target: float(th[e.block_name][0]) for e in self._stages.time_effects
                if e.name == "time_offset"}

    def time_drifts(self, x: np.ndarray | None = None) -> dict[str, float]:
        """Each device's time offset's drift (s per s of the recording), for devices that have one."""
        th = self.unpack(x)
        return {e.target: float(th[e.block_name][0]) for e in self._stages.time_effects
                if e.name == "time_drift"}

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
        """Stages 1-6 for ``streams``: the physical values through every effect, read at their
        time offsets, then in counts (``units``); with the Jacobian dict when ``want``."""
        streams = self._checked_streams(state, streams, units)
        th = self.unpack(x)
        q0 = state.q_rad[0] if q0 is None else np.asarray(q0, dtype=float)
        timing = _Timing.of(self._stages.time_effects, self.arm, th, streams, want)
        if state_at is None:
            pred, jac = self._first_order_timed(state, th, streams, q0, want, timing)
        else:
            pred, jac = self._exact_timed(state, state_at, th, streams, q0, want, timing)
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

    def _checked_streams(self, state: MotionState, streams, units: str) -> tuple[str, ...]:
        """The streams asked for (default: all), each one of the arm's, for a state of the
        arm's joints in known units (else a ``KeyError`` or ``ValueError``)."""
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
        return streams

    def _first_order_timed(self, state: MotionState, th, streams, q0, want, timing: _Timing):
        """Stage 5 without a state function: each timed stream read ``tau = offset + rate t``
        earlier to first order, ``y(t) - tau dy/dt`` (its Jacobian likewise)."""
        pred: dict[str, np.ndarray] = {}
        jac: dict[str, StreamJac] = {}
        offset, rate, want_t, want_r = timing.offset, timing.rate, timing.want_t, timing.want_r
        p, j = self._stages.evaluate(state, th, streams, q0, want, want_t, want_r)
        for s in streams:
            y, J = p[s], j.get(s)
            timed = s in timing.tblock or s in timing.rblock
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
        return pred, jac

    def _exact_timed(self, state: MotionState, state_at: StateAt, th, streams, q0, want, timing: _Timing):
        """Stage 5 with a state function: the streams of one time offset and drift evaluated
        together at ``t - offset - rate t``."""
        pred: dict[str, np.ndarray] = {}
        jac: dict[str, StreamJac] = {}
        groups: dict[tuple[float, float], list[str]] = {}
        for s in streams:
            groups.setdefault((timing.offset[s], timing.rate[s]), []).append(s)
        for (tau, r), ss in groups.items():
            st = state if tau == 0.0 and r == 0.0 else state_at(state.t_s - tau - r * state.t_s)
            p, j = self._stages.evaluate(st, th, tuple(ss), q0, want, timing.want_t, timing.want_r)
            for s in ss:
                J = j.get(s)
                if J is not None and s in timing.want_t:
                    J.set(timing.want_t[s], -_gradient_t(p[s], state.t_s)[..., None])
                if J is not None and s in timing.want_r:
                    J.set(timing.want_r[s], -(state.t_s[:, None] * _gradient_t(p[s], state.t_s))[..., None])
                pred[s] = p[s]
                if J is not None:
                    jac[s] = J
        return pred, jac

    def context(self, state: MotionState, x: np.ndarray | None = None,
                streams: Sequence[str] | None = None) -> Context:
        """The context effects see for ``state`` (joint stage and kinematics done): for
        checking an effect on its own, or for an estimator that needs the kinematics."""
        streams = self.stream_names if streams is None else tuple(streams)
        ctx, _, _ = self._stages.prepare(state, self.unpack(x), streams, None)
        return ctx


@dataclass(frozen=True)
class _Timing:
    """Each stream's time offset (s) and its drift (s per s), the blocks that give them, and
    those of them whose Jacobian is wanted."""

    offset: dict[str, float]
    rate: dict[str, float]
    tblock: dict[str, str]
    rblock: dict[str, str]
    want_t: dict[str, str]
    want_r: dict[str, str]

    @classmethod
    def of(cls, time_effects: Sequence[TimeEffect], arm: ArmModel, th: Mapping[str, np.ndarray],
           streams: Sequence[str], want) -> _Timing:
        """The timing of ``streams`` under the time effects' values ``th``."""
        offset = {s: 0.0 for s in streams}
        rate = {s: 0.0 for s in streams}
        tblock: dict[str, str] = {}
        rblock: dict[str, str] = {}
        for e in time_effects:
            for s in device_streams(arm, e.target):
                if s in offset:
                    if e.name == "time_drift":
                        rate[s] = float(th[e.block_name][0])
                        rblock[s] = e.block_name
                    else:
                        offset[s] = float(th[e.block_name][0])
                        tblock[s] = e.block_name
        want_t = {s: b for s, b in tblock.items() if want is not None and b in want}
        want_r = {s: b for s, b in rblock.items() if want is not None and b in want}
        return cls(offset, rate, tblock, rblock, want_t, want_r)
