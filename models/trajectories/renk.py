"""The sensor-calibration article's sweep: ``renk-maneuver`` (the chair parked) and
``renk-ramp`` (the same sweep with the chair parked in turn level, on a 1:12 ramp facing up,
down and across it both ways)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG
from armfusion.models.trajectories.paths import DrivingChair, SinePath, StepsBuilder, chair_lever_m
from armfusion.models.trajectories.scenario import Scenario, margin_limits, parked_chair, warm_up

RENK_DURATION_S = 27.74 * 60.0
RENK_RATES_DEG_S = {"yaw": 3.1, "pitch": 0.87, "roll": 13.9}
"""The article's average joint rates: joint 1 (yaw), joint 5 (pitch), joint 6 (roll)."""


def _renk_path(arm: ArmModel, rng: np.random.Generator, still_s: float, fade_s: float, joints=None):
    """The renk sweep's joint path and its description (see :func:`renk_maneuver`)."""
    n = arm.n_joints
    moving = list(range(n)) if joints is None else [
        arm.joint_names.index(j) if isinstance(j, str) else int(j) for j in joints]
    if not moving:
        raise ValueError("renk-maneuver: give at least one joint to move")
    m = len(moving)
    lo, hi = margin_limits(arm)
    center = np.array(arm.ready_pose_rad, dtype=float)
    center[moving] = (0.5 * (lo + hi))[moving]
    half = 0.5 * (hi - lo)
    amp = np.zeros(n)
    rates = np.zeros(n)
    amp[moving] = 0.45 * half[moving]
    rates[moving[1:-1]] = np.linspace(RENK_RATES_DEG_S["pitch"], 5.0, max(m - 2, 0))
    amp[moving[0]] = 0.9 * half[moving[0]]
    rates[moving[0]] = RENK_RATES_DEG_S["yaw"]
    if m > 1:
        amp[moving[-1]] = 0.9 * half[moving[-1]]
        rates[moving[-1]] = RENK_RATES_DEG_S["roll"]
    amp = np.minimum(amp, np.pi)
    freq = np.divide(rates * DEG, 4.0 * amp, out=np.zeros(n), where=amp > 0)  # mean |rate| = 4·A·f
    phase = rng.uniform(0, 2 * np.pi, n)
    path = SinePath(center, amp, freq, phase, still_s, fade_s)
    what = "renk sweep: " + ", ".join(f"{arm.joint_names[i]} ±{np.degrees(amp[i]):.0f}° "
                                      f"at {rates[i]:.2f}°/s" for i in moving)
    return path, what


def renk_maneuver(arm: ArmModel, duration_s: float, rng: np.random.Generator,
                  still_s: float = 5.0, fade_s: float = 20.0, joints=None) -> Scenario:
    """First moving joint: slow sweep over most of its range at the article's 3.1 °/s
    average; last: roll at 13.9 °/s; the joints between nod at rates spread from the
    article's 0.87 °/s to 5 °/s. Incommensurate periods make the sensors pass through many
    orientations (the article's Fig. 2).

    ``joints`` (names or 0-based indices) moves only those, the others held at the ready
    pose: the article's own experiment is ``joints=["j1", "j5", "j6"]`` on
    ``config/crs_a465.yaml``, whose ready pose holds joints 2-4 at 90°, -180°, 0°.
    """
    path, what = _renk_path(arm, rng, still_s, fade_s, joints)
    # start from rest at the sinusoid's value at fade-in: q(0) = center (envelope 0)
    events = [{"t_start_s": 0.0, "t_end_s": still_s, "what": "still at the sweep's centre"},
              {"t_start_s": still_s, "t_end_s": duration_s, "what": what}]
    return Scenario("renk-maneuver", arm, duration_s, path, parked_chair(rng, 0.5 * DEG), warm_up(), events)


RAMP_SLOPE = 1.0 / 12.0
"""The steepest ramp a wheelchair user meets (ADA): 1:12, 4.76°."""
RAMP_STANCES = (("level", 0.0, 0.0), ("ramp facing up", 0.0, -1.0), ("ramp facing down", 0.0, 1.0),
                ("across the ramp, right side low", 1.0, 0.0), ("across the ramp, left side low", -1.0, 0.0))
