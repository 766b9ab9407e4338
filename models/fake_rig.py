"""The simulator feeding the fake devices: one :class:`~armfusion.sensors.fakes.physics.PhysicsSource`
per device, from a simulator run.

``sensors/`` may not import ``models/``, so the bridge lives here, beside the simulator
(it imports only models and sensors; ``armfusion drivers --fake`` uses it). :func:`simulate_physics`
runs the simulator's measurement chain (scenario motion, the model with its effects,
time offsets) on a fine time grid (:data:`FINE_RATE_HZ`) and keeps the *physical*
values, before any noise or rounding:

- each link accelerometer: its specific force in g in its own axes, with motion and
  every effect (mount, scale, bias…) as the simulator applies them;
- the IMU: specific force (g), angular rate (rad/s), magnetic field (µT, in the MPU
  accelerometer's axes) and die temperature (°C);
- the encoders: their counts (float, before rounding).

:class:`SimulatedPhysics` then gives a device's values at any time on the fakes' clock by
linear interpolation (``t_sim = t_clock - epoch_s``; the scenario's t = 0 is ``epoch_s``,
the moment the rig powers up; before 0 and after the end the values are held). The fake
devices do the rest: scaling to counts, rounding, saturation, their register formats.

Noise: the fakes model ideal parts, so the sensors' white noise (the simulator's
datasheet rms at the sampling rate, :mod:`armfusion.models.sensor_models`) is added here, drawn
per call from a seeded generator per device (``noise=False`` leaves it out).

An ADXL345 whose config sets ``lsb_per_g`` other than the nominal 256 is fed
``f · lsb_per_g / 256``, so that the fake (which scales by the nominal 256 LSB/g)
gives the counts the simulator would.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.effects import Model
from armfusion.models.effects.base import device_streams
from armfusion.models.sensor_models import ADXL345_LSB_PER_G, stream_models
from armfusion.models.simulator import (
    DEFAULT_OPTIONS,
    SimulationOptions,
    TruthSettings,
    build_model,
    resolve_scenario,
    truth_document,
    without_time_effects,
)
from armfusion.models.trajectories import Scenario
from armfusion.sensors.samples import TRUTH_BASE_COLUMNS, Stream, truth_joint_columns

FINE_RATE_HZ = 1000.0
"""Rate of the simulator's grid; at 1 kHz linear interpolation is off by < 1e-5 g for
the scenarios' motions (1 ms² · |f''| / 8), far below one ADXL345 LSB (3.9 mg)."""
CHUNK_SAMPLES = 30000
IMU_QUANTITIES = {"specific_force": "imu_acc", "angular_rate": "imu_gyro",
                  "magnetic_field": "imu_mag", "temperature": "imu_temp"}


@dataclass(frozen=True)
class SimulatedRun:
    """The simulator's physical values on a fine grid, for one scenario on one arm.

    ``t_s (M,)`` is the grid (from 0, at ``rate_hz``); ``values[stream] (M, k)`` the
    physical values (g, rad/s, µT, °C; ``enc`` in float counts) without time offsets;
    ``noise_rms[stream]`` the white noise each device adds, in the same units;
    ``time_offset_s[stream]`` its device's time offset (its samples are the values
    ``offset`` before their stamps: :meth:`at` applies it); ``truth`` the JSON-ready truth
    (effects as config entries, events, settings) as ``armfusion simulate`` writes it.
    """

    arm: ArmModel
    scenario: Scenario
    model: Model
    x: np.ndarray
    rate_hz: float
    t_s: np.ndarray
    values: dict[str, np.ndarray]
    noise_rms: dict[str, np.ndarray]
    time_offset_s: dict[str, float]
    truth: dict

    def at(self, stream: str, t_sim_s: float) -> np.ndarray:
        """The noise-free reading of ``stream`` stamped at simulation time ``t_sim_s``
        (the value ``time_offset_s`` earlier; held outside the grid)."""
        return _interp(self.values[stream], self.rate_hz, t_sim_s - self.time_offset_s[stream])

    def at_many(self, stream: str, t_sim_s: np.ndarray) -> np.ndarray:
        """:meth:`at` for an array of times: ``(N, k)``."""
        y = self.values[stream]
        t = np.asarray(t_sim_s, dtype=float) - self.time_offset_s[stream]
        return np.stack([np.interp(t, self.t_s, y[:, j]) for j in range(y.shape[1])], axis=1)

    def truth_streams(self, rate_hz: float, t_end_s: float) -> dict[str, Stream]:
        """``true_q`` and ``true_base`` at ``rate_hz`` from 0 to ``t_end_s`` (the
        scenario's exact state, as the simulator writes them)."""
        n = int(np.floor(max(t_end_s, 0.0) * rate_hz + 1e-9)) + 1
        t = np.arange(n) / rate_hz
        st = self.scenario.state(t)
        return {
            "true_q": Stream("true_q", "truth_joints", t, st.q_rad,
                             truth_joint_columns(self.arm.n_joints)),
            "true_base": Stream("true_base", "truth_base", t, st.rpy_rad, TRUTH_BASE_COLUMNS),
        }


