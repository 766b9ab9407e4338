"""Scenarios: how the arm's joints and the chair move over time, as smooth functions.

A :class:`Scenario` gives the full :class:`~models.motion.MotionState` at any instants
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

The motion profiles are quintic "minimum-jerk" blends between levels (continuous up to
the acceleration), so accelerations and their derivatives stay finite and realistic.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from models.arm import ArmModel
from models.kinematics import joint_axis_angle_to_vertical
from models.motion import MotionState, body_rates_from_rpy, cross
from models.rotations import DEG, R_from_rpy, up_from_tilt


# --------------------------------------------------------------------------------------
# smooth building blocks
# --------------------------------------------------------------------------------------
def _blend(tau: np.ndarray):
    """Quintic blend s(τ) = 10τ³ - 15τ⁴ + 6τ⁵ on [0, 1] and its derivatives in τ, and ∫s."""
    t2 = tau * tau
    t3 = t2 * tau
    s = t3 * (10.0 - 15.0 * tau + 6.0 * t2)
    s1 = 30.0 * t2 * (1.0 - tau) ** 2
    s2 = 60.0 * tau - 180.0 * t2 + 120.0 * t3
    S = t2 * t2 * (2.5 - 3.0 * tau + t2)
    return s, s1, s2, S


class SmoothSteps:
    """Levels joined by quintic blends: value, its first two derivatives and its integral at
    any instants (vectorised; ``searchsorted``, not a loop over steps).

    Transition k goes from ``levels[k]`` to ``levels[k+1]`` during
    ``[starts[k], starts[k] + durations[k]]``; transitions are sorted and do not overlap.
    ``levels`` is ``(K+1, d)``; the integral starts at t = 0.
    """

    def __init__(self, starts, durations, levels):
        self.starts = np.asarray(starts, dtype=float).reshape(-1)
        self.durations = np.asarray(durations, dtype=float).reshape(-1)
        lv = np.asarray(levels, dtype=float)
        self.levels = lv.reshape(len(self.starts) + 1, -1)
        K = len(self.starts)
        if K:
            ends = self.starts + self.durations
            if np.any(self.durations <= 0) or np.any(self.starts[1:] < ends[:-1] - 1e-9):
                raise ValueError("SmoothSteps: transitions must have positive durations and not overlap")
        # integral from 0 to each transition's start
        C = np.zeros((max(K, 1), self.levels.shape[1]))
        if K:
            C[0] = self.levels[0] * self.starts[0]
        for k in range(1, K):
            prev_end = self.starts[k - 1] + self.durations[k - 1]
            seg = self.durations[k - 1] * 0.5 * (self.levels[k - 1] + self.levels[k])
            C[k] = C[k - 1] + seg + self.levels[k] * (self.starts[k] - prev_end)
        self._C = C

    @property
    def dim(self) -> int:
        return self.levels.shape[1]

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, first and second derivative, each ``(N, d)``."""
        t = np.asarray(t, dtype=float).reshape(-1)
        N, d = t.shape[0], self.dim
        if not len(self.starts):
            return np.broadcast_to(self.levels[0], (N, d)).copy(), np.zeros((N, d)), np.zeros((N, d))
        k = np.searchsorted(self.starts, t, side="right") - 1
        before = k < 0
        kk = np.maximum(k, 0)
        T = self.durations[kk]
        tau = np.clip((t - self.starts[kk]) / T, 0.0, 1.0)
        s, s1, s2, _ = _blend(tau)
        a, b = self.levels[kk], self.levels[kk + 1]
        delta = b - a
        v = a + delta * s[:, None]
        v1 = delta * (s1 / T)[:, None]
        v2 = delta * (s2 / T**2)[:, None]
        done = tau >= 1.0
        v1[done] = 0.0
        v2[done] = 0.0
        v[before] = self.levels[0]
        v1[before] = 0.0
        v2[before] = 0.0
        return v, v1, v2

    def integral(self, t: np.ndarray) -> np.ndarray:
        """``∫_0^t value``, ``(N, d)``."""
        t = np.asarray(t, dtype=float).reshape(-1)
        if not len(self.starts):
            return self.levels[0] * t[:, None]
        k = np.searchsorted(self.starts, t, side="right") - 1
        before = k < 0
        kk = np.maximum(k, 0)
        T = self.durations[kk]
        tau = np.clip((t - self.starts[kk]) / T, 0.0, 1.0)
        _, _, _, S = _blend(tau)
        a, b = self.levels[kk], self.levels[kk + 1]
        inside = self._C[kk] + T[:, None] * (a * tau[:, None] + (b - a) * S[:, None])
        after = t - (self.starts[kk] + T)
        out = inside + b * np.maximum(after, 0.0)[:, None]
        out[before] = self.levels[0] * t[before, None]
        return out


