"""A planned self-calibration maneuver (``armfusion plan-maneuver``): a sequence of still
poses, each held for a dwell, joined by minimum-jerk moves, the chair parked.

:class:`PlannedManeuver` is the plan itself (poses, dwells, move durations), as the
planner writes it and a maneuver file holds it (:meth:`PlannedManeuver.as_dict`,
:meth:`PlannedManeuver.from_dict`: the file's shape, checked here; whether the plan is
safe for this arm is checked in ``armfusion.fusion.identification.planner.maneuver_problems``).
:func:`planned_scenario` turns it into a :class:`~armfusion.models.trajectories.scenario.Scenario` the
simulator plays (a :class:`~armfusion.models.trajectories.paths.WaypointPath`, the same pieces as
``static-poses``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG
from armfusion.models.trajectories.paths import StepsBuilder, WaypointPath
from armfusion.models.trajectories.scenario import Scenario, parked_chair, scenario_rng, warm_up

MAX_POSES = 1000
"""A maneuver file holds at most this many poses (a plan of 60 s has about 15)."""


@dataclass(frozen=True)
class PlannedManeuver:
    """Poses ``(K, n)`` rad, each held ``dwell_s[k]`` seconds, reached from the previous one
    by a minimum-jerk move of ``move_s[k - 1]`` seconds (``move_s``: ``K - 1`` values)."""

    joint_names: tuple[str, ...]
    poses_rad: np.ndarray
    dwell_s: np.ndarray
    move_s: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(np.sum(self.dwell_s) + np.sum(self.move_s))

    def schedule(self) -> list[tuple[float, float, float]]:
        """Per pose: (move start, dwell start, dwell end) in seconds from the start."""
        out, t = [], 0.0
        for k in range(len(self.poses_rad)):
            t_move = t
            if k:
                t += float(self.move_s[k - 1])
            out.append((t_move, t, t + float(self.dwell_s[k])))
            t += float(self.dwell_s[k])
        return out

    def until(self, duration_s: float) -> PlannedManeuver:
        """The maneuver's first poses, as many as end their dwell within ``duration_s``
        seconds (a shorter maneuver of the same poses; at least the first)."""
        ends = np.array([end for _, _, end in self.schedule()])
        k = max(1, int(np.sum(ends <= duration_s + 1e-9)))
        return PlannedManeuver(self.joint_names, self.poses_rad[:k], self.dwell_s[:k], self.move_s[:k - 1])

    def as_dict(self) -> dict[str, Any]:
        """The maneuver file's content (degrees and seconds, rounded to what a controller needs)."""
        return {"joints": list(self.joint_names),
                "poses": [{"pose_deg": [round(float(v), 4) for v in np.degrees(q)],
                           # rounded up: a move never faster than planned
                           "move_s": math.ceil(float(self.move_s[k - 1]) * 1e4) / 1e4 if k else 0.0,
                           "dwell_s": round(float(self.dwell_s[k]), 4)}
                          for k, q in enumerate(self.poses_rad)]}

    @classmethod
    def from_dict(cls, data: Any, where: str = "maneuver") -> PlannedManeuver:
        """Read a maneuver file's content, refusing a malformed one by key (``where``: the
        file's name, for the messages)."""
        if not isinstance(data, dict) or not isinstance(data.get("joints"), list) \
                or not isinstance(data.get("poses"), list):
            raise ValueError(f"{where}: expected a mapping with 'joints' (names) and 'poses' (a list)")
        names = data["joints"]
        if not names or not all(isinstance(n, str) and 0 < len(n) <= 40 for n in names):
            raise ValueError(f"{where}: 'joints' must be a list of joint names")
        poses = data["poses"]
        if not 1 <= len(poses) <= MAX_POSES:
            raise ValueError(f"{where}: 'poses' must hold 1 to {MAX_POSES} poses, not {len(poses)}")
        q, dwell, move = [], [], []
        for k, p in enumerate(poses):
            at = f"{where}: poses[{k}]"
            if not isinstance(p, dict):
                raise ValueError(f"{at}: expected a mapping with pose_deg, move_s, dwell_s")
            pose = p.get("pose_deg")
            if not isinstance(pose, list) or len(pose) != len(names):
                raise ValueError(f"{at}.pose_deg: expected {len(names)} angles (one per joint)")
            vals = []
            for key, v in [("pose_deg", x) for x in pose] + [("dwell_s", p.get("dwell_s")),
                                                              ("move_s", p.get("move_s", 0.0))]:
                if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
                    shown = repr(v)
                    raise ValueError(f"{at}.{key}: expected a finite number, got "
                                     f"{shown[:30] + '…' if len(shown) > 30 else shown}")
                vals.append(float(v))
            *pose_deg, d, m = vals
            if d < 0:
                raise ValueError(f"{at}.dwell_s: must not be negative, got {d:g}")
            if k and m <= 0:
                raise ValueError(f"{at}.move_s: a move takes a positive time, got {m:g}")
            q.append(np.radians(pose_deg))
            dwell.append(d)
            if k:
                move.append(m)
        return cls(tuple(names), np.array(q), np.array(dwell), np.array(move))


def planned_scenario(arm: ArmModel, maneuver: PlannedManeuver, rng: np.random.Generator,
                     tilt_sigma_rad: float = 0.5 * DEG) -> Scenario:
    """The maneuver as a scenario: its poses held and joined by minimum-jerk moves, the chair
    parked at a random tilt (``tilt_sigma_rad``, as ``renk-maneuver``'s) and heading, the
    electronics warming up. After the last dwell the arm stays at the last pose."""
    if tuple(maneuver.joint_names) != tuple(arm.joint_names):
        raise ValueError(f"the maneuver's joints {list(maneuver.joint_names)[:10]} are not the arm's "
                         f"{list(arm.joint_names)}")
    b = StepsBuilder(maneuver.poses_rad[0])
    events = []
    for k, (q, (t_move, t0, t1)) in enumerate(zip(maneuver.poses_rad, maneuver.schedule(), strict=True)):
        if k:
            b.move(q, float(maneuver.move_s[k - 1]))
            events.append({"t_start_s": round(t_move, 3), "t_end_s": round(t0, 3),
                           "what": f"move to pose {k}"})
        b.hold(float(maneuver.dwell_s[k]))
        events.append({"t_start_s": round(t0, 3), "t_end_s": round(t1, 3), "what": f"still pose {k}",
                       "pose_deg": np.degrees(q).round(3).tolist()})
    return Scenario("planned", arm, maneuver.duration_s, WaypointPath(b.build()),
                    parked_chair(rng, tilt_sigma_rad), warm_up(), events)


def played_scenario(arm: ArmModel, maneuver: PlannedManeuver, seed: int) -> Scenario:
    """The maneuver as ``armfusion simulate --maneuver M --seed S`` plays it: the chair's tilt
    and heading drawn from recording seed ``seed`` (its scenario stream, as a named scenario's)."""
    return planned_scenario(arm, maneuver, scenario_rng(seed))
