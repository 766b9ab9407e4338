"""One instant through the filter, the tracker's pipeline once the instant's frame is made
(:class:`InstantUpdate`): predict (:meth:`InstantUpdate.predict`), the base's stillness and
motion averages (:meth:`InstantUpdate.averages`), the compass's averaged reading
(:meth:`InstantUpdate.compass_reading`), then the update (:meth:`InstantUpdate.fuse`): stack
and innovate every accelerometer and the compass of the instant at once, gate (the base
setting off), let the listeners read the rows (health, the slip detector, the recalibration
alarm, the observability; the compass), correct. It holds the parts it talks to and what it
keeps between instants (the links read lately); the filter, the time, the gyro and the
encoders' angles come with each call."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.tracking.alarm import AccelRows, ModelChangeAlarm
from armfusion.fusion.tracking.compass import Compass
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.health import SensorHealth
from armfusion.fusion.tracking.measurement import AccelReadings, Measurements
from armfusion.fusion.tracking.observability import FilterNow, Observability
from armfusion.fusion.tracking.process import MotionIntensity, ProcessModel, StillDetector
from armfusion.fusion.tracking.settings import C_REJECTED, C_USED, StateLayout, TrackerSettings
from armfusion.fusion.tracking.slips import SlipDetector
from armfusion.fusion.tracking.ukf import BatchedUKF, Innovation
from armfusion.fusion.tracking.update import MagReading, UpdateResult
from armfusion.models.rotations import up_from_tilt


@dataclass(frozen=True, slots=True)
class UpdateParts:
    """What an update talks to: the tracker's parts of a start (:meth:`Tracker.initialise`)."""

    settings: TrackerSettings
    layout: StateLayout
    n_joints: int
    measurements: Measurements
    process: ProcessModel
    observability: Observability
    still: StillDetector
    intensity: MotionIntensity | None
    compass: Compass
    health: SensorHealth
    slips: SlipDetector
    alarm: ModelChangeAlarm
    mag_index: int | None
    """The magnetometer's index among the sensors (None without one)."""
    R_0I: np.ndarray | None
    """The base IMU's axes in the base's (None without an IMU)."""
    P0: np.ndarray
    """The filter's first covariance."""


