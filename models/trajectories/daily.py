"""Scenarios where the chair moves: ``daily-use`` (reaching while the chair drives, turns
and takes ramps), ``excitation`` (everything at once, for identification) and
``compass-turn`` (one turn on the spot, the arm parked: what the compass's iron needs)."""

from __future__ import annotations

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG
from armfusion.models.trajectories.paths import (
    CHAIR_LEVER_M,
    DrivingChair,
    SinePath,
    StepsBuilder,
    WaypointPath,
    chair_lever_m,
    min_jerk_duration,
)
from armfusion.models.trajectories.scenario import Scenario, clip_pose, margin_limits, warm_up


def _reach_path(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float,
                home, spread_rad: float = 35 * DEG, peak_rate_rad_s: float = 25 * DEG):
    b = StepsBuilder(home)
    b.hold(still_s)
    events = []
    while b.t < duration_s:
        b.hold(rng.uniform(2.0, 20.0))
        t0 = b.t
        for _ in range(rng.integers(1, 3)):  # out to one or two targets
            target = clip_pose(arm, home + rng.normal(0, spread_rad, arm.n_joints))
            b.move(target, min_jerk_duration(target - b.level, peak_rate_rad_s, 1.5))
            b.hold(rng.uniform(1.0, 6.0))
        b.move(home, min_jerk_duration(home - b.level, peak_rate_rad_s, 1.5))
        events.append({"t_start_s": round(t0, 3), "t_end_s": round(b.t, 3), "what": "arm reaches"})
    return WaypointPath(b.build()), events


RAMP_ANGLE_RAD = float(np.arctan(1 / 12))
"""The steepest ramp of a drive (1:12); a ramp taken is 0.5-1 of it."""
CROSS_SLOPE_RAD = float(np.arctan(1 / 50))
"""A pavement's cross-slope (1:50)."""


class _DrivenChair:
    """The driven chair's four channels (speed, yaw rate, pitch, roll), built in step."""

    def __init__(self, still_s: float):
        self.speed, self.yaw = StepsBuilder(0.0), StepsBuilder(0.0)
        self.pitch, self.roll = StepsBuilder(0.0), StepsBuilder(0.0)
        self.sync(still_s)

    def sync(self, t_s: float) -> None:
        """Hold every channel until ``t_s``."""
        for ch in (self.speed, self.yaw, self.pitch, self.roll):
            ch.hold(t_s - ch.t)

    def build(self, yaw0: float, lever_m) -> DrivingChair:
        """The chair's motion, starting at heading ``yaw0``."""
        return DrivingChair(self.speed.build(), self.yaw.build(), self.pitch.build(), self.roll.build(),
                            yaw0, lever_m)


def _turn_on_the_spot(chair: _DrivenChair, rng: np.random.Generator, t: float) -> tuple[float, dict]:
    """A turn on the spot of 60-180° at 45 °/s from ``t``: when it ends, and its event."""
    ang = rng.uniform(60, 180) * DEG * rng.choice([-1, 1])
    r = 45 * DEG * np.sign(ang)
    Tr = 0.8
    cruise = abs(ang) / abs(r) - Tr
    chair.yaw.move([r], Tr).hold(cruise).move([0.0], Tr)
    event = {"t_start_s": round(t, 3), "t_end_s": round(chair.yaw.t, 3),
             "what": f"turn on the spot {np.degrees(ang):.0f}°"}
    return chair.yaw.t, event


