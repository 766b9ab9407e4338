"""The filter's process model (:class:`ProcessModel`: how the state moves between two
instants, and its noise) and :class:`StillDetector`, which tells when the chair stands
still (then its acceleration is zero: a pseudo-measurement that pins the tilt, and its
process noise shrinks)."""

from __future__ import annotations

import math

import numpy as np
from armfusion.fusion.tracking.process_kernels import (
    fold_attitude,
    points_from_tangent,
    process_points,
    process_points_tangent,
)
from armfusion.fusion.tracking.settings import G, StateLayout, TrackerSettings
from armfusion.models.rotations import DEG


def gyro_newer_weight(delay_s: float, rate_hz: float) -> float:
    """The newer sample's weight ``k`` in the rate the attitude turns by over the interval
    between two gyro samples, ``(1 - k) ω_prev + k ω_new``: the rate at the interval's
    midpoint, from samples that each stand for the rate ``delay_s`` before their stamps (the
    gyroscope's ``delay_s``, its description's), read linearly between them: ``k = 1/2 +
    delay_s · rate_hz``. The midpoint rule (``k`` = 1/2) for a sample that is the rate at its
    own instant; the newer sample alone (``k`` = 1) for one that is its period's mean, half a
    period late. Capped at 1: a longer delay is made up for to half a period, and the rest
    stays a lag (the samples to read it from have not come yet)."""
    return min(1.0, 0.5 + max(0.0, float(delay_s)) * float(rate_hz))


class MotionIntensity:
    """How vigorously a base whose speed is bounded (a hand) moves now, as the time scale
    ``k`` of its motion: a hand turning a sensor slowly accelerates it by a few tenths of
    m/s², one shaking it by 8, and a calm stretch and a vigorous one are the same kind of
    motion played slower or faster. Played ``k`` times faster, a motion's acceleration
    spread is ``k²`` times its nominal one (the config's ``accel_sigma_mps2``), its speed's
    ``k`` times, its reach the same, and its correlation time ``1/k`` times: the process
    model takes all four from ``k`` (:meth:`ProcessModel.fx_tangent`,
    :meth:`ProcessModel.Q`). Without it one spread serves every stretch, too wide for the
    calm ones (the tilt then rests on the gyro longer than it need) and too narrow for the
    vigorous ones (an acceleration is then read as a tilt).

    ``k`` comes from the IMU accelerometer alone, free of any attitude error: the deviation
    of its reading's magnitude from gravity, ``‖f‖ - g``, is the acceleration along gravity
    (to first order; across it the magnitude changes only to second order), averaged in
    square over three of the nominal correlation times. A hand's acceleration is not
    spread evenly over directions (at any moment it lies mostly along its stroke, which may
    be any axis), so each axis is given the whole magnitude's spread, ``sqrt(3 m)``, not one
    axis's share of it; ``k²`` is that over the nominal spread, within
    :attr:`~armfusion.fusion.tracking.settings.TrackerSettings.base_intensity_range`."""

    def __init__(self, settings: TrackerSettings):
        self.nominal_mps2 = float(settings.base_accel_sigma_mps2)
        self.tau_s = 3.0 * float(settings.base_accel_tau_s)
        self.k2_min, self.k2_max = (float(v) for v in settings.base_intensity_range)
        self.mean_sq = self.nominal_mps2**2 / 3.0  # starts at the nominal intensity (k = 1)
        self.k = 1.0

    def update(self, dt: float, f_imu_g: np.ndarray) -> float:
        """One IMU accelerometer reading ``f_imu_g (3,)`` (g) ``dt`` after the last: the new ``k``."""
        if not dt > 0.0:
            return self.k
        fx, fy, fz = f_imu_g.tolist()
        e = (math.sqrt(fx * fx + fy * fy + fz * fz) - 1.0) * G
        if not math.isfinite(e):
            return self.k
        self.mean_sq += min(1.0, dt / self.tau_s) * (e * e - self.mean_sq)
        k2 = math.sqrt(3.0 * self.mean_sq) / self.nominal_mps2
        self.k = math.sqrt(min(max(k2, self.k2_min), self.k2_max))
        return self.k

    def snapshot(self) -> list:
        return [self.mean_sq, self.k]

    def restore(self, snap) -> None:
        self.mean_sq, self.k = (float(v) for v in snap)


