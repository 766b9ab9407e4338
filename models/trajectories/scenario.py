"""What a scenario is (:class:`Scenario`: joints, base and temperature as functions of
time) and what the scenario families share: the warm-up of the electronics, poses kept
inside the joint limits, the chair parked at a random attitude.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.motion import MotionState
from armfusion.models.rotations import DEG
from armfusion.models.trajectories.paths import BasePath, JointPath, ParkedBase

SCENARIO_STREAM = 0x5CE
"""The stream of a recording's seed that draws its scenario (the chair's tilt and heading, a
sweep's random poses), apart from the simulator's noise."""


def scenario_rng(seed: int) -> np.random.Generator:
    """The generator a scenario of recording seed ``seed`` is drawn from (``make_scenario``,
    a planned maneuver played by ``armfusion simulate --maneuver --seed``)."""
    return np.random.default_rng([int(seed), SCENARIO_STREAM])


def warm_up(t0_c: float = 22.0, rise_c: float = 8.0, tau_s: float = 600.0) -> Callable:
    """Electronics warming after power-up: ``T0 + rise·(1 - exp(-t/τ))`` °C."""
    return lambda t: t0_c + rise_c * (1.0 - np.exp(-np.asarray(t, float) / tau_s))


@dataclass
class Scenario:
    """A named motion: joints and base as functions of time, and a temperature profile."""

    name: str
    arm: ArmModel
    duration_s: float
    joints: JointPath
    base: BasePath
    temperature: Callable[[np.ndarray], np.ndarray]
    events: list[dict] = field(default_factory=list)

    def state(self, t_s: np.ndarray) -> MotionState:
        t = np.asarray(t_s, float).reshape(-1)
        q, qd, qdd = self.joints(t)
        b = self.base(t)
        return MotionState(t, q, qd, qdd, b.R_WB, b.omega_B, b.omega_dot_B, b.accel_B,
                           self.temperature(t))

    __call__ = state

    def base_position_m(self, t_s: np.ndarray) -> np.ndarray:
        return self.base.position_m(t_s)


def margin_limits(arm: ArmModel, margin_rad: float = 5 * DEG):
    lo, hi = arm.min_rad + margin_rad, arm.max_rad - margin_rad
    return lo, np.maximum(hi, lo)


def clip_pose(arm: ArmModel, q):
    lo, hi = margin_limits(arm)
    return np.clip(q, lo, hi)


def parked_chair(rng: np.random.Generator, tilt_sigma_rad: float = 1.5 * DEG) -> ParkedBase:
    roll, pitch = np.clip(rng.normal(0, tilt_sigma_rad, 2), -4 * DEG, 4 * DEG)
    return ParkedBase(float(roll), float(pitch), float(rng.uniform(-np.pi, np.pi)))