"""Where the chair parks, in turn: (what, roll, pitch) in units of the slope's angle (nose up
climbing is negative pitch in R = Rz Ry Rx)."""


@dataclass(frozen=True)
class RampDrive:
    """The ramp the chair parks on and how it is driven between stances."""

    slope: float = RAMP_SLOPE
    """Rise over run, in (0, 0.3]."""
    drive_speed_mps: float = 0.3
    """The speed the chair rolls onto and off the slope at."""
    turn_rate_deg_s: float = 45.0
    """The rate it turns on the spot at."""
    wheelbase_m: float = 0.6
    """The chair's wheelbase: the tilt follows it over the slope's edge."""

    def problem(self) -> str | None:
        """What is wrong with these numbers, or None."""
        if not 0.0 < self.slope <= 0.3:
            return f"renk-ramp: slope must be in (0, 0.3] (rise over run), got {self.slope!r}"
        if not self.drive_speed_mps > 0 or not self.turn_rate_deg_s > 0:
            return "renk-ramp: drive speed and turn rate must be positive"
        return None

    @property
    def angle_rad(self) -> float:
        """The slope's angle."""
        return float(np.arctan(self.slope))

    @property
    def roll_on_s(self) -> float:
        """How long the wheelbase takes to roll onto (or off) the slope."""
        return max(1.0, 1.875 * self.wheelbase_m / self.drive_speed_mps)

    @property
    def transition_s(self) -> float:
        """One move between two stances: off the slope, turn (180° at most, and a second),
        onto it, and a second."""
        turn_s = (180.0 / self.turn_rate_deg_s) + 1.0
        return 3 * self.roll_on_s + turn_s + 1.0


class _ChairChannels:
    """The driven chair's four channels (speed, yaw rate, pitch, roll), built in step."""

    def __init__(self, ramp: RampDrive, roll0_rad: float, pitch0_rad: float):
        self.ramp = ramp
        self.speed, self.yaw = StepsBuilder(0.0), StepsBuilder(0.0)
        self.roll, self.pitch = StepsBuilder(roll0_rad), StepsBuilder(pitch0_rad)
        self.all = (self.speed, self.yaw, self.pitch, self.roll)

    @property
    def t(self) -> float:
        """The time the channels have reached (the speed channel's: they end in step)."""
        return self.speed.t

    def sync(self) -> None:
        """Hold every channel to the latest one's end."""
        t = max(c.t for c in self.all)
        for c in self.all:
            c.hold(t - c.t)

    def hold_until(self, t_end_s: float) -> None:
        """Hold every channel until ``t_end_s``."""
        for c in self.all:
            c.hold(t_end_s - c.t)

    def roll_to(self, roll_level: float, pitch_level: float) -> None:
        """Drive slowly while the wheelbase rolls onto (off) the slope, to the tilt given in
        units of the slope's angle."""
        roll_on_s, angle = self.ramp.roll_on_s, self.ramp.angle_rad
        self.speed.move([self.ramp.drive_speed_mps], 0.5 * roll_on_s)
        self.pitch.move([pitch_level * angle], roll_on_s)
        self.roll.move([roll_level * angle], roll_on_s)
        self.speed.hold(0.0)
        self.sync()
        self.speed.move([0.0], 0.5 * roll_on_s)
        self.sync()

    def turn(self, angle_rad: float) -> None:
        """Turn on the spot by ``angle_rad`` at the ramp's turn rate."""
        r = self.ramp.turn_rate_deg_s * DEG
        T = 0.8
        self.yaw.move([np.sign(angle_rad) * r], T).hold(abs(angle_rad) / r - T).move([0.0], T)
        self.sync()


def _stance_turn_rad(k: int) -> float:
    """The turn on the spot before stance ``k``: 180° between up and down, 90° onto the
    cross slope, 180° across."""
    return (np.pi if k in (2, 4) else np.pi / 2) * (1 if k % 2 else -1)


