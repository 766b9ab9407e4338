"""The filter's process model (:class:`ProcessModel`: how the state moves between two
instants, and its noise) and :class:`StillDetector`, which tells when the chair stands
still (then its acceleration is zero: a pseudo-measurement that pins the tilt, and its
process noise shrinks)."""

from __future__ import annotations

import math

import numpy as np

from fusion.tracking.settings import G, StateLayout, TrackerSettings
from fusion.tracking.tracker_kernels import process_points
from models.rotations import DEG


class ProcessModel:
    """Offsets, the gyro bias and the IMU accelerometer's bias take random walks; the
    attitude turns with the gyro (or a random walk without one); the chair's acceleration
    is a first-order Gauss-Markov process."""

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
        self._decay: dict[float, float] = {}
        self._Q: dict = {}
        self._zeros3 = np.zeros(3)

    def fx(self, X: np.ndarray, dt: float, w: np.ndarray | None) -> np.ndarray:
        """Every sigma point at once (compiled:
        :func:`fusion.tracking.tracker_kernels.process_points`): the gyro (minus each point's bias)
        turns the attitude (midpoint rule on the Euler-angle rates), the base's
        acceleration decays, offsets and bias stay."""
        L = self.layout
        decay = self._decay.get(dt)
        if decay is None:
            if len(self._decay) > 64:
                self._decay.clear()
            decay = self._decay[dt] = math.exp(-dt / self.settings.base_accel_tau_s)
        have_w = w is not None
        return process_points(np.ascontiguousarray(X), dt, w if have_w else self._zeros3, have_w,
                              L.roll, L.yaw, L.n_joints + 6, L.n_joints + 2, decay)

    def Q(self, dt: float, have_gyro: bool, still: bool) -> np.ndarray:
        """The process noise over ``dt`` (cached)."""
        key = (round(dt * 1e9), have_gyro, still)  # dt to the nanosecond
        Q = self._Q.get(key)
        if Q is None:
            if len(self._Q) > 64:
                self._Q.clear()
            Q = self._Q[key] = self._make_Q(dt, have_gyro, still)
        return Q

    def _make_Q(self, dt: float, have_gyro: bool, still: bool) -> np.ndarray:
        st, L = self.settings, self.layout
        q = np.zeros(L.size)
        q[L.offset] = self._offset_rw_rad**2 * dt
        rw = st.gyro_noise_dps_per_sqrt_hz if have_gyro else st.attitude_random_walk_deg_per_sqrt_s
        q[L.roll] = q[L.pitch] = q[L.yaw] = (rw * DEG) ** 2 * dt
        q[L.accel] = st.base_accel_sigma_mps2**2 * (1.0 - np.exp(-2.0 * dt / st.base_accel_tau_s))
        if still:  # a parked chair's acceleration changes only when it sets off
            q[L.accel] *= st.still_accel_q_factor
        if not st.motion_compensation:
            q[L.accel] = 0.0
        q[L.bias] = (st.gyro_bias_random_walk_dps_per_sqrt_s * DEG) ** 2 * dt
        q[L.imu_bias] = st.imu_accel_bias_random_walk_g_per_sqrt_s**2 * dt
        return np.diag(q)


class StillDetector:
    """Exponential averages of the gyro and the IMU accelerometer (and the IMU's NIS): is the
    chair still? The tracker starts at the end of a still window: it is."""

    def __init__(self, settings: TrackerSettings, layout: StateLayout, t_s: float):
        self.settings, self.layout = settings, layout
        self.w = 0.0  # EMA of the bias-corrected gyro norm, rad/s
        self.mean = None  # EMA of the IMU accelerometer, g
        self.var = 0.0  # EMA of its squared deviation, g^2 (summed over axes)
        self.still = True
        self.imu_nis = 3.0  # EMA of the IMU accelerometer's NIS over 0.2 s
        self._imu_nis_t = float(t_s)

    def update(self, dt: float, gyro: np.ndarray | None, f_imu: np.ndarray | None, x: list) -> None:
        """One instant: ``gyro`` (rad/s, base axes), ``f_imu`` the IMU accelerometer (g), ``x``
        the state (a list)."""
        st = self.settings
        a = min(1.0, max(dt, 1e-4) / st.still_tau_s)
        n = self.layout.n_joints
        if gyro is not None:
            b = n + 6  # gyro_bias
            gx, gy, gz = gyro.tolist()
            wx, wy, wz = gx - x[b], gy - x[b + 1], gz - x[b + 2]
            wn = math.sqrt(wx * wx + wy * wy + wz * wz)
            w0 = self.w
            self.w = wn if not math.isfinite(w0) else w0 + a * (wn - w0)
        if f_imu is not None:
            fi = f_imu.tolist()
            if self.mean is None:
                self.mean = fi
            else:
                d = [u - v for u, v in zip(fi, self.mean, strict=True)]
                self.mean = [m + a * e for m, e in zip(self.mean, d, strict=True)]
                self.var += a * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - self.var)
        # and the filter itself no longer sees the chair accelerate (a smooth stop looks
        # quiet to the averages before it is over)
        ax, ay, az = x[n + 2:n + 5]  # accel_B
        self.still = (self.w < st.still_gyro_dps * DEG
                      and self.var < 3.0 * st.still_accel_g**2
                      and ax * ax + ay * ay + az * az < (2.0 * st.still_accel_g * G) ** 2)

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
        self.var = max(self.var, 10.0 * self.settings.still_accel_g**2)

    def snapshot(self) -> list:
        return [self.w, self.mean, self.var, self.still]

    def restore(self, snap: list) -> None:
        self.w, self.mean, self.var, self.still = snap