def _interp(y: np.ndarray, rate_hz: float, t: float) -> np.ndarray:
    """Row of ``y`` (sampled at ``k / rate_hz``) at time ``t``, linear; held at the ends."""
    if y.shape[0] == 1:
        return y[0].copy()
    pos = min(max(t * rate_hz, 0.0), y.shape[0] - 1.0)
    i = min(int(pos), y.shape[0] - 2)
    u = pos - i
    return y[i] * (1.0 - u) + y[i + 1] * u


def simulate_physics(
    arm: ArmModel,
    scenario: str | Scenario,
    duration_s: float,
    *,
    seed: int = 0,
    effects: Model | Iterable[Any] | None = None,
    realistic: bool = False,
    sample_rate_hz: float = 100.0,
    options: SimulationOptions = DEFAULT_OPTIONS,
) -> SimulatedRun:
    """The physical values of ``scenario`` on ``arm`` from 0 to ``duration_s`` on a grid at
    :data:`FINE_RATE_HZ`, with the same scenario, effects and seed semantics as
    :func:`armfusion.models.simulator.simulate` (the same seed gives the same motion and arm).
    ``sample_rate_hz`` (the devices' read rate) sets the noise rms. Of ``options`` the
    scenario's options and Earth's field are read (the fake devices add the noise,
    :func:`physics_for`, and sample at their own rates).
    """
    if not duration_s > 0:
        raise ValueError(f"duration must be positive, got {duration_s!r} s")
    rate_hz = FINE_RATE_HZ
    sc = resolve_scenario(arm, scenario, duration_s, seed, options.scenario_options)
    model, x = build_model(arm, effects, realistic, seed, earth_field_ut=options.earth_field_ut)
    smodels = stream_models(arm, float(sample_rate_hz))
    streams = tuple(model.stream_names)
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    t = np.arange(n) / rate_hz
    q0 = sc.state(np.zeros(1)).q_rad[0]
    # time offsets as the simulator applies them: predict without them, then read each
    # device ``offset`` earlier on the grid (SimulatedRun.at)
    offsets = {s: off for d, off in model.time_offsets_s(x).items() for s in device_streams(arm, d)}
    x_now = without_time_effects(model, x)
    parts: dict[str, list[np.ndarray]] = {s: [] for s in streams}
    for a in range(0, n, CHUNK_SAMPLES):
        st = sc.state(t[a:a + CHUNK_SAMPLES])
        pred = model.predict(st, x_now, streams, encoder_zero_rad=q0, units="physical")
        for s in streams:
            parts[s].append(pred[s])
    values: dict[str, np.ndarray] = {}
    noise: dict[str, np.ndarray] = {}
    adxl = {m.name for m in arm.link_accelerometers if m.type == "adxl345"}
    for s in streams:
        v = np.concatenate(parts[s])
        sm = smodels[s]
        if s == "enc":
            v = sm.to_counts(v)
        elif s in adxl:
            # fed to a fake that scales by the nominal 256 LSB/g
            scale = sm.gain / ADXL345_LSB_PER_G
            v = v * scale
            noise[s] = sm.noise_counts_rms / ADXL345_LSB_PER_G
        if s not in noise:
            noise[s] = sm.noise_physical_rms()
        v.setflags(write=False)
        values[s] = v
    truth = truth_document(arm, sc, model, x, q0, TruthSettings("armfusion drivers --fake", sample_rate_hz,
                                                                seed, realistic))
    return SimulatedRun(arm, sc, model, np.array(x), float(rate_hz), t, values, noise,
                        {s: offsets.get(s, 0.0) for s in streams}, truth)