def _parked_s(duration_s: float, still_s: float, transition_s: float) -> float:
    """Each stance's parked time: an equal share of what the transitions leave (a
    ``ValueError`` when under 10 s, or under the still start and 5 s)."""
    n_st = len(RAMP_STANCES)
    parked_s = (duration_s - (n_st - 1) * transition_s) / n_st
    if parked_s < max(still_s + 5.0, 10.0):
        raise ValueError(f"renk-ramp: {duration_s:g} s is too short for {n_st} stances of at least "
                         f"10 s parked each (transitions take {transition_s:.1f} s); give at least "
                         f"{n_st * max(still_s + 5.0, 10.0) + (n_st - 1) * transition_s:.0f} s")
    return parked_s


def _drive_the_stances(chair: _ChairChannels, uneven: np.ndarray, parked_s: float) -> list[dict]:
    """Park in every stance of ``RAMP_STANCES`` in turn (each tilt off by ``uneven``, in
    units of the slope's angle), moving between them; the events of the moves and stances."""
    angle, transition_s = chair.ramp.angle_rad, chair.ramp.transition_s
    events = []
    for k, (name, r_lvl, p_lvl) in enumerate(RAMP_STANCES):
        r_lvl, p_lvl = r_lvl + uneven[k, 0], p_lvl + uneven[k, 1]
        if k:
            t0 = chair.t
            chair.roll_to(0.0, 0.0)
            chair.turn(_stance_turn_rad(k))
            chair.roll_to(r_lvl, p_lvl)
            events.append({"t_start_s": round(t0, 3), "t_end_s": round(chair.t, 3),
                           "what": f"the chair moves to: {name}"})
            t_end = t0 + transition_s + parked_s  # every stance ends on the same schedule
        else:
            t_end = parked_s
        t_start = chair.t
        chair.hold_until(t_end)
        events.append({"t_start_s": round(t_start, 3), "t_end_s": round(chair.t, 3),
                       "what": f"parked: {name}", "parked": True,
                       "tilt_deg": [round(float(np.degrees(r_lvl * angle)), 3),
                                    round(float(np.degrees(p_lvl * angle)), 3)]})
    return events


def renk_ramp(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float = 5.0,
              fade_s: float = 20.0, joints=None, ramp: RampDrive = RampDrive()) -> Scenario:
    """The renk sweep with the chair parked in turn on level ground, on a ramp facing up,
    facing down, and across it both ways (``RAMP_STANCES``), an equal share of the time
    each: gravity then reaches the base from several directions, which separates the IMU's
    mount on the base from the base's tilt (one parked stance cannot).

    Between two stances the chair (a technician drives it; the arm keeps sweeping) rolls
    off the slope, turns on the spot to face the next way and rolls onto the slope again:
    the tilt follows the wheelbase over the slope at ``ramp.drive_speed_mps`` (about 2 s),
    the turn goes at ``ramp.turn_rate_deg_s`` (:class:`DrivingChair`, so the base's rates and
    accelerations are those of the move). The first stance holds the arm still for
    ``still_s`` (the startup's still second), as ``renk-maneuver``.
    """
    why = ramp.problem()
    if why is not None:
        raise ValueError(why)
    path, what = _renk_path(arm, rng, still_s, fade_s, joints)
    angle = ramp.angle_rad
    # the ground is not flat and the chair not square to the fall line: each stance's tilt
    # is off the nominal by a few tenths of a degree
    uneven = rng.normal(0.0, 0.3 * DEG, (len(RAMP_STANCES), 2)) / angle
    chair = _ChairChannels(ramp, (RAMP_STANCES[0][1] + uneven[0, 0]) * angle,
                           (RAMP_STANCES[0][2] + uneven[0, 1]) * angle)
    parked_s = _parked_s(duration_s, still_s, ramp.transition_s)
    events = [{"t_start_s": 0.0, "t_end_s": still_s, "what": "still at the sweep's centre"},
              {"t_start_s": still_s, "t_end_s": duration_s, "what": what},
              *_drive_the_stances(chair, uneven, parked_s)]
    base = DrivingChair(chair.speed.build(), chair.yaw.build(), chair.pitch.build(), chair.roll.build(),
                        float(rng.uniform(-np.pi, np.pi)), chair_lever_m(arm))
    events.sort(key=lambda e: e["t_start_s"])
    return Scenario("renk-ramp", arm, duration_s, path, base, warm_up(),
                    [e for e in events if e["t_start_s"] < duration_s])