class StepsBuilder:
    """Builds a :class:`SmoothSteps` channel by appending holds and moves in time order."""

    def __init__(self, level, t0: float = 0.0):
        self.t = t0
        self.level = np.atleast_1d(np.asarray(level, dtype=float)).copy()
        self.starts: list[float] = []
        self.durations: list[float] = []
        self.levels = [self.level.copy()]

    def hold(self, duration_s: float) -> StepsBuilder:
        self.t += max(0.0, duration_s)
        return self

    def move(self, to, duration_s: float) -> StepsBuilder:
        to = np.atleast_1d(np.asarray(to, dtype=float))
        if duration_s <= 0 or np.allclose(to, self.level, atol=1e-15):
            self.t += max(0.0, duration_s)
            return self
        self.starts.append(self.t)
        self.durations.append(duration_s)
        self.levels.append(to.copy())
        self.level = to.copy()
        self.t += duration_s
        return self

    def build(self) -> SmoothSteps:
        return SmoothSteps(self.starts, self.durations, np.stack(self.levels))


def min_jerk_duration(delta, peak_rate, min_s: float = 0.5) -> float:
    """Duration of a quintic move of size ``delta`` whose peak rate is ``peak_rate``."""
    return max(min_s, 1.875 * float(np.max(np.abs(delta) / peak_rate)))


# --------------------------------------------------------------------------------------
# joint paths
# --------------------------------------------------------------------------------------
class JointPath:
    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError


class WaypointPath(JointPath):
    """Holds and minimum-jerk moves between poses (a :class:`SmoothSteps` over joints)."""

    def __init__(self, steps: SmoothSteps):
        self.steps = steps

    def __call__(self, t):
        return self.steps(t)


class SinePath(JointPath):
    """``q = c + A·e(t)·sin(2π f t + φ)`` per joint; ``e`` fades in from 0 to 1 over
    ``[fade_start_s, fade_start_s + fade_s]`` so that the arm starts from rest."""

    def __init__(self, center, amplitude, freq_hz, phase_rad, fade_start_s: float, fade_s: float):
        self.c = np.asarray(center, float)
        self.A = np.asarray(amplitude, float)
        self.w = 2 * np.pi * np.asarray(freq_hz, float)
        self.ph = np.asarray(phase_rad, float)
        self.env = SmoothSteps([fade_start_s], [fade_s], [[0.0], [1.0]])

    def __call__(self, t):
        t = np.asarray(t, float).reshape(-1)
        e, e1, e2 = self.env(t)
        arg = t[:, None] * self.w + self.ph
        s, c = np.sin(arg), np.cos(arg)
        q = self.c + self.A * e * s
        qd = self.A * (e1 * s + e * self.w * c)
        qdd = self.A * (e2 * s + 2 * e1 * self.w * c - e * self.w**2 * s)
        return q, qd, qdd


# --------------------------------------------------------------------------------------
# base paths
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BaseMotion:
    """The arm base at N instants: attitude, body rates, linear acceleration (base axes)."""

    R_WB: np.ndarray
    omega_B: np.ndarray
    omega_dot_B: np.ndarray
    accel_B: np.ndarray


class BasePath:
    def __call__(self, t: np.ndarray) -> BaseMotion:
        raise NotImplementedError

    def position_m(self, t: np.ndarray) -> np.ndarray:
        """World position of the arm base's origin, ``(N, 3)``."""
        raise NotImplementedError


class ParkedBase(BasePath):
    """The chair parked, at a fixed attitude."""

    def __init__(self, roll_rad: float = 0.0, pitch_rad: float = 0.0, yaw_rad: float = 0.0):
        self.rpy = np.array([roll_rad, pitch_rad, yaw_rad], float)

    def __call__(self, t):
        N = np.asarray(t).reshape(-1).shape[0]
        R = np.broadcast_to(R_from_rpy(*self.rpy), (N, 3, 3))
        z = np.zeros((N, 3))
        return BaseMotion(R, z, z, z)

    def position_m(self, t):
        return np.zeros((np.asarray(t).reshape(-1).shape[0], 3))