class InstantUpdate:
    """The update of one instant (:meth:`fuse`), with the links read lately as its own state."""

    def __init__(self, parts: UpdateParts, n_links: int,
                 reacquire: Callable[[int, float], None]):
        """``reacquire(i, t)``: what a sensor's re-acquisition does (the alarm's, the slip
        detector's)."""
        self.parts = parts
        self.reacquire = reacquire
        self.link_read_t = np.full(n_links, -np.inf)
        """Each link accelerometer's last accepted sample, s."""
        self.obs_used_key: tuple | None = None
        self.obs_t = -np.inf
        self._rate_of: tuple | None = None  # (gyro, state, the turn rate): :meth:`turn_rate`

    def predict(self, ukf: BatchedUKF, dt: float, omega_prev: np.ndarray | None, gyro: np.ndarray | None,
                newer_weight: float, attitude_index: np.ndarray) -> np.ndarray | None:
        """Predict over ``dt`` > 0 with the gyro's rate over the interval (from its last
        reading ``omega_prev`` and this instant's ``gyro``, the newer weighted by
        ``newer_weight``: :func:`armfusion.fusion.tracking.process.gyro_newer_weight`), the compass's
        average turned with it. Returns the attitude's anchor (the propagated central
        point's, ``attitude_index``), or None when the step drew no points."""
        p = self.parts
        process = p.process
        w = mid_rate(omega_prev if omega_prev is not None else gyro, gyro, newer_weight)
        rate_sq = 0.0
        if w is not None and p.settings.base_turns_about_any:  # the scale error: σ_s |ω| on the attitude
            om = process.rate(w, ukf.mean)
            rate_sq = float(om @ om)
        Q = process.Q(dt, w is not None, p.still.still, rate_sq)
        ukf.predict(process.fx_tangent, Q, dt=dt, w=w)
        # the attitude is now the propagated central point's plus a tangent vector
        Y = ukf.propagated_points
        anchor = Y[0, attitude_index] if Y is not None else None  # (a copy: fancy indexing)
        if w is not None and p.compass.averaging:  # (the rate is needed mid-period only)
            p.compass.turn(process.rate(w, ukf.mean), dt)
        return anchor

    def averages(self, ukf: BatchedUKF, dt: float, gyro: np.ndarray | None,
                 acc: AccelReadings | None) -> None:
        """The base's stillness and the motion's intensity, from the gyro and the IMU's
        accelerometer."""
        p = self.parts
        imu_f = None
        if acc is not None and p.R_0I is not None and acc.selection.imu_pos >= 0:
            imu_f = acc.g[acc.selection.imu_pos]
        p.still.update(dt, gyro, imu_f, ukf.mean.tolist())
        if p.intensity is not None and imu_f is not None:
            p.intensity.update(dt, imu_f)

    def compass_reading(self, ukf: BatchedUKF, t: float, mag: MagReading, frame: Frames | None,
                        omega_B: np.ndarray | None, q_enc: np.ndarray) -> tuple | None:
        """The magnetometer's sample heard; the compass's averaged reading when it has one
        to give (:meth:`armfusion.fusion.tracking.compass.Compass.prepare`), else None."""
        p = self.parts
        compass = p.compass
        p.health.heard(p.mag_index, t)
        m_B, out = mag.field_B_ut, None
        if compass.listening and frame is not None:
            om = self.turn_rate(omega_B, ukf.mean) if compass.delay_s and omega_B is not None else None
            out = compass.average(t, m_B, om)
        if out is not None:
            x, L = ukf.mean, p.layout
            ix = [L.roll, L.pitch]
            # (the filter's tilt, floored where it claims more than the accelerometers can tell)
            compass.tilt_seen(ukf.covariance[np.ix_(ix, ix)] + np.diag(p.observability.tilt_var))
            out = compass.prepare(t, out[0], out[1], float(x[L.roll]), float(x[L.pitch]), x[L.offset] + q_enc)
        return out

    def fuse(self, ukf: BatchedUKF, t: float, acc: AccelReadings | None, mag: tuple | None,
             frame: Frames | None, omega_B: np.ndarray | None, q_enc: np.ndarray,
             link_read_horizon_s: np.ndarray) -> None:
        """One update with every accelerometer and the magnetometer of this instant, each
        sensor gated on its own NIS: stack and innovate (:meth:`innovate`), gate
        (:meth:`gate`: the base setting off; then health, slips, the alarm and the
        observability read the accelerometers' rows, :meth:`listen_accels`, and the compass
        its row, :meth:`listen_compass`, each deciding what is used), correct."""
        upd = self.innovate(ukf, t, acc, mag, frame, omega_B)
        self.gate(ukf, upd)
        if upd.k:
            self.listen_accels(ukf, upd, q_enc, link_read_horizon_s)
        if mag is not None:
            self.listen_compass(upd)
        ukf.correct(upd.inn, upd.accept, self.parts.observability.hold, upd.mask)

    def innovate(self, ukf: BatchedUKF, t: float, acc: AccelReadings | None, mag: tuple | None,
                 frame: Frames | None, omega_B: np.ndarray | None) -> UpdateResult:
        """Stack this instant's measurements with their noise (a recalibration alarm's
        widening, the compass's variance, a pivot's share) and innovate them at once."""
        p = self.parts
        L, ms = p.layout, p.measurements
        m_B = check = None
        still = p.still.still and acc is not None and p.settings.motion_compensation
        stack = ms.stack(acc, frame, still, mag is not None)
        var = stack.var
        k, m = len(stack.counts), len(stack.z)
        if k and p.alarm.active:  # a changed sensor is down-weighted until recalibrated
            p.alarm.widen(stack.index, var)
        if mag is not None:
            m_count, m_B, extra_var = mag
            x = ukf.mean
            check, var[-1] = p.compass.variance(m_B, up_from_tilt(x[L.roll], x[L.pitch]), m_count)
            var[-1] += extra_var
        plan = ms.plan(stack.selection.key, k, still, mag is not None)
        om = None
        if L.pivot_B is not None and k and omega_B is not None:
            # the base turns about its pivot: the origin's acceleration at every point's offset
            # (Measurements.h_all), the differentiated gyro's error times the offset as noise
            om = self.turn_rate(omega_B, ukf.mean)
            var[:3 * k] += ms.pivot_variance(frame, ukf.mean[L.pivot_B], ukf.covariance[L.pivot_B, L.pivot_B])
        upd = UpdateResult(t, frame, stack, k, still, plan, (m - 1,) if mag is not None else (),
                           p.compass.heading_shift_rad() if mag is not None else 0.0, om, m_B, mag, check)
        upd.inn = inn = self.innovation(ukf, upd)
        upd.accept = inn.gate_ok.copy()
        upd.gate = inn.gate_ok.tolist()
        return upd

    def innovation(self, ukf: BatchedUKF, upd: UpdateResult) -> Innovation:
        wz = self.prediction_weights(ukf) if self.parts.settings.innovation_at_mean_state else None
        s = upd.stack
        return ukf.innovate(s.z, self.h_tangent, s.var, upd.plan, angle_rows=upd.angle_rows,
                            z_weights=wz,
                            frame=upd.frame, sel=s.index, m_B=upd.m_B, still=upd.still,
                            heading_shift_rad=upd.heading_shift_rad, omega_B=upd.omega_B)

    def gate(self, ukf: BatchedUKF, upd: UpdateResult) -> None:
        """Whether the base set off (its still rows failed, or the IMU disagrees while it
        stood): then its acceleration is freed and the update innovated again; whether it is
        calm (the slip detector listens only then)."""
        p = self.parts
        st, L, k, still = p.settings, p.layout, upd.k, p.still
        gate_l = upd.gate
        set_off = upd.still and not gate_l[k]
        imu_ok = True
        if k:
            imu_pos = upd.stack.selection.imu_pos
            if imu_pos >= 0:
                imu_ok = still.imu_agrees(upd.t, upd.inn.nis.item(imu_pos), gate_l[imu_pos])
            set_off |= still.still and not imu_ok
            # the slip detector listens only while the base behaves as modelled: the IMU
            # agrees and the chair is not wrenched about (a lurch is common to all sensors)
            upd.calm = (imu_ok and still.imu_nis < 4.5
                        and upd.frame.omega_dot_norm.item() < st.shift_max_angular_accel_rad_s2)
        if set_off:
            # the chair set off: it is no longer still (the averages will say so later), and
            # its acceleration, held near zero while it stood, must be free to follow at once
            still.set_off()
            ukf.inflate(np.arange(L.accel.start, L.accel.stop), p.process.accel_sigma_mps2**2)
            if L.jerk_B is not None:
                ukf.inflate(np.arange(L.jerk_B.start, L.jerk_B.stop), st.base_jerk_sigma_mps3**2)
            upd.inn = inn = self.innovation(ukf, upd)
            upd.accept = inn.gate_ok.copy()
            if upd.still:
                upd.accept[k] = False
        upd.set_off = set_off

    def listen_accels(self, ukf: BatchedUKF, upd: UpdateResult, q_enc: np.ndarray,
                      link_read_horizon_s: np.ndarray) -> None:
        """The accelerometers' rows: health's verdicts (which are used), the slip detector
        and the recalibration alarm on the residuals, the links read lately
        (``settings.observability_read_periods``: ``link_read_horizon_s``) and the
        observability when they change."""
        p = self.parts
        L, ms, t, k = p.layout, p.measurements, upd.t, upd.k
        s, inn, accept = upd.stack, upd.inn, upd.accept
        sel = s.index
        gate_l = None if upd.set_off else upd.gate
        accept[:k], u, nu, Su = p.health.accel(t, s, inn, gate_l, ms.rows, self.reacquire)
        if u is not None:
            calm = upd.calm and not upd.set_off
            p.slips.listen(t, u, nu, Su, calm, self.reacquire)
            p.alarm.listen(t, u, nu, Su, AccelRows(inn.z_pred, s.var, ms.rows, sel), calm, upd.frame,
                           ukf.mean[L.offset])
        read_t = self.link_read_t
        used = ()
        if len(read_t):  # (none without link accelerometers: an IMU alone)
            for i, a in zip(sel.tolist(), accept[:k].tolist(), strict=True):
                if i < len(read_t):  # (a rejected sample leaves the set at once)
                    read_t[i] = t if a else -np.inf
            used = tuple(np.flatnonzero(t - read_t <= link_read_horizon_s).tolist())
        if used != self.obs_used_key or t - self.obs_t >= p.settings.observability_period_s:
            self.obs_used_key, self.obs_t = used, t
            p.observability.update(t, upd.frame, used, FilterNow(ukf.mean, ukf.covariance, p.P0, q_enc),
                                   p.slips.calibration, self.imu_up(ukf.mean))

    def listen_compass(self, upd: UpdateResult) -> None:
        """The heading's row: the compass's verdict (used or not), the health's count, the
        alarm; the gain mask that keeps the heading off the tilt and the arm."""
        p = self.parts
        inn, check, t = upd.inn, upd.check, upd.t
        use = p.compass.verdict(t, bool(inn.gate_ok[-1]), check, inn.innovation[-1:], inn.S[-1:, -1:],
                                inn.nis[-1])
        mi = p.mag_index
        p.health.rejecting[mi] = not use
        p.health.counts[mi, C_USED if use else C_REJECTED] += upd.mag[0]
        upd.accept[-1] = use
        p.alarm.compass(t, check.disturbed, check.magnitude_error_ut)
        upd.mask = p.measurements.heading_mask(len(upd.stack.z))

    def turn_rate(self, omega_B: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The base's turn rate from the gyro's ``omega_B`` at the state ``x``
        (:meth:`armfusion.fusion.tracking.process.ProcessModel.rate`), kept for the same two
        arrays: the compass's reading and the pivot's rows of one instant read the same
        rate. (The filter replaces its mean on every change and never writes into it, so the
        same array is the same state; the rate is read, never written.)"""
        kept = self._rate_of
        if kept is not None and kept[0] is omega_B and kept[1] is x:
            return kept[2]
        om = self.parts.process.rate(omega_B, x)
        self._rate_of = (omega_B, x, om)
        return om

    def imu_up(self, x: np.ndarray) -> np.ndarray | None:
        """Up in base axes as the base IMU's accelerometer alone reads it: its average over
        ``still_tau_s`` (:class:`armfusion.fusion.tracking.process.StillDetector`), the filter's estimate
        of its bias removed, turned into base axes; None without an IMU reading yet. A
        shaking frame's acceleration averages out of it; the link accelerometers do not pull
        it (see :meth:`armfusion.fusion.tracking.observability.Observability.update`)."""
        p = self.parts
        mean = p.still.mean if p.R_0I is not None else None
        if mean is None:
            return None
        f = p.R_0I @ (np.asarray(mean, float) - x[p.layout.imu_bias])
        norm = float(np.linalg.norm(f))
        return f / norm if norm > 0.5 else None

    def prediction_weights(self, ukf: BatchedUKF) -> np.ndarray | None:
        """The sigma points' weights in the prediction an update's innovation is taken
        against: the unscented mean's (None) unless a joint is gimbal-locked (held) and
        known only widely (30 deg at startup: ``Observability.held_wide``). Then each pair of
        points keeps its weight only for the share of its offsets' displacement off those
        joints: the update does not correct along them, and the points' spread there
        (±65 deg) would shrink the predicted specific force that the joint turns (see
        ``TrackerSettings.innovation_at_mean_state``). None also when the step's points are
        not drawn yet."""
        U = self.parts.observability.held_wide
        X = ukf.propagated_points
        if U is None or X is None:
            return None
        n, ns = self.parts.n_joints, ukf.mean.shape[0]
        D = X[1:1 + ns, :n] - X[0, :n]  # each pair's displacement of the offsets
        d2 = np.einsum("ij,ij->i", D, D)
        along = np.einsum("ij,ij->i", D @ U, D @ U)
        keep = 1.0 - np.divide(along, d2, out=np.zeros(ns), where=d2 > 0.0)
        w = ukf.mean_weights.copy()
        w[1:1 + ns] *= keep
        w[1 + ns:] *= keep
        w[0] = 1.0 - w[1:].sum()
        return w

    def h_tangent(self, X: np.ndarray, **kw) -> np.ndarray:
        """Every measurement at sigma points whose attitude is in the filter's tangent space
        (:meth:`armfusion.fusion.tracking.process.ProcessModel.fx_tangent`), through the Euler-angle
        models (:meth:`armfusion.fusion.tracking.measurement.Measurements.h_all`)."""
        p = self.parts
        return p.measurements.h_all(p.process.euler_points(X), **kw)


def mid_rate(w0: np.ndarray | None, gyro: np.ndarray | None, newer_weight: float) -> np.ndarray | None:
    """The gyro's rate over an interval, ``(1 - k) w0 + k gyro`` (``k`` = ``newer_weight``;
    :func:`armfusion.fusion.tracking.process.gyro_newer_weight`), from its last reading ``w0``
    and this instant's ``gyro`` (either may be None: the other alone). Three floats each,
    the same operations as on the arrays, so the same numbers."""
    if w0 is None or gyro is None:
        return w0 if gyro is None else gyro
    a0, a1, a2 = w0.tolist()
    b0, b1, b2 = gyro.tolist()
    c = 1.0 - newer_weight
    return np.array([c * a0 + newer_weight * b0, c * a1 + newer_weight * b1, c * a2 + newer_weight * b2])