def _cruise_piece(chair: _DrivenChair, rng: np.random.Generator, t: float, v: float) -> tuple[float, str]:
    """One piece of a cruise at ``v`` m/s from ``t``: straight on, a turn, a ramp up or down or
    a cross-slope; when it ends, and what it was."""
    kind = rng.choice(["straight", "turn", "ramp", "cross"], p=[0.35, 0.35, 0.15, 0.15])
    if kind == "straight":
        return t + rng.uniform(2.0, 10.0), ""
    if kind == "turn":
        r_max = min(60 * DEG, 0.6 / v)
        r = rng.uniform(0.5, 1.0) * r_max * rng.choice([-1, 1])
        ang = rng.uniform(30, 150) * DEG
        Tr = max(0.6, abs(r) / (90 * DEG))
        cruise = max(0.0, ang / abs(r) - Tr)
        chair.yaw.move([r], Tr).hold(cruise).move([0.0], Tr)
        return chair.yaw.t, f"turn {np.degrees(np.sign(r) * ang):.0f}°"
    up = rng.choice([-1, 1])
    level = (RAMP_ANGLE_RAD * rng.uniform(0.5, 1.0) if kind == "ramp" else CROSS_SLOPE_RAD) * up
    ch = chair.pitch if kind == "ramp" else chair.roll
    Tt = max(0.6, 0.6 / v)  # the wheelbase rolls onto the slope
    length = rng.uniform(2.0, 9.0)
    # nose up climbing: negative pitch in R = Rz Ry Rx
    ch.move([-level if kind == "ramp" else level], Tt).hold(length / v).move([0.0], Tt)
    if kind == "ramp":
        what = f"ramp 1:{round(1 / np.tan(abs(level)))} " + ("up" if up > 0 else "down")
    else:
        what = "cross-slope 1:50 " + ("right" if up > 0 else "left") + " low"
    return ch.t, what


def _drive(chair: _DrivenChair, rng: np.random.Generator, t: float) -> tuple[float, dict]:
    """A drive from ``t``: start, cruise in one to three pieces, stop; when it ends, and its
    event."""
    v = rng.uniform(0.4, 1.3)
    acc = rng.uniform(0.4, 1.0)
    Ta = np.sqrt(5.7735 * v / acc)  # quintic: peak acceleration 5.77·Δ/T²
    t0 = t
    chair.speed.move([v], Ta)
    t += Ta
    chair.sync(t)
    what = [f"drive {v:.1f} m/s"]
    for _ in range(rng.integers(1, 4)):  # cruise pieces: straight, a turn or a ramp
        t, piece = _cruise_piece(chair, rng, t, v)
        if piece:
            what.append(piece)
        chair.sync(t)
    dec = rng.uniform(0.4, 1.0)
    Td = np.sqrt(5.7735 * v / dec)
    chair.speed.move([0.0], Td)
    t += Td
    chair.sync(t)
    return t, {"t_start_s": round(t0, 3), "t_end_s": round(t, 3), "what": ", ".join(what)}


def _chair_path(duration_s: float, rng: np.random.Generator, still_s: float, yaw0: float,
                lever_m=CHAIR_LEVER_M):
    """Random drives: start, cruise with turns and ramps, stop; turns on the spot; pauses."""
    chair = _DrivenChair(still_s)
    events = []
    t = still_s
    while t < duration_s:
        t += rng.uniform(3.0, 20.0)  # pause
        chair.sync(t)
        if rng.uniform() < 0.2:
            t, event = _turn_on_the_spot(chair, rng, t)
        else:
            t, event = _drive(chair, rng, t)
        chair.sync(t)
        events.append(event)
    return chair.build(yaw0, lever_m), events


def daily_use(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float = 8.0) -> Scenario:
    home = arm.ready_pose_rad
    rng_arm, rng_chair = (np.random.default_rng(s) for s in rng.integers(0, 2**62, 2))
    joints, arm_events = _reach_path(arm, duration_s, rng_arm, still_s, home)
    chair, chair_events = _chair_path(duration_s, rng_chair, still_s, float(rng.uniform(-np.pi, np.pi)),
                                      chair_lever_m(arm))
    events = [{"t_start_s": 0.0, "t_end_s": still_s, "what": "still (startup)"}]
    events += sorted(arm_events + chair_events, key=lambda e: e["t_start_s"])
    return Scenario("daily-use", arm, duration_s, joints, chair, warm_up(),
                    [e for e in events if e["t_start_s"] < duration_s])