class DrivingChair(BasePath):
    """A power wheelchair: forward speed ``v(t)`` along its x axis and yaw rate ``r(t)``
    (both :class:`SmoothSteps`), its pitch and roll following the ground (ramps, cross
    slopes). The arm's base is fixed to the chair at ``lever_m`` (chair axes) from the
    turning centre (mid-point of the drive wheels), axes parallel to the chair's.

    In base axes: ``a_B = v' e_x + v (ω x e_x) + ω' x ρ + ω x (ω x ρ)``.
    """

    def __init__(self, speed: SmoothSteps, yaw_rate: SmoothSteps, pitch: SmoothSteps,
                 roll: SmoothSteps, yaw0_rad: float = 0.0, lever_m=(0.25, -0.35, 0.45)):
        self.speed, self.yaw_rate, self.pitch, self.roll = speed, yaw_rate, pitch, roll
        self.yaw0 = float(yaw0_rad)
        self.lever = np.asarray(lever_m, float)
        self._table = None

    def rpy(self, t):
        t = np.asarray(t, float).reshape(-1)
        ph, ph1, ph2 = self.roll(t)
        th, th1, th2 = self.pitch(t)
        r, r1, _ = self.yaw_rate(t)
        ps = self.yaw0 + self.yaw_rate.integral(t)
        rpy = np.concatenate([ph, th, ps], 1)
        return rpy, np.concatenate([ph1, th1, r], 1), np.concatenate([ph2, th2, r1], 1)

    def __call__(self, t):
        t = np.asarray(t, float).reshape(-1)
        rpy, d1, d2 = self.rpy(t)
        R = R_from_rpy(rpy[:, 0], rpy[:, 1], rpy[:, 2])
        w, wd = body_rates_from_rpy(rpy, d1, d2)
        v, v1, _ = self.speed(t)
        ex = np.array([1.0, 0.0, 0.0])
        rho = self.lever
        a = v1 * ex + v * cross(w, ex) + cross(wd, rho) + cross(w, cross(w, rho))
        return BaseMotion(R, w, wd, a)

    # position: a quadrature table (for plots and the finite-difference tests only)
    def _velocity_W(self, t):
        rpy, _, _ = self.rpy(t)
        R = R_from_rpy(rpy[:, 0], rpy[:, 1], rpy[:, 2])
        v, _, _ = self.speed(t)
        return v * R[:, :, 0], R

    def position_m(self, t):
        t = np.asarray(t, float).reshape(-1)
        if self._table is None or t.max(initial=0.0) > self._table[0][-1]:
            t_end = max(float(t.max(initial=0.0)), 1.0) + 1.0
            h = 0.005
            grid = np.arange(0.0, t_end + h, h)
            f0, _ = self._velocity_W(grid)
            fm, _ = self._velocity_W(grid[:-1] + h / 2)
            inc = h / 6.0 * (f0[:-1] + 4.0 * fm + f0[1:])
            P = np.concatenate([np.zeros((1, 3)), np.cumsum(inc, axis=0)])
            self._table = (grid, P, f0)
        grid, P, V = self._table
        h = grid[1] - grid[0]
        k = np.clip(np.floor(t / h).astype(int), 0, len(grid) - 2)
        s = ((t - grid[k]) / h)[:, None]
        h00 = 2 * s**3 - 3 * s**2 + 1
        h10 = s**3 - 2 * s**2 + s
        h01 = -2 * s**3 + 3 * s**2
        h11 = s**3 - s**2
        Pc = h00 * P[k] + h10 * h * V[k] + h01 * P[k + 1] + h11 * h * V[k + 1]
        _, R = self._velocity_W(t)
        return Pc + np.einsum("nij,j->ni", R, self.lever)


# --------------------------------------------------------------------------------------
# scenario
# --------------------------------------------------------------------------------------
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


def _margin_limits(arm: ArmModel, margin_rad: float = 5 * DEG):
    lo, hi = arm.min_rad + margin_rad, arm.max_rad - margin_rad
    return lo, np.maximum(hi, lo)


def _clip_pose(arm: ArmModel, q):
    lo, hi = _margin_limits(arm)
    return np.clip(q, lo, hi)


def _parked(rng: np.random.Generator, tilt_sigma_rad: float = 1.5 * DEG) -> ParkedBase:
    roll, pitch = np.clip(rng.normal(0, tilt_sigma_rad, 2), -4 * DEG, 4 * DEG)
    return ParkedBase(float(roll), float(pitch), float(rng.uniform(-np.pi, np.pi)))