def attitude_sigma_rad(rpy_rad: np.ndarray, C_att: np.ndarray, heading_floor_var=0.0) -> np.ndarray:
    """Roll, pitch and heading sigmas ``(..., 3)`` from the attitude covariance ``C_att
    (..., 3, 3)`` of the filter's tangent space (a world-axis rotation vector ``δ``) at
    attitudes ``rpy_rad (..., 3)``: roll and pitch through the Euler angles' own rates
    (``dε = E R^T δ``, which grows without bound near pitch ±90 deg, where they are
    undefined: held at pi), the heading as ``δ``'s vertical part, whose sigma stays finite
    at any attitude (for a level base all three are ``δ``'s own), with
    ``heading_floor_var`` (rad², scalar or ``(...)``: what the filter cannot average away,
    :attr:`armfusion.fusion.tracking.compass.Compass.heading_floor_var`) added."""
    r, p = (np.asarray(rpy_rad, float)[..., k] for k in range(2))
    cp = np.cos(p)
    cp_safe = np.where(np.abs(cp) < 1e-9, np.copysign(1e-9, cp), cp)
    y = np.asarray(rpy_rad, float)[..., 2]
    sy, cy = np.sin(y), np.cos(y)
    # Euler rates from world rates: roll' = (cy wx + sy wy) / cp, pitch' = -sy wx + cy wy
    rows = np.stack([np.stack([cy / cp_safe, sy / cp_safe, np.zeros_like(r)], -1),
                     np.stack([-sy, cy, np.zeros_like(r)], -1),
                     np.stack([np.zeros_like(r), np.zeros_like(r), np.ones_like(r)], -1)], -2)
    C = np.asarray(C_att, float)
    var = np.einsum("...ij,...jk,...ik->...i", rows, C, rows)
    var[..., 2] += heading_floor_var
    # (an angle known to no better than pi is not known: roll's at pitch ±90 deg stops there)
    return np.minimum(np.sqrt(np.clip(var, 0.0, None)), np.pi)