class SimulatedPhysics:
    """One device's :class:`~armfusion.sensors.fakes.physics.PhysicsSource` from a :class:`SimulatedRun`.

    ``device``: a link accelerometer's name, or the IMU's name (then all four quantities
    come from the ``imu_*`` streams). ``epoch_s``: the fakes' clock time of the
    scenario's t = 0. ``noise``: add the device's white noise (seeded by ``seed``).
    A link accelerometer reports no rotation, no field and the scenario's temperature
    (the ADXL345 fake reads only the specific force).
    """

    def __init__(self, run: SimulatedRun, device: str, epoch_s: float, *, noise: bool = True,
                 seed: int = 0):
        arm = run.arm
        self.run = run
        self.device = device
        self.epoch_s = float(epoch_s)
        self.is_imu = arm.imu is not None and device == arm.imu.name
        if not self.is_imu and device not in run.values:
            known = [s.name for s in arm.link_accelerometers] + ([arm.imu.name] if arm.imu else [])
            raise ValueError(f"no device {device!r} in the simulation; devices: {', '.join(known)}")
        self._force = IMU_QUANTITIES["specific_force"] if self.is_imu else device
        self._noise = noise
        self._rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 3, _stable_id(device)])

    def _value(self, stream: str, t_s: float) -> np.ndarray:
        v = self.run.at(stream, t_s - self.epoch_s)
        if self._noise:
            v = v + self._rng.standard_normal(v.shape) * self.run.noise_rms[stream]
        return v

    def true_specific_force_g(self, t_s: float) -> np.ndarray:
        """The specific force without noise, at clock time ``t_s``."""
        return self.run.at(self._force, t_s - self.epoch_s)

    # PhysicsSource ---------------------------------------------------------------------

    def specific_force_g(self, t_s: float) -> np.ndarray:
        return self._value(self._force, t_s)

    def angular_rate_rad_s(self, t_s: float) -> np.ndarray:
        if not self.is_imu:
            return np.zeros(3)
        return self._value(IMU_QUANTITIES["angular_rate"], t_s)

    def magnetic_field_uT(self, t_s: float) -> np.ndarray:
        if not self.is_imu:
            return np.zeros(3)
        return self._value(IMU_QUANTITIES["magnetic_field"], t_s)

    def temperature_c(self, t_s: float) -> float:
        if not self.is_imu:
            return float(self.run.scenario.temperature(np.array([t_s - self.epoch_s]))[0])
        return float(self._value(IMU_QUANTITIES["temperature"], t_s)[0])


def _stable_id(name: str) -> int:
    return int.from_bytes(name.encode()[:8].ljust(8, b"\0"), "little") & 0xFFFFFFFF


def physics_for(run: SimulatedRun, devices: Iterable[str], epoch_s: float, *, noise: bool = True,
                seed: int = 0) -> dict[str, SimulatedPhysics]:
    """A :class:`SimulatedPhysics` per device name (for ``FakeRig(clock, physics=...)``)."""
    return {d: SimulatedPhysics(run, d, epoch_s, noise=noise, seed=seed) for d in devices}


def encoder_counts_at(run: SimulatedRun, epoch_s: float):
    """``counts_at(t)`` for :class:`~armfusion.sensors.encoders.SimulatedEncoderFeed`: the encoders'
    counts at clock time ``t`` (rounded, as the controller counts them)."""

    def counts_at(t_s: float) -> list[int]:
        return [int(c) for c in np.rint(run.at("enc", t_s - epoch_s))]

    return counts_at