def startup(arm: ArmModel, duration_s: float, rng: np.random.Generator, pose_rad=None) -> Scenario:
    q = arm.ready_pose_rad if pose_rad is None else _clip_pose(arm, np.asarray(pose_rad, float))
    path = WaypointPath(SmoothSteps([], [], [q]))
    return Scenario("startup", arm, duration_s, path, _parked(rng), warm_up(),
                    [{"t_start_s": 0.0, "t_end_s": duration_s, "what": "still at one pose",
                      "pose_deg": np.degrees(q).round(3).tolist()}])


def random_still_poses(arm: ArmModel, k: int, rng: np.random.Generator,
                       near_lock_share: float = 0.25, lock_deg: float = 3.0,
                       up_0: np.ndarray | None = None) -> np.ndarray:
    """``k`` poses inside the limits; a share of them with some joint axis within
    ``lock_deg`` of vertical (``up_0``: world up in the base frame; default level), picked
    from a large random pool."""
    lo, hi = _margin_limits(arm)
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
    base = _parked(rng)
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
    lo, hi = _margin_limits(arm)
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
    return Scenario("renk-maneuver", arm, duration_s, path, _parked(rng, 0.5 * DEG), warm_up(), events)


RAMP_SLOPE = 1.0 / 12.0
"""The steepest ramp a wheelchair user meets (ADA): 1:12, 4.76°."""
RAMP_STANCES = (("level", 0.0, 0.0), ("ramp facing up", 0.0, -1.0), ("ramp facing down", 0.0, 1.0),
                ("across the ramp, right side low", 1.0, 0.0), ("across the ramp, left side low", -1.0, 0.0))
"""Where the chair parks, in turn: (what, roll, pitch) in units of the slope's angle (nose up
climbing is negative pitch in R = Rz Ry Rx)."""


def renk_ramp(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float = 5.0,
              fade_s: float = 20.0, slope: float = RAMP_SLOPE, joints=None,
              drive_speed_mps: float = 0.3, turn_rate_deg_s: float = 45.0) -> Scenario:
    """The renk sweep with the chair parked in turn on level ground, on a ramp facing up,
    facing down, and across it both ways (``RAMP_STANCES``), an equal share of the time
    each: gravity then reaches the base from several directions, which separates the IMU's
    mount on the base from the base's tilt (one parked stance cannot).

    Between two stances the chair (a technician drives it; the arm keeps sweeping) rolls
    off the slope, turns on the spot to face the next way and rolls onto the slope again:
    the tilt follows the wheelbase over the slope at ``drive_speed_mps`` (about 2 s), the
    turn goes at ``turn_rate_deg_s`` (:class:`DrivingChair`, so the base's rates and
    accelerations are those of the move). The first stance holds the arm still for
    ``still_s`` (the startup's still second), as ``renk-maneuver``.
    """
    if not 0.0 < slope <= 0.3:
        raise ValueError(f"renk-ramp: slope must be in (0, 0.3] (rise over run), got {slope!r}")
    if not drive_speed_mps > 0 or not turn_rate_deg_s > 0:
        raise ValueError("renk-ramp: drive speed and turn rate must be positive")
    path, what = _renk_path(arm, rng, still_s, fade_s, joints)
    angle = float(np.arctan(slope))
    wheelbase_m = 0.6
    roll_on_s = max(1.0, 1.875 * wheelbase_m / drive_speed_mps)  # the wheelbase onto the slope
    r = turn_rate_deg_s * DEG
    # the ground is not flat and the chair not square to the fall line: each stance's tilt
    # is off the nominal by a few tenths of a degree
    n_st = len(RAMP_STANCES)
    uneven = rng.normal(0.0, 0.3 * DEG, (n_st, 2)) / angle
    speed, yaw = StepsBuilder(0.0), StepsBuilder(0.0)
    roll = StepsBuilder((RAMP_STANCES[0][1] + uneven[0, 0]) * angle)
    pitch = StepsBuilder((RAMP_STANCES[0][2] + uneven[0, 1]) * angle)
    chans = (speed, yaw, pitch, roll)

    def sync():
        t = max(c.t for c in chans)
        for c in chans:
            c.hold(t - c.t)

    def roll_to(r_lvl, p_lvl):  # drive slowly while the wheelbase rolls onto (off) the slope
        speed.move([drive_speed_mps], 0.5 * roll_on_s)
        pitch.move([p_lvl * angle], roll_on_s)
        roll.move([r_lvl * angle], roll_on_s)
        speed.hold(0.0)
        sync()
        speed.move([0.0], 0.5 * roll_on_s)
        sync()

    # per stance: the transition's length, then an equal share of what is left parked
    turn_s = (180.0 / turn_rate_deg_s) + 1.0
    transition_s = 3 * roll_on_s + turn_s + 1.0  # off the slope, turn, onto it
    parked_s = (duration_s - (n_st - 1) * transition_s) / n_st
    if parked_s < max(still_s + 5.0, 10.0):
        raise ValueError(f"renk-ramp: {duration_s:g} s is too short for {n_st} stances of at least "
                         f"10 s parked each (transitions take {transition_s:.1f} s); give at least "
                         f"{n_st * max(still_s + 5.0, 10.0) + (n_st - 1) * transition_s:.0f} s")
    events = [{"t_start_s": 0.0, "t_end_s": still_s, "what": "still at the sweep's centre"},
              {"t_start_s": still_s, "t_end_s": duration_s, "what": what}]
    heading = 0.0
    for k, (name, r_lvl, p_lvl) in enumerate(RAMP_STANCES):
        r_lvl, p_lvl = r_lvl + uneven[k, 0], p_lvl + uneven[k, 1]
        if k:
            t0 = speed.t
            roll_to(0.0, 0.0)
            # turn on the spot: 180° between up and down, 90° onto the cross slope, 180° across
            ang = (np.pi if k in (2, 4) else np.pi / 2) * (1 if k % 2 else -1)
            T = 0.8
            yaw.move([np.sign(ang) * r], T).hold(abs(ang) / r - T).move([0.0], T)
            heading += ang
            sync()
            roll_to(r_lvl, p_lvl)
            events.append({"t_start_s": round(t0, 3), "t_end_s": round(speed.t, 3),
                           "what": f"the chair moves to: {name}"})
            t_end = t0 + transition_s + parked_s  # every stance ends on the same schedule
        else:
            t_end = parked_s
        t_start = speed.t
        for c in chans:
            c.hold(t_end - c.t)
        events.append({"t_start_s": round(t_start, 3), "t_end_s": round(speed.t, 3),
                       "what": f"parked: {name}", "parked": True,
                       "tilt_deg": [round(float(np.degrees(r_lvl * angle)), 3),
                                    round(float(np.degrees(p_lvl * angle)), 3)]})
    chair = DrivingChair(speed.build(), yaw.build(), pitch.build(), roll.build(),
                         float(rng.uniform(-np.pi, np.pi)))
    events.sort(key=lambda e: e["t_start_s"])
    return Scenario("renk-ramp", arm, duration_s, path, chair, warm_up(),
                    [e for e in events if e["t_start_s"] < duration_s])