class ProcessModel:
    """Offsets, the gyro bias, its scale about z (where a state) and the IMU accelerometer's
    bias take random walks; the attitude turns with the gyro (or a random walk without
    one); the chair's acceleration is a first-order Gauss-Markov process."""

    def __init__(self, settings: TrackerSettings, layout: StateLayout, joint_names=()):
        self.settings, self.layout = settings, layout
        rw = np.full(layout.n_joints, settings.offset_random_walk_deg_per_sqrt_s)
        for name, deg in settings.offset_random_walk_by_joint_deg_per_sqrt_s:
            if name not in joint_names:
                raise ValueError(f"offset_random_walk_by_joint_deg_per_sqrt_s: no joint {name!r} "
                                 f"(joints: {', '.join(joint_names)})")
            if not (np.isfinite(deg) and deg > 0):
                raise ValueError(f"offset_random_walk_by_joint_deg_per_sqrt_s[{name!r}]: a random "
                                 f"walk must be a positive number of deg/sqrt(s), got {deg!r}")
            rw[list(joint_names).index(name)] = float(deg)
        self._offset_rw_rad = rw * DEG
        self._velocity_rate_s2 = 0.0
        if layout.vel is not None:
            # the velocity's oscillator, 1 / (τ_a τ_v) = σ_a² / σ_v² (s⁻²): its stationary spread
            # is then σ_v and its acceleration's σ_a (:func:`process_points_tangent`)
            self._velocity_rate_s2 = (settings.base_accel_sigma_mps2 / settings.base_speed_sigma_mps) ** 2
        self.intensity: MotionIntensity | None = None
        """How vigorously the base moves now, where that is followed (a hand's: the tracker
        sets it); None: at the config's own motion."""
        self._scale_noise_rad2 = 0.0
        self.last_points: tuple[np.ndarray, np.ndarray] | None = None
        self._decay: dict[float, float] = {}
        self._Q: dict = {}
        self._zeros3 = np.zeros(3)

    def fx(self, X: np.ndarray, dt: float, w: np.ndarray | None) -> np.ndarray:
        """Every sigma point at once (compiled:
        :func:`armfusion.fusion.tracking.process_kernels.process_points`): the gyro (minus each point's bias)
        turns the attitude exactly, the base's acceleration decays, offsets and bias stay.
        The points' attitude columns are Euler angles (the filter calls
        :meth:`fx_tangent`, which alone carries a base velocity block)."""
        L = self.layout
        if L.vel is not None:
            raise ValueError("ProcessModel.fx: the Euler-angle path has no base velocity; a layout with "
                             "one is propagated by fx_tangent")
        decay = self._decay_of(dt)
        have_w = w is not None
        jerk, jerk_decay = self._jerk_of(dt)
        return process_points(np.ascontiguousarray(X), dt, w if have_w else self._zeros3, have_w,
                              L.roll, L.yaw, L.bias.start, L.accel.start, L.scale, decay, jerk, jerk_decay)

    def _jerk_of(self, dt: float) -> tuple[int, float]:
        """The jerk block's first column (-1 without one) and the jerk's decay over ``dt``."""
        if self.layout.jerk_B is None:
            return -1, 1.0
        return self.layout.jerk_B.start, math.exp(-dt / self.settings.base_jerk_tau_s)

    @property
    def k(self) -> float:
        """The base motion's time scale now (:class:`MotionIntensity`; 1: the config's own)."""
        return 1.0 if self.intensity is None else self.intensity.k

    def set_scale_noise(self, sigma: float) -> None:
        """For a base that turns about every axis (:attr:`TrackerSettings.base_turns_about_any`),
        the gyro's scale-and-axes error ``sigma`` (a fraction per axis) as the attitude's
        process noise (:meth:`Q`)."""
        self._scale_noise_rad2 = float(sigma) ** 2

    def _decay_of(self, dt: float) -> float:
        """The base acceleration's decay over ``dt`` (cached), at the motion's time scale."""
        if self.k != 1.0:
            return math.exp(-dt * self.k / self.settings.base_accel_tau_s)
        decay = self._decay.get(dt)
        if decay is None:
            if len(self._decay) > 64:
                self._decay.clear()
            decay = self._decay[dt] = math.exp(-dt / self.settings.base_accel_tau_s)
        return decay

    def fx_tangent(self, X: np.ndarray, dt: float, w: np.ndarray | None) -> np.ndarray:
        """:meth:`fx` for points whose attitude is in the filter's tangent space (the central
        point's Euler angles plus a world-axis rotation vector, whose covariance the filter
        holds: meaningful at any attitude, where Euler angles are singular at pitch ±90 deg):
        turned into Euler angles for the kernel
        (:func:`~armfusion.fusion.tracking.process_kernels.points_from_tangent`), and back about the
        propagated central point."""
        L = self.layout
        decay = self._decay_of(dt)
        have_w = w is not None
        vel, vel_gain = -1, 0.0
        if L.vel is not None:  # the acceleration is a bounded velocity's: see _velocity_step
            vel, vel_gain = L.vel.start, dt * self._velocity_rate_s2 * self.k**2
        jerk, jerk_decay = self._jerk_of(dt)  # the acceleration changes by its jerk
        T, Y = process_points_tangent(np.ascontiguousarray(X), dt, w if have_w else self._zeros3, have_w,
                                      L.roll, L.yaw, L.bias.start, L.accel.start, L.scale, decay, vel,
                                      vel_gain, jerk, jerk_decay)
        self.last_points = (T, Y)  # the propagated points, in the tangent space and in Euler angles
        return T

    def euler_points(self, X: np.ndarray) -> np.ndarray:
        """Points in the tangent space as Euler-angle points (the last propagated ones are
        kept: an update at the predicted points does not convert them again)."""
        last = self.last_points
        if last is not None and (X is last[0] or (X.base is last[0] and X.shape == last[0].shape)):
            return last[1]
        L = self.layout
        return points_from_tangent(np.ascontiguousarray(X), L.roll, L.yaw)

    def fold_attitude(self, x: np.ndarray, anchor_rpy: np.ndarray) -> np.ndarray:
        """The state ``x`` with its attitude columns, held as ``anchor_rpy`` plus a world-axis
        rotation vector ``δ`` (the filter's tangent space about the points' central
        attitude), turned back into the Euler angles of ``exp([δ]x) R(anchor)``, in the
        canonical chart (pitch within ±pi/2, roll and yaw within ±pi). The covariance is
        left as it is: it is ``δ``'s, about the new mean (a multiplicative filter's reset,
        to first order)."""
        L = self.layout
        return fold_attitude(np.ascontiguousarray(x, dtype=float),
                             np.ascontiguousarray(anchor_rpy, dtype=float), L.roll, L.yaw)

    def rate(self, w: np.ndarray, x) -> np.ndarray:
        """The base's turn rate (rad/s, base axes; ``w`` one reading ``(3,)`` or several
        ``(B, 3)``) from the gyro's ``w`` at the state ``x``: its bias taken out and, where the
        state holds it, its scale error about z."""
        L = self.layout
        om = w - x[L.bias]  # a new array
        if L.scale >= 0:
            om[..., 2] /= 1.0 + x[L.scale]
        return om

    def Q(self, dt: float, have_gyro: bool, still: bool, rate_sq: float = 0.0) -> np.ndarray:
        """The process noise over ``dt`` (cached), at the motion's time scale ``k``; with the
        gyro's scale-and-axes error as attitude noise (:meth:`set_scale_noise`), its share at the
        turn rate's square ``rate_sq`` (rad²/s²): ``σ_s² |ω|² τ dt`` on roll, pitch and yaw,
        the turn's error correlated over the base motion's correlation time ``τ`` (a hand keeps
        turning about one axis for about that long, so the error does not average away
        faster). The heading takes it as the tilt does: a gyro that turns the sensor wrong
        turns its heading wrong by as much, and a heading whose sigma did not grow would
        barely hear the compass that shows it (docs/tracking-hand.md)."""
        key = (round(dt * 1e9), have_gyro, still)  # dt to the nanosecond
        Q = self._Q.get(key)
        if Q is None:
            if len(self._Q) > 64:
                self._Q.clear()
            Q = self._Q[key] = self._make_Q(dt, have_gyro, still)
        k, scale_var = self.k, self._scale_noise_rad2 * rate_sq
        if k == 1.0 and scale_var == 0.0:
            return Q
        st, L = self.settings, self.layout
        Q = Q.copy()
        q = Q.reshape(-1)[::L.size + 1]  # its diagonal (a view: each entry changed as itself)
        if k != 1.0:  # the acceleration's spread k² σ_a, its correlation time τ_a / k
            tau = st.base_accel_tau_s
            q[L.accel] *= k**4 * (-math.expm1(-2.0 * dt * k / tau)) / (-math.expm1(-2.0 * dt / tau))
        if scale_var:
            add = scale_var * st.base_accel_tau_s * dt
            q[L.roll] += add
            q[L.pitch] += add
            q[L.yaw] += add
        return Q

    @property
    def accel_sigma_mps2(self) -> float:
        """The base's acceleration spread now: the config's at the motion's intensity."""
        return self.settings.base_accel_sigma_mps2 * self.k**2

    def _make_Q(self, dt: float, have_gyro: bool, still: bool) -> np.ndarray:
        st, L = self.settings, self.layout
        q = np.zeros(L.size)
        q[L.offset] = self._offset_rw_rad**2 * dt
        rw = st.gyro_noise_dps_per_sqrt_hz if have_gyro else st.attitude_random_walk_deg_per_sqrt_s
        q[L.roll] = q[L.pitch] = q[L.yaw] = (rw * DEG) ** 2 * dt
        q[L.accel] = st.base_accel_sigma_mps2**2 * (1.0 - np.exp(-2.0 * dt / st.base_accel_tau_s))
        if L.jerk_B is not None:  # most of the change comes through the jerk; the rest: bumps
            q[L.accel] *= st.base_accel_direct_share**2
            q[L.jerk_B] = st.base_jerk_sigma_mps3**2 * (1.0 - np.exp(-2.0 * dt / st.base_jerk_tau_s))
            if still:
                q[L.jerk_B] *= st.still_accel_q_factor
        if still:  # a parked chair's acceleration changes only when it sets off
            q[L.accel] *= st.still_accel_q_factor
        if not st.motion_compensation or st.base_fixed:
            q[L.accel] = 0.0
        if st.base_fixed:  # a bolted base keeps its attitude
            q[L.roll] = q[L.pitch] = q[L.yaw] = 0.0
        q[L.bias] = (st.gyro_bias_random_walk_dps_per_sqrt_s * DEG) ** 2 * dt
        q[L.imu_bias] = st.imu_accel_bias_random_walk_g_per_sqrt_s**2 * dt
        if L.scale >= 0:
            q[L.scale] = st.gyro_scale_random_walk_per_sqrt_s**2 * dt
        if L.pivot_B is not None:
            q[L.pivot_B] = st.base_pivot_random_walk_m_per_sqrt_s**2 * dt
        return np.diag(q)