def excitation(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float = 2.0) -> Scenario:
    """Everything moves: every joint sinusoidally (periods 6-25 s over ±35 % of its range),
    the chair turning on the spot and rocking on ramps and cross slopes, temperature rising
    fast (6 °C over the first minutes)."""
    n = arm.n_joints
    lo, hi = margin_limits(arm)
    center = 0.5 * (lo + hi)
    amp = np.minimum(0.35 * (hi - lo), np.pi / 2)
    periods = rng.uniform(6.0, 25.0, n)
    path = SinePath(center, amp, 1.0 / periods, rng.uniform(0, 2 * np.pi, n), still_s, 2.0)
    yaw = StepsBuilder(0.0).hold(still_s)
    pitch = StepsBuilder(0.0).hold(still_s)
    roll = StepsBuilder(0.0).hold(still_s)
    speed = StepsBuilder(0.0)
    k = 0
    while yaw.t < duration_s:
        r = (35 + 10 * rng.uniform()) * DEG * (1 if k % 2 == 0 else -1)
        yaw.move([r], 1.0).hold(rng.uniform(4.0, 10.0)).move([0.0], 1.0).hold(0.5)
        k += 1
    k = 0
    while pitch.t < duration_s:
        a = np.arctan(1 / 12) * (1 if k % 2 == 0 else -1)
        pitch.move([a], 1.5).hold(rng.uniform(2.0, 5.0))
        roll.hold(pitch.t - roll.t).move([np.arctan(1 / 40) * (1 if k % 3 else -1)], 1.5)
        pitch.move([0.0], 1.5).hold(0.5)
        k += 1
    chair = DrivingChair(speed.build(), yaw.build(), pitch.build(), roll.build(),
                         float(rng.uniform(-np.pi, np.pi)), chair_lever_m(arm))
    return Scenario("excitation", arm, duration_s, path, chair, warm_up(20.0, 6.0, 20.0),
                    [{"t_start_s": 0.0, "t_end_s": duration_s, "what": "everything moves"}])


def compass_turn(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float = 3.0,
                 turn_deg: float = 360.0, rate_deg_s: float = 45.0, ramp_s: float = 0.8) -> Scenario:
    """The chair turns once on the spot on level ground (``turn_deg`` at ``rate_deg_s``, its
    rate ramped up and down in ``ramp_s``) between two still stretches, the arm at its ready
    pose throughout, from a random heading: the drive ``calibrate sensors --compass-drive``
    learns the compass's hard and soft iron from (every heading seen once), which no parked
    maneuver can. Its length at the defaults: 14.8 s; a longer ``duration_s`` stays still."""
    r = rate_deg_s * DEG
    cruise = max(0.0, turn_deg / rate_deg_s - ramp_s)
    yaw = StepsBuilder(0.0).hold(still_s).move([r], ramp_s).hold(cruise).move([0.0], ramp_s)
    t_end = yaw.t
    yaw.hold(max(still_s, duration_s - t_end))
    level = [StepsBuilder(0.0).hold(yaw.t) for _ in range(3)]  # speed, pitch, roll
    chair = DrivingChair(level[0].build(), yaw.build(), level[1].build(), level[2].build(),
                         float(rng.uniform(-np.pi, np.pi)), chair_lever_m(arm))
    joints = WaypointPath(StepsBuilder(arm.ready_pose_rad).hold(yaw.t).build())
    events = [{"t_start_s": 0.0, "t_end_s": still_s, "what": "still"},
              {"t_start_s": still_s, "t_end_s": round(t_end, 3),
               "what": f"turn on the spot {turn_deg:.0f}° at {rate_deg_s:g}°/s"}]
    return Scenario("compass-turn", arm, duration_s, joints, chair, warm_up(), events)