def _reach_path(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float,
                home, spread_rad: float = 35 * DEG, peak_rate_rad_s: float = 25 * DEG):
    b = StepsBuilder(home)
    b.hold(still_s)
    events = []
    while b.t < duration_s:
        b.hold(rng.uniform(2.0, 20.0))
        t0 = b.t
        for _ in range(rng.integers(1, 3)):  # out to one or two targets
            target = _clip_pose(arm, home + rng.normal(0, spread_rad, arm.n_joints))
            b.move(target, min_jerk_duration(target - b.level, peak_rate_rad_s, 1.5))
            b.hold(rng.uniform(1.0, 6.0))
        b.move(home, min_jerk_duration(home - b.level, peak_rate_rad_s, 1.5))
        events.append({"t_start_s": round(t0, 3), "t_end_s": round(b.t, 3), "what": "arm reaches"})
    return WaypointPath(b.build()), events


def _chair_path(duration_s: float, rng: np.random.Generator, still_s: float, yaw0: float):
    """Random drives: start, cruise with turns and ramps, stop; turns on the spot; pauses."""
    speed = StepsBuilder(0.0)
    yaw = StepsBuilder(0.0)
    pitch = StepsBuilder(0.0)
    roll = StepsBuilder(0.0)
    for ch in (speed, yaw, pitch, roll):
        ch.hold(still_s)
    ramp = np.arctan(1 / 12)
    cross_slope = np.arctan(1 / 50)
    events = []
    t = still_s

    def sync(t_):
        for ch in (speed, yaw, pitch, roll):
            ch.hold(t_ - ch.t)

    while t < duration_s:
        t += rng.uniform(3.0, 20.0)  # pause
        sync(t)
        if rng.uniform() < 0.2:  # turn on the spot
            ang = rng.uniform(60, 180) * DEG * rng.choice([-1, 1])
            r = 45 * DEG * np.sign(ang)
            Tr = 0.8
            cruise = abs(ang) / abs(r) - Tr
            yaw.move([r], Tr).hold(cruise).move([0.0], Tr)
            events.append({"t_start_s": round(t, 3), "t_end_s": round(yaw.t, 3),
                           "what": f"turn on the spot {np.degrees(ang):.0f}°"})
            t = yaw.t
            sync(t)
            continue
        v = rng.uniform(0.4, 1.3)
        acc = rng.uniform(0.4, 1.0)
        Ta = np.sqrt(5.7735 * v / acc)  # quintic: peak acceleration 5.77·Δ/T²
        t0 = t
        speed.move([v], Ta)
        t += Ta
        sync(t)
        what = [f"drive {v:.1f} m/s"]
        for _ in range(rng.integers(1, 4)):  # cruise pieces: straight, a turn or a ramp
            kind = rng.choice(["straight", "turn", "ramp", "cross"], p=[0.35, 0.35, 0.15, 0.15])
            if kind == "straight":
                t += rng.uniform(2.0, 10.0)
            elif kind == "turn":
                r_max = min(60 * DEG, 0.6 / v)
                r = rng.uniform(0.5, 1.0) * r_max * rng.choice([-1, 1])
                ang = rng.uniform(30, 150) * DEG
                Tr = max(0.6, abs(r) / (90 * DEG))
                cruise = max(0.0, ang / abs(r) - Tr)
                yaw.move([r], Tr).hold(cruise).move([0.0], Tr)
                what.append(f"turn {np.degrees(np.sign(r) * ang):.0f}°")
                t = yaw.t
            else:
                up = rng.choice([-1, 1])
                level = (ramp * rng.uniform(0.5, 1.0) if kind == "ramp" else cross_slope) * up
                ch = pitch if kind == "ramp" else roll
                Tt = max(0.6, 0.6 / v)  # the wheelbase rolls onto the slope
                length = rng.uniform(2.0, 9.0)
                # nose up climbing: negative pitch in R = Rz Ry Rx
                ch.move([-level if kind == "ramp" else level], Tt).hold(length / v).move([0.0], Tt)
                slope = f"ramp 1:{round(1 / np.tan(abs(level)))}" if kind == "ramp" else "cross-slope 1:50"
                if kind == "ramp":
                    way = "up" if up > 0 else "down"
                else:
                    way = ("right" if up > 0 else "left") + " low"
                what.append(f"{slope} {way}")
                t = ch.t
            sync(t)
        dec = rng.uniform(0.4, 1.0)
        Td = np.sqrt(5.7735 * v / dec)
        speed.move([0.0], Td)
        t += Td
        sync(t)
        events.append({"t_start_s": round(t0, 3), "t_end_s": round(t, 3), "what": ", ".join(what)})
    return DrivingChair(speed.build(), yaw.build(), pitch.build(), roll.build(), yaw0), events


