"""Scenarios of a still arm: ``startup`` (one pose) and ``static-poses`` (random still
poses, a share near gimbal lock, slow moves between), and the random poses themselves."""

from __future__ import annotations

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.kinematics import joint_axis_angle_to_vertical
from armfusion.models.rotations import DEG, up_from_tilt
from armfusion.models.trajectories.paths import SmoothSteps, StepsBuilder, WaypointPath, min_jerk_duration
from armfusion.models.trajectories.scenario import Scenario, clip_pose, margin_limits, parked_chair, warm_up


def startup(arm: ArmModel, duration_s: float, rng: np.random.Generator, pose_rad=None) -> Scenario:
    q = arm.ready_pose_rad if pose_rad is None else clip_pose(arm, np.asarray(pose_rad, float))
    path = WaypointPath(SmoothSteps([], [], [q]))
    return Scenario("startup", arm, duration_s, path, parked_chair(rng), warm_up(),
                    [{"t_start_s": 0.0, "t_end_s": duration_s, "what": "still at one pose",
                      "pose_deg": np.degrees(q).round(3).tolist()}])


def random_still_poses(arm: ArmModel, k: int, rng: np.random.Generator,
                       near_lock_share: float = 0.25, lock_deg: float = 3.0,
                       up_0: np.ndarray | None = None) -> np.ndarray:
    """``k`` poses inside the limits; a share of them with some joint axis within
    ``lock_deg`` of vertical (``up_0``: world up in the base frame; default level), picked
    from a large random pool."""
    lo, hi = margin_limits(arm)
    pool = rng.uniform(lo, hi, size=(max(20000, 50 * k), arm.n_joints))
    ang = joint_axis_angle_to_vertical(arm, pool, up_0)  # (P, n)
    # a joint whose axis is fixed in the base (the first) is as near vertical as the chair's
    # tilt makes it, whatever the pose: not what "a pose near gimbal lock" means
    fixed = np.ptp(ang, axis=0) < 1e-9
    ang = np.where(fixed, np.inf, ang)
    near = np.flatnonzero(ang.min(axis=1) < lock_deg * DEG)
    n_near = min(len(near), int(round(near_lock_share * k)))
    chosen_near = rng.choice(near, size=n_near, replace=False) if n_near else np.array([], int)
    rest = np.setdiff1d(np.arange(len(pool)), near)
    chosen = np.concatenate([chosen_near, rng.choice(rest, size=k - n_near, replace=False)])
    rng.shuffle(chosen)
    return pool[chosen]


def static_poses(arm: ArmModel, duration_s: float, rng: np.random.Generator,
                 hold_s: float = 4.0, peak_rate_rad_s: float = 30 * DEG) -> Scenario:
    base = parked_chair(rng)
    up_0 = up_from_tilt(base.rpy[0], base.rpy[1])
    poses = random_still_poses(arm, max(1, int(duration_s // (hold_s + 3.0)) + 1), rng, up_0=up_0)
    b = StepsBuilder(poses[0])
    events = []
    for k, q in enumerate(poses):
        if k:
            T = min_jerk_duration(q - b.level, peak_rate_rad_s, min_s=2.0)
            b.move(q, T)
        t0 = b.t
        b.hold(hold_s)
        events.append({"t_start_s": round(t0, 3), "t_end_s": round(b.t, 3), "what": f"still pose {k}",
                       "pose_deg": np.degrees(q).round(3).tolist(),
                       "min_axis_to_vertical_deg": float(np.degrees(
                           joint_axis_angle_to_vertical(arm, q, up_0).min()))})
        if b.t >= duration_s:
            break
    return Scenario("static-poses", arm, duration_s, WaypointPath(b.build()), base, warm_up(),
                    [e for e in events if e["t_start_s"] < duration_s])