class StillDetector:
    """Exponential averages of the gyro and the IMU accelerometer (and the IMU's NIS): is the
    chair still? The tracker starts at the end of a still window: it is."""

    def __init__(self, settings: TrackerSettings, layout: StateLayout, t_s: float, imu_noise_g: float = 0.0):
        """``imu_noise_g``: the IMU accelerometer's own noise per axis at its rate (its
        description's): a still sensor wanders by that much, so the quiet threshold is at
        least sqrt(2) times it (``still_accel_g`` where that is more: the MPU-9150 at 100 Hz,
        2.8 mg, meets the default 4 mg)."""
        self.settings, self.layout = settings, layout
        self.quiet_accel_g = max(settings.still_accel_g, math.sqrt(2.0) * float(imu_noise_g))
        self.w = 0.0  # EMA of the bias-corrected gyro norm, rad/s
        self.mean = None  # EMA of the IMU accelerometer, g
        self.var = 0.0  # EMA of its squared deviation, g^2 (summed over axes)
        self.still = True
        self.quiet_s = 0.0  # how long the gyro and the IMU accelerometer have been quiet
        self.imu_nis = 3.0  # EMA of the IMU accelerometer's NIS over 0.2 s
        self._imu_nis_t = float(t_s)
        # the settings' thresholds, computed once (:meth:`update` runs every instant)
        self._tau_s = settings.still_tau_s
        self._gyro_limit_rad_s = settings.still_gyro_dps * DEG
        self._quiet_outlasts_s = 3.0 * settings.base_accel_tau_s
        self._limits_for: float | None = None
        self._limits = (0.0, 0.0)

    def update(self, dt: float, gyro: np.ndarray | None, f_imu: np.ndarray | None, x: list) -> None:
        """One instant: ``gyro`` (rad/s, base axes), ``f_imu`` the IMU accelerometer (g), ``x``
        the state (a list)."""
        a = min(1.0, max(dt, 1e-4) / self._tau_s)
        n = self.layout.n_joints
        if gyro is not None:
            b = n + 6  # gyro_bias
            gx, gy, gz = gyro.tolist()
            wx, wy, wz = gx - x[b], gy - x[b + 1], gz - x[b + 2]
            wn = math.sqrt(wx * wx + wy * wy + wz * wz)
            w0 = self.w
            self.w = wn if not math.isfinite(w0) else w0 + a * (wn - w0)
        if f_imu is not None:
            fx, fy, fz = f_imu.tolist()
            if self.mean is None:
                self.mean = [fx, fy, fz]
            else:  # (three floats, not arrays: a step's few numbers)
                mx, my, mz = self.mean
                dx, dy, dz = fx - mx, fy - my, fz - mz
                self.mean = [mx + a * dx, my + a * dy, mz + a * dz]
                self.var += a * (dx * dx + dy * dy + dz * dz - self.var)
        # and the filter itself no longer sees the chair accelerate (a smooth stop looks
        # quiet to the averages before it is over), or the quiet has outlasted any of the
        # base's accelerations (three of their correlation times): then an acceleration the
        # filter still holds is a tilt it mistook for one, and only stillness tells it so
        quiet_g = self.quiet_accel_g
        if quiet_g != self._limits_for:  # (the thresholds, kept while the quiet level is)
            self._limits_for = quiet_g
            self._limits = (3.0 * quiet_g**2, (2.0 * quiet_g * G) ** 2)
        var_limit, accel_limit = self._limits
        quiet = self.w < self._gyro_limit_rad_s and self.var < var_limit
        self.quiet_s = self.quiet_s + dt if quiet else 0.0
        ax, ay, az = x[n + 2:n + 5]  # accel_B
        self.still = quiet and (ax * ax + ay * ay + az * az < accel_limit
                                or self.quiet_s >= self._quiet_outlasts_s)

    def imu_agrees(self, t: float, nis: float, gate_ok: bool) -> bool:
        """The IMU accelerometer's NIS, averaged over 0.2 s: a chair that sets off smoothly
        shows there before any average of the raw readings does."""
        a = min(1.0, max(t - self._imu_nis_t, 0.0) / 0.2)
        self._imu_nis_t = t
        self.imu_nis += a * (min(nis, 100.0) - self.imu_nis)
        return gate_ok and self.imu_nis < 6.0

    def set_off(self) -> None:
        """The chair set off: it is no longer still (the averages will say so later)."""
        self.still = False
        self.quiet_s = 0.0
        self.var = max(self.var, 10.0 * self.quiet_accel_g**2)

    def snapshot(self) -> list:
        return [self.w, self.mean, self.var, self.still, self.quiet_s]

    def restore(self, snap: list) -> None:
        self.w, self.mean, self.var, self.still = snap[:4]
        self.quiet_s = float(snap[4]) if len(snap) > 4 else 0.0
