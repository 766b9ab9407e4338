"""Scenarios: how the arm's joints and the chair move over time, as smooth functions.

A :class:`Scenario` gives the full :class:`~armfusion.models.motion.MotionState` at any instants
``t`` (vectorised; no loop per sample), with joint rates and accelerations and the base's
angular velocity, angular acceleration and linear acceleration that are the exact
derivatives of the poses it gives. That is what lets the simulator sample each device at
its own (time-shifted) instants, and what the finite-difference tests check.

Scenarios (``make_scenario(arm, name, …)``):

- ``startup``: one still pose (the arm's ready pose by default), the chair parked.
- ``static-poses``: K random still poses inside the joint limits (a quarter of them with
  a joint axis within 3° of vertical, for the chair's actual tilt: gimbal lock), each
  held a few seconds, with slow minimum-jerk moves between them.
- ``renk-maneuver``: the sensor-calibration article's sweep, scaled to this arm: the
  first joint sweeps slowly ("yaw", the article's 3.1 °/s on average), the last joint
  rolls continuously (13.9 °/s), the joints between nod (0.87-5 °/s), each a sinusoid of
  its own period over a wide part of its range; 27.74 min by default, as the article.
- ``renk-ramp``: the same sweep with the chair parked in turn level, on a 1:12 ramp facing
  up, facing down and across it both ways (driven, turned on the spot and rolled onto the
  slope between stances): gravity reaches the base from several directions.
- ``daily-use``: reaching motions at up to 25 °/s (out to a target, a pause, maybe a
  second target, back) while the chair drives: starts and stops at up to 1 m/s², turns at up to 60 °/s (0.6
  m/s² sideways), turns on the spot, ramps of up to 1:12 and cross-slopes of 1:50. The
  chair is a 2-D vehicle (speed along its forward axis, yaw rate) whose attitude follows
  the ground; the arm's base is mounted off its turning centre.
- ``excitation``: a short sequence where everything moves at once (every joint, the
  chair spinning on the spot and rocking on a ramp, the temperature rising): what
  identification tests need to see every effect.
- ``compass-turn``: the chair turns once on the spot (360° at 45 °/s) between two still
  stretches, the arm parked at its ready pose: every heading seen once, what the
  compass's iron needs (``calibrate sensors --compass-drive``).

The motion profiles are quintic "minimum-jerk" blends between levels (continuous up to
the acceleration), so accelerations and their derivatives stay finite and realistic.

The package: :mod:`~armfusion.models.trajectories.paths` (the smooth pieces),
:mod:`~armfusion.models.trajectories.scenario` (:class:`Scenario` and what the families share), one
module per family (:mod:`~armfusion.models.trajectories.still`, :mod:`~armfusion.models.trajectories.renk`,
:mod:`~armfusion.models.trajectories.daily`), and here the table of scenarios by name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from armfusion.models.arm import ArmModel
from armfusion.models.trajectories.daily import compass_turn, daily_use, excitation
from armfusion.models.trajectories.paths import (
    BaseMotion,
    BasePath,
    DrivingChair,
    JointPath,
    ParkedBase,
    SinePath,
    SmoothSteps,
    StepsBuilder,
    WaypointPath,
    min_jerk_duration,
)
from armfusion.models.trajectories.renk import (
    RAMP_SLOPE,
    RAMP_STANCES,
    RENK_DURATION_S,
    RENK_RATES_DEG_S,
    RampDrive,
    renk_maneuver,
    renk_ramp,
)
from armfusion.models.trajectories.scenario import Scenario, scenario_rng, warm_up
from armfusion.models.trajectories.still import random_still_poses, startup, static_poses


@dataclass(frozen=True)
class ScenarioSpec:
    build: Callable
    default_duration_s: float
    description: str


SCENARIOS: dict[str, ScenarioSpec] = {
    "startup": ScenarioSpec(startup, 10.0, "one still pose (the ready pose), the chair parked"),
    "static-poses": ScenarioSpec(static_poses, 120.0,
                                 "random still poses (a quarter near gimbal lock), slow moves between"),
    "renk-maneuver": ScenarioSpec(renk_maneuver, RENK_DURATION_S,
                                  "the sensor-calibration article's yaw / nod / roll sweep"),
    "renk-ramp": ScenarioSpec(renk_ramp, 600.0,
                              "the renk sweep with the chair parked level, on a 1:12 ramp facing up, "
                              "down and across both ways (separates the IMU's mount from the tilt)"),
    "daily-use": ScenarioSpec(daily_use, 600.0, "reaching while the chair drives, turns, takes ramps"),
    "excitation": ScenarioSpec(excitation, 60.0, "everything moves at once (for identification tests)"),
    "compass-turn": ScenarioSpec(compass_turn, 14.8, "one turn on the spot (360° at 45 °/s), the arm "
                                 "parked: the compass's iron (calibrate sensors --compass-drive)"),
}


def make_scenario(arm: ArmModel, name: str, duration_s: float | None = None, seed: int = 0,
                  **options) -> Scenario:
    """Build the scenario ``name`` for ``arm`` (seeded: the same seed, the same motion)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    spec = SCENARIOS[name]
    d = spec.default_duration_s if duration_s is None else float(duration_s)
    if not d > 0:
        raise ValueError(f"duration must be positive, got {duration_s!r} s")
    return spec.build(arm, d, scenario_rng(seed), **options)


__all__ = [
    "RAMP_SLOPE", "RAMP_STANCES", "RENK_DURATION_S", "RENK_RATES_DEG_S", "SCENARIOS", "BaseMotion",
    "BasePath", "DrivingChair", "JointPath", "ParkedBase", "Scenario", "ScenarioSpec", "SinePath",
    "RampDrive", "SmoothSteps", "StepsBuilder", "WaypointPath", "compass_turn", "daily_use", "excitation",
    "make_scenario",
    "min_jerk_duration", "random_still_poses", "renk_maneuver", "renk_ramp", "startup",
    "static_poses", "warm_up",
]
