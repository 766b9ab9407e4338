"""The simulator: a scenario plus a model with effects becomes a recording of raw counts.

``simulate(arm, scenario, …)`` returns a :class:`~armfusion.sensors.samples.Recording` (every raw
stream as the devices would give it, plus the ground-truth streams ``true_q`` and
``true_base``) and a JSON-ready truth dict (every effect's true parameters as config
entries, the scenario's events, the settings). It does no I/O: ``armfusion simulate``
(``fusion/cli/simulate.py``) writes the files.

The chain per device, per chunk of samples (no loop per sample):

1. the scenario's exact :class:`~armfusion.models.motion.MotionState` at the sample instants;
2. the model's prediction in float counts (every effect but the time offsets);
3. a device with a time offset is read ``offset`` earlier, by 4-point cubic
   interpolation along time (its error at 100 Hz is ~1e-7 g);
4. white Gaussian noise at the datasheet rms for the rate, rounding, saturation.

Randomness is seeded and split: the scenario's motion, the drawn effects and each
stream's noise come from independent generators derived from ``seed``, so the same seed
gives the same arm (effects) in every scenario, and changing the duration does not change
the effects.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.effects import (
    Model,
    all_effects,
    entries_from_model,
    model_from_entries,
    realistic_values,
)
from armfusion.models.effects.base import device_names, device_streams
from armfusion.models.rotations import GRAVITY_MPS2
from armfusion.models.sensor_models import EARTH_FIELD_TAMPA_UT, stream_models
from armfusion.models.trajectories import SCENARIOS, Scenario, make_scenario
from armfusion.sensors.samples import (
    TRUTH_BASE_COLUMNS,
    Recording,
    Stream,
    truth_joint_columns,
)

TRUTH_FORMAT = "armfusion.truth/1"
REALISTIC_EXCLUDE = frozenset({"enc.time_offset", "enc.time_drift"})
"""Blocks ``--realistic`` leaves at zero: the encoders are the time reference (a common
delay of every stream cannot be seen, so one device must define the clock)."""
NOT_OF_THE_DEVICES = frozenset({"time_drift"})
"""Effects ``--realistic`` does not draw and ``--effects all`` does not fit: not a device's
but a logging set-up's (a clock not disciplined to the encoders'). On the WMRA every device is
read and stamped by the one computer's clock; a scenario with two clocks declares its drift
(``tools/twin_ur5.py``), and the workbench proposes it where a recording shows it."""


def drawn_by_default(e) -> bool:
    """Whether ``--realistic`` draws effect ``e`` and ``--effects all`` fits it."""
    return e.block_name not in REALISTIC_EXCLUDE and e.name not in NOT_OF_THE_DEVICES
CHUNK_SAMPLES = 30000
"""Samples simulated at once: bounds memory (a few hundred MB at most) without slowing."""


def _rng(seed: int, *path: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *path])


def build_model(arm: ArmModel, effects: Model | Iterable[Any] | None = None, realistic: bool = False,
                seed: int = 0, source: str = "(effects)",
                earth_field_ut: np.ndarray = EARTH_FIELD_TAMPA_UT) -> tuple[Model, np.ndarray]:
    """The simulation's true model and its parameters.

    ``realistic`` draws every effect of the library on every target at datasheet-typical
    magnitudes (seeded by ``seed``); ``effects`` (a :class:`Model`, or entries as in a
    config's ``effects:`` list) adds effects or overrides drawn values of the same block.
    ``earth_field_ut``: Earth's field in the world frame (x magnetic north, z up), µT.
    """
    base = Model(arm, earth_field_W_ut=earth_field_ut)
    values: dict[str, np.ndarray] = {}
    if realistic:
        base = Model(arm, [e for e in all_effects(arm) if drawn_by_default(e)],
                     earth_field_W_ut=earth_field_ut)
        values = realistic_values(base, _rng(seed, 1))
    if effects is not None:
        given = effects if isinstance(effects, Model) else model_from_entries(arm, effects, source)
        extra = [e for e in given.effects if e.block_name not in base.index]
        given_vals = given.unpack()
        base = base.with_effects(extra)
        values.update(given_vals)
    model = base.with_values(values)
    return model, np.array(model.x0)


def _shifted(y: np.ndarray, pad: int, n: int, shift) -> np.ndarray:
    """Rows ``pad … pad+n-1`` of ``y`` read ``shift`` samples earlier (4-point cubic; one
    shift, or one per row)."""
    if np.all(np.asarray(shift) == 0.0):
        return y[pad:pad + n]
    pos = np.arange(pad, pad + n) - shift
    i = np.floor(pos).astype(int)
    u = (pos - i)[:, None]
    w = (-u * (u - 1) * (u - 2) / 6, (u + 1) * (u - 1) * (u - 2) / 2,
         -(u + 1) * u * (u - 2) / 2, (u + 1) * u * (u - 1) / 6)
    return w[0] * y[i - 1] + w[1] * y[i] + w[2] * y[i + 1] + w[3] * y[i + 2]


@dataclass(frozen=True)
class SimulationOptions:
    """The simulator's settings beyond the arm, the scenario, its length, rate and seed and
    the true effects, each with its default."""

    noise: bool = True
    """White Gaussian noise at the datasheet rms for the rate; False gives the ideal counts
    (still rounded and saturated)."""
    rates_hz: Mapping[str, float] | None = None
    """A device's own sample rate by its name (``acc1``, ``imu``, ``enc``…), Hz; the others
    sample at the run's ``rate_hz``."""
    scenario_options: Mapping[str, Any] | None = None
    """Options of a named scenario (``startup``: ``pose_rad``; ``renk-maneuver``: ``joints``)."""
    earth_field_ut: np.ndarray = field(default_factory=lambda: EARTH_FIELD_TAMPA_UT)
    """Earth's field in the world frame (x magnetic north, z up), µT (default Tampa)."""
    progress: Callable[[float], None] | None = None
    """Called with the fraction done after every chunk of samples."""


DEFAULT_OPTIONS = SimulationOptions()
"""Noise on, every device at the run's rate, the scenario's own options, Earth's field at Tampa."""


def resolve_scenario(arm: ArmModel, scenario: str | Scenario, duration_s: float | None, seed: int,
                     scenario_options: Mapping[str, Any] | None = None) -> Scenario:
    """``scenario`` itself (with ``duration_s`` where given), or the named one built for ``arm``
    (seeded; a ``ValueError`` naming the known ones for an unknown name)."""
    if isinstance(scenario, Scenario):
        if duration_s is None:
            return scenario
        return Scenario(scenario.name, scenario.arm, float(duration_s), scenario.joints, scenario.base,
                        scenario.temperature, scenario.events)
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
    return make_scenario(arm, scenario, duration_s, seed, **(scenario_options or {}))


def without_time_effects(model: Model, x: np.ndarray) -> np.ndarray:
    """``x`` with the time effects' parameters zeroed: the prediction on the grid leaves
    them out, and each stream is then read its offset earlier."""
    x_now = np.array(x, dtype=float)
    for e in model.effects:
        if e.stage == "time":
            x_now[model.index[e.block_name]] = 0.0
    return x_now


def _device_rates(arm: ArmModel, rate_hz: float, rates_hz: Mapping[str, float] | None) -> dict[str, float]:
    """Each device's sample rate: ``rates_hz``'s where it names the device, else ``rate_hz``
    (a ``ValueError`` for an unknown device or a rate not positive)."""
    rates = {d: float(rate_hz) for d in device_names(arm)}
    for d, r in (rates_hz or {}).items():
        if d not in rates:
            raise ValueError(f"rates_hz: no device {d!r}; devices are {', '.join(rates)}")
        if not r > 0:
            raise ValueError(f"rates_hz[{d!r}] must be positive, got {r!r}")
        rates[d] = float(r)
    return rates


def _samples(duration_s: float, rate_hz: float) -> int:
    """How many samples ``duration_s`` holds at ``rate_hz`` (the first at t = 0)."""
    return int(np.floor(duration_s * rate_hz + 1e-9))


class _Progress:
    """Counts the samples done against the run's total and tells ``callback`` the fraction."""

    def __init__(self, work: int, callback: Callable[[float], None] | None):
        self.work, self.callback, self.done = work, callback, 0

    def advanced(self, k: int) -> None:
        """``k`` more samples done."""
        self.done += k
        if self.callback is not None:
            self.callback(self.done / max(self.work, 1))


@dataclass(frozen=True)
class _TrueRun:
    """What every grid of a run reads: its scenario, the true model with its parameters (and
    those without the time effects), the encoders' zero and each stream's model."""

    arm: ArmModel
    sc: Scenario
    model: Model
    x: np.ndarray
    x_now: np.ndarray
    q0: np.ndarray
    smodels: dict


def _sample_grid(run: _TrueRun, rate_hz: float, devices: list[str], noise_rng: dict,
                 progress: _Progress) -> dict[str, tuple[np.ndarray, list[np.ndarray]]]:
    """The devices sampling at ``rate_hz``, read on one grid: per stream its times and its
    digitised values, chunk by chunk (one state per chunk, shared by the devices)."""
    arm, sc, smodels = run.arm, run.sc, run.smodels
    # time offsets (a device's, plus a part's own delay: its description's delay_s): predict
    # once on the grid, then read each stream at t - offset - delay by cubic interpolation
    # (4 points; at 100 Hz its error is ~1e-7 g, far below any noise)
    offsets = run.model.time_offsets_s(run.x)
    drifts = run.model.time_drifts(run.x)  # a drifting offset: offset + rate t, t from the start
    r = rate_hz
    n = _samples(sc.duration_s, r)
    t_all = np.arange(n) / r
    streams = [s for d in devices for s in device_streams(arm, d)]
    shift = {s: (offsets.get(d, 0.0) + smodels[s].delay_s) * r for d in devices
             for s in device_streams(arm, d)}
    drift = {s: drifts.get(d, 0.0) for d in devices for s in device_streams(arm, d)}
    most = max((abs(v) + abs(drift[s]) * sc.duration_s * r for s, v in shift.items()), default=0.0)
    pad = int(np.ceil(most)) + 2
    out: dict[str, tuple[np.ndarray, list[np.ndarray]]] = {s: (t_all, []) for s in streams}
    for a in range(0, n, CHUNK_SAMPLES):
        b = min(n, a + CHUNK_SAMPLES)
        k = np.arange(a - pad, b + pad)
        state = sc.state(k / r)
        pred = run.model.predict(state, run.x_now, streams, encoder_zero_rad=run.q0)
        for s in streams:
            sh = shift[s] + drift[s] * t_all[a:b] * r if drift[s] else shift[s]
            y = _shifted(pred[s], pad, b - a, sh)
            out[s][1].append(smodels[s].digitise(y, noise_rng.get(s)))
        progress.advanced(b - a)
    return out


def _truth_streams(run: _TrueRun, rate_hz: float, progress: _Progress) -> dict[str, Stream]:
    """The ground truth at ``rate_hz``: ``true_q`` (the joint angles) and ``true_base`` (the
    base's roll, pitch, yaw)."""
    truth_t = np.arange(_samples(run.sc.duration_s, rate_hz)) / rate_hz
    q_true = np.zeros((len(truth_t), run.arm.n_joints))
    rpy_true = np.zeros((len(truth_t), 3))
    for a in range(0, len(truth_t), CHUNK_SAMPLES):
        st = run.sc.state(truth_t[a:a + CHUNK_SAMPLES])
        q_true[a:a + CHUNK_SAMPLES], rpy_true[a:a + CHUNK_SAMPLES] = st.q_rad, st.rpy_rad
        progress.advanced(len(st.q_rad))
    return {"true_q": Stream("true_q", "truth_joints", truth_t, q_true,
                             truth_joint_columns(run.arm.n_joints)),
            "true_base": Stream("true_base", "truth_base", truth_t, rpy_true, TRUTH_BASE_COLUMNS)}


def simulate(
    arm: ArmModel,
    scenario: str | Scenario,
    duration_s: float | None = None,
    rate_hz: float = 100.0,
    seed: int = 0,
    effects: Model | Iterable[Any] | None = None,
    realistic: bool = False,
    options: SimulationOptions = DEFAULT_OPTIONS,
) -> tuple[Recording, dict]:
    """Simulate ``scenario`` on ``arm`` for ``duration_s`` seconds (default: the scenario's).

    Every device samples at ``rate_hz`` unless ``options.rates_hz`` names it.
    ``effects``/``realistic``: see :func:`build_model`. ``options``: noise, per-device rates,
    the scenario's options, Earth's field, progress (:class:`SimulationOptions`). Returns
    ``(recording, truth)``.
    """
    if not rate_hz > 0:
        raise ValueError(f"rate must be positive, got {rate_hz!r} Hz")
    sc = resolve_scenario(arm, scenario, duration_s, seed, options.scenario_options)
    model, x = build_model(arm, effects, realistic, seed, earth_field_ut=options.earth_field_ut)
    rates = _device_rates(arm, rate_hz, options.rates_hz)
    smodels = stream_models(arm, {s: rates[d] for d in rates for s in device_streams(arm, d)})
    q0 = sc.state(np.zeros(1)).q_rad[0]
    run = _TrueRun(arm, sc, model, x, without_time_effects(model, x), q0, smodels)
    # devices grouped by rate: one state per grid and chunk, shared by the devices on it
    grids: dict[float, list[str]] = {}
    for d, r in rates.items():
        grids.setdefault(r, []).append(d)
    noise_rng = {s: _rng(seed, 2, i) for i, s in enumerate(smodels)} if options.noise else {}
    progress = _Progress(sum(_samples(sc.duration_s, r) for r in grids) + _samples(sc.duration_s, rate_hz),
                         options.progress)
    sampled: dict[str, tuple[np.ndarray, list[np.ndarray]]] = {}
    for r, devices in grids.items():
        sampled.update(_sample_grid(run, r, devices, noise_rng, progress))
    rec_streams: dict[str, Stream] = {}
    for s, m in smodels.items():
        t_s, parts = sampled[s]
        v = np.concatenate(parts) if parts else np.zeros((0, m.size), np.int64)
        rec_streams[s] = Stream(s, m.kind, t_s, v, m.channels)
    rec_streams.update(_truth_streams(run, rate_hz, progress))
    meta = {"generator": "armfusion simulate", "arm": arm.name, "scenario": sc.name, "seed": int(seed),
            "rate_hz": float(rate_hz), "realistic": bool(realistic), "noise": bool(options.noise)}
    device_rate = {s: rates[d] for d in rates for s in device_streams(arm, d)}
    truth = truth_document(arm, sc, model, x, run.q0, TruthSettings(
        "armfusion simulate", rate_hz, seed, realistic, rates_hz=rates, noise=options.noise,
        gravity_mps2=GRAVITY_MPS2,
        streams={s: {"samples": len(st), "rate_hz": device_rate.get(s, float(rate_hz))}
                 for s, st in rec_streams.items()}))
    return Recording(rec_streams, meta), truth


@dataclass(frozen=True)
class TruthSettings:
    """The settings a truth document records of the run that made it. Those left ``None``
    are left out of it (the fakes' run has no per-device rates, noise switch or streams)."""

    generator: str
    """The program that made the run (``armfusion simulate``, ``armfusion drivers --fake``)."""
    rate_hz: float
    seed: int
    realistic: bool
    rates_hz: dict | None = None
    """Each device's sample rate, Hz."""
    noise: bool | None = None
    gravity_mps2: float | None = None
    streams: dict | None = None
    """Per stream: its samples and rate."""


def truth_document(arm: ArmModel, sc: Scenario, model: Model, x: np.ndarray, q0: np.ndarray,
                   settings: TruthSettings) -> dict:
    """The JSON-ready truth of a simulated run (``REC.truth.json``): the arm, the scenario,
    the settings, every effect's true parameters as config entries, the encoders' zero, the
    world and its temperature, the scenario's events."""
    temp = sc.temperature(np.array([0.0, sc.duration_s]))
    st = settings
    optional = {"rates_hz": st.rates_hz, "noise": None if st.noise is None else bool(st.noise),
                "gravity_mps2": st.gravity_mps2, "streams": st.streams}
    doc = {
        "format": TRUTH_FORMAT,
        "generator": st.generator,
        "arm": arm.name,
        "config": arm.source,
        "scenario": sc.name,
        "duration_s": float(sc.duration_s),
        "rate_hz": float(st.rate_hz),
        "rates_hz": st.rates_hz,
        "seed": int(st.seed),
        "realistic": bool(st.realistic),
        "noise": optional["noise"],
        "effects": entries_from_model(model, x),
        "encoder_zero_rad": q0.tolist(),
        "earth_field_world_ut": model.earth_field_W_ut.tolist(),
        "world_frame": "x magnetic north, z up; base attitude R_WB = Rz(yaw) Ry(pitch) Rx(roll)",
        "gravity_mps2": st.gravity_mps2,
        "temperature_c": {"start": float(temp[0]), "end": float(temp[1])},
        "events": sc.events,
        "streams": st.streams,
    }
    return {k: v for k, v in doc.items() if not (k in optional and optional[k] is None)}


def true_zero_offsets_rad(truth: dict, joint_names: Iterable[str]) -> np.ndarray:
    """Per joint, the true DH zero offset (the ``joint_offset`` effects of a truth document,
    ``REC.truth.json``), rad; zero for a joint without one."""
    names = list(joint_names)
    out = np.zeros(len(names))
    for e in truth.get("effects", ()):
        if e.get("effect") == "joint_offset" and e.get("target") in names:
            out[names.index(e["target"])] += float(np.ravel(e["params"]["offset_rad"])[0])
    return out


def angle_truth(true_q: Stream, truth: dict, joint_names: Iterable[str]) -> Stream:
    """The joint angles an absolute estimator must find, to score it: the simulated
    controller angle (``true_q``) plus each joint's true zero offset. A relative encoder's
    zero is whatever the startup makes it, and no gravity reading can tell the DH zero's
    assembly error from the angle, so the angle that puts the nominal DH model's links where
    they really are is the one to find."""
    off = true_zero_offsets_rad(truth, joint_names)
    return Stream(true_q.name, true_q.kind, true_q.t_s, true_q.values + off, true_q.channels)
