"""The smooth pieces a scenario is built of: levels joined by quintic minimum-jerk blends
(:class:`SmoothSteps`, built by :class:`StepsBuilder`), joint paths (waypoints, sines) and
base paths (the chair parked, or driving), each giving values and their exact derivatives
at any instants, vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.models.motion import body_rates_from_rpy, cross
from armfusion.models.rotations import R_from_rpy


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


def min_jerk_progress(tau: np.ndarray) -> np.ndarray:
    """How far a minimum-jerk move has gone, 0…1, at the fractions ``tau`` of its time (the
    blend every move of a :class:`SmoothSteps` follows)."""
    return _blend(np.clip(np.asarray(tau, float), 0.0, 1.0))[0]


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

    def _locate(self, t: np.ndarray):
        """For instants ``t``: which come before the first transition, the transition each is
        in or after, its duration and the fraction of it done (τ in [0, 1])."""
        k = np.searchsorted(self.starts, t, side="right") - 1
        before = k < 0
        kk = np.maximum(k, 0)
        T = self.durations[kk]
        tau = np.clip((t - self.starts[kk]) / T, 0.0, 1.0)
        return before, kk, T, tau

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, first and second derivative, each ``(N, d)``."""
        t = np.asarray(t, dtype=float).reshape(-1)
        N, d = t.shape[0], self.dim
        if not len(self.starts):
            return np.broadcast_to(self.levels[0], (N, d)).copy(), np.zeros((N, d)), np.zeros((N, d))
        before, kk, T, tau = self._locate(t)
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
        before, kk, T, tau = self._locate(t)
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


CHAIR_LEVER_M = (0.25, -0.35, 0.45)
"""Where a simulated chair carries the arm's base from its turning centre (chair axes, m),
unless the arm's config says (:func:`chair_lever_m`)."""


def chair_lever_m(arm) -> tuple[float, float, float]:
    """The arm's base from its chair's turning centre (m): the config's ``chair:`` block
    where it has one (:attr:`armfusion.models.arm.ArmModel.base_from_turning_centre_m`), else
    :data:`CHAIR_LEVER_M`."""
    rho = getattr(arm, "base_from_turning_centre_m", None)
    return CHAIR_LEVER_M if rho is None else tuple(float(v) for v in rho)


class DrivingChair(BasePath):
    """A power wheelchair: forward speed ``v(t)`` along its x axis and yaw rate ``r(t)``
    (both :class:`SmoothSteps`), its pitch and roll following the ground (ramps, cross
    slopes). The arm's base is fixed to the chair at ``lever_m`` (chair axes) from the
    turning centre (mid-point of the drive wheels), axes parallel to the chair's.

    In base axes: ``a_B = v' e_x + v (ω x e_x) + ω' x ρ + ω x (ω x ρ)``.
    """

    def __init__(self, speed: SmoothSteps, yaw_rate: SmoothSteps, pitch: SmoothSteps,
                 roll: SmoothSteps, yaw0_rad: float = 0.0, lever_m=CHAIR_LEVER_M):
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