def daily_use(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float = 8.0) -> Scenario:
    home = arm.ready_pose_rad
    rng_arm, rng_chair = (np.random.default_rng(s) for s in rng.integers(0, 2**62, 2))
    joints, arm_events = _reach_path(arm, duration_s, rng_arm, still_s, home)
    chair, chair_events = _chair_path(duration_s, rng_chair, still_s, float(rng.uniform(-np.pi, np.pi)))
    events = [{"t_start_s": 0.0, "t_end_s": still_s, "what": "still (startup)"}]
    events += sorted(arm_events + chair_events, key=lambda e: e["t_start_s"])
    return Scenario("daily-use", arm, duration_s, joints, chair, warm_up(),
                    [e for e in events if e["t_start_s"] < duration_s])


def excitation(arm: ArmModel, duration_s: float, rng: np.random.Generator, still_s: float = 2.0) -> Scenario:
    """Everything moves: every joint sinusoidally (periods 6-25 s over ±35 % of its range),
    the chair turning on the spot and rocking on ramps and cross slopes, temperature rising
    fast (6 °C over the first minutes)."""
    n = arm.n_joints
    lo, hi = _margin_limits(arm)
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
                         float(rng.uniform(-np.pi, np.pi)))
    return Scenario("excitation", arm, duration_s, path, chair, warm_up(20.0, 6.0, 20.0),
                    [{"t_start_s": 0.0, "t_end_s": duration_s, "what": "everything moves"}])


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
    rng = np.random.default_rng([int(seed), 0x5CE])
    return spec.build(arm, d, rng, **options)
