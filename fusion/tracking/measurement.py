"""The measurement model of one update: every accelerometer's specific force, the still
chair's zero acceleration and the tilt-compensated heading, at every sigma point
(compiled: :func:`armfusion.fusion.tracking.tracker_kernels.measurement_points`, whose docstring has the
model); the accelerometers' noise at their rates (:meth:`Measurements.with_noise`); and the
update's groups, each gated on its own NIS (:meth:`Measurements.plan`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.calibrated import StampOffsets
from armfusion.fusion.tracking.differentiator import derivative_noise_gain
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.settings import GYRO, MAG, G, StateLayout, TrackerSettings
from armfusion.fusion.tracking.tracker_kernels import measurement_points
from armfusion.fusion.tracking.turn_kernels import cross_rows, origin_accel_points
from armfusion.fusion.tracking.ukf_groups import GroupPlan, MeasurementGroup, nis_bound
from armfusion.models.motion import cross
from armfusion.models.rotations import DEG
from armfusion.models.sensor_models import StreamModel


class Selection(NamedTuple):
    """What an update needs to know of a set of accelerometers (:meth:`Measurements.selection`,
    cached per set)."""

    key: bytes
    """The set's indices as bytes (the key of its cached plan)."""
    imu_pos: int
    """The base IMU's position in the set (-1: absent)."""
    full: bool
    """Whether the set is every accelerometer, in order."""
    var_g2: np.ndarray | None
    """Their datasheet variances, ``(k, 3)`` (g²)."""


class AccelReadings(NamedTuple):
    """One instant's accelerometer samples, admitted (finite, not saturated)."""

    index: np.ndarray | None
    """``(k,)`` int64: each one's index in the tracker's ``sensor_names``."""
    counts: np.ndarray
    """``(k, 3)``: as the devices gave them."""
    g: np.ndarray | None
    """``(k, 3)``: in g, sensor axes, the config's corrections applied."""
    selection: Selection


class Stack(NamedTuple):
    """One update's stacked measurement (:meth:`Measurements.stack`)."""

    index: np.ndarray | None
    """The accelerometers' indices (as :attr:`AccelReadings.index`)."""
    counts: np.ndarray
    f_g: np.ndarray | None
    """Their readings in g, each turned back to its time stamp."""
    selection: Selection
    var_a: np.ndarray | None
    """Their variances at this instant, ``(k, 3)`` (g²): the frame's."""
    z: np.ndarray
    """``(m,)``: the readings, the still chair's zero acceleration, a row left for the heading."""
    var: np.ndarray
    """``(m,)``: their variances (the heading's left to fill)."""


class Measurements:
    """The measurement side of a tracker with accelerometer streams ``accel_streams``
    (the IMU's at ``imu_index``, -1 without), on links ``links``; ``names`` every stream it
    takes; ``unmodelled_g`` per accelerometer the error each reading carries beyond the
    datasheet noise (the config's unmodelled error with its fast one);
    ``stamps`` per accelerometer its time stamp's offset and variance (None: none stated)."""

    def __init__(self, settings: TrackerSettings, layout: StateLayout, names: tuple[str, ...],
                 accel_streams: tuple[str, ...], links: np.ndarray, imu_index: int,
                 unmodelled_g: np.ndarray, stamps: StampOffsets):
        self.settings, self.layout, self.names, self.accel_streams = settings, layout, names, accel_streams
        self.links = links.astype(np.int64)
        self.imu_index = imu_index
        self.unmodelled_g, self.time_offset_s, self.time_var_s2 = unmodelled_g, stamps.offset_s, stamps.var_s2
        self._no_acc = AccelReadings(None, np.zeros((0, 3)), None, Selection(b"", -1, False, None))
        self.rows = np.arange(3 * len(accel_streams)).reshape(-1, 3)
        self._gate3 = float(nis_bound(3, settings.gate_significance))
        self._gate1 = float(nis_bound(1, settings.gate_significance))
        self._no_field = np.full(3, np.nan)
        self._no_sel = np.zeros(0, dtype=np.int64)
        self.still_var3 = np.full(3, settings.still_accel_sigma_mps2**2)
        self._plans: dict = {}
        self._masks: dict = {}

    def set_rates(self, models: Mapping[str, StreamModel], rates: Mapping[str, float]) -> None:
        """The accelerometers' noise at their rates (datasheet rms with the unmodelled
        floor), and the differentiated gyro's noise."""
        st = self.settings
        sig = []
        for i, s in enumerate(self.accel_streams):
            m = models[s]
            floor = max(st.accel_floor_g, self.unmodelled_g[i])
            sig.append(np.sqrt((m.noise_counts_rms / np.abs(m.gain)) ** 2 + floor**2))
        self.accel_sigma_g = np.array(sig).reshape(-1, 3)  # (S, 3)
        self.accel_var_g2 = self.accel_sigma_g**2
        self.accel_rate_hz = np.array([rates[s] for s in self.accel_streams])
        # noise of the gyro's causal derivative: the fit's weights on unit white noise
        r = rates.get(GYRO, 100.0)
        W = st.gyro_window
        gain = derivative_noise_gain(np.arange(W) / r, st.gyro_order)
        sig_w = st.gyro_noise_dps_per_sqrt_hz * DEG * np.sqrt(r / 2.0)
        self.omega_dot_noise = float(gain * sig_w)
        self._sel: dict = {}  # per set of accelerometers: see selection

    def h_all(self, X, frame: Frames, sel, m_B, still=False, heading_shift_rad: float = 0.0,
              omega_B: np.ndarray | None = None):
        """Every measurement of one update at every sigma point, ``(N, m)``: the
        accelerometers ``sel`` (specific force in g), the still chair's zero acceleration,
        the heading residual ``yaw - tilt-compensated heading`` when ``m_B`` (the mean
        field in base axes) is given (``heading_shift_rad``: the declination less π).

        With a pivot (``layout.pivot_B``) and the base's rate ``omega_B`` (rad/s, base axes),
        the acceleration state is the pivot's and every sensor is moved with the base's origin,
        whose acceleration is the pivot's plus ``ω̇ × r + ω × (ω × r)`` at each point's offset
        ``r`` (``ω̇`` the frame's causal derivative of the gyro): the points' acceleration
        columns are replaced by it before the compiled model (a copy; the still chair's rows
        then read it too, and with ``ω`` near zero it is the pivot's)."""
        L = self.layout
        n = L.n_joints
        if L.pivot_B is not None and omega_B is not None:
            X = origin_accel_points(X, L.pivot_B.start, L.accel.start, omega_B, frame.omega_dot_B)
        if sel is None:
            sel = self._no_sel
        field = self._no_field if m_B is None else m_B
        shift = heading_shift_rad if m_B is not None else 0.0
        return measurement_points(np.ascontiguousarray(X), sel, self.links, frame.axes, frame.offset_ref,
                                  frame.motion_mps2, frame.R_0S, self.imu_index, L.roll, n + 2, L.yaw,
                                  n + 9, G, bool(still), field, shift)

    def pivot_variance(self, frame: Frames, r_m: np.ndarray, P_r: np.ndarray) -> float:
        """Every accelerometer row's extra variance (g²) from the base turning about its pivot
        at the offset ``r_m`` (m, its covariance ``P_r``): the differentiated gyro's error (its
        noise and lag, as :meth:`with_noise` takes them) times the offset's expected length."""
        wd_err = (self.omega_dot_noise + self.settings.angular_accel_error_fraction
                  * float(frame.omega_dot_norm)) / G
        return wd_err * wd_err * (float(r_m @ r_m) + float(P_r.trace()))

    def with_noise(self, frames: Frames) -> Frames:
        """``frames`` with the accelerometers' measurement variances at their instants
        (g²): the datasheet noise at the stream's rate with the unmodelled floor, a share of
        the predicted motion acceleration (the differentiator), and the differentiated
        gyro's error times the sensor's distance from the IMU."""
        st = self.settings
        wd_err = (self.omega_dot_noise + st.angular_accel_error_fraction * frames.omega_dot_norm) / G
        # (x * x: a NumPy scalar's ** 2 goes through pow, which can differ in the last bit from an
        # array's square; so one instant's frame (live) and a block's (a run) agree to the bit)
        extra = ((st.motion_model_fraction * frames.motion_g) ** 2
                 + (wd_err * wd_err)[..., None] * frames.dist2_m2)
        var = self.accel_var_g2 + extra[..., None]
        if self.time_var_s2 is not None and frames.omega_S_rad_s is not None:
            # a stamp known to sigma_t reads gravity turned by omega x g sigma_t (sensor axes)
            turn = cross(frames.omega_S_rad_s, frames.R_0S[..., 2, :])
            var = var + self.time_var_s2[:, None] * turn**2
        return frames._replace(accel_var_g2=var)

    def stack(self, acc: AccelReadings | None, frame: Frames | None, still: bool, mag: bool) -> Stack:
        """One update's stacked measurement ``z`` and its variances ``var``: the
        accelerometers ``acc`` (None: none), each turned back to its time stamp, with the
        frame's variances ``var_a``; the still chair's zero acceleration; a last row left for
        the heading when ``mag``."""
        sel, counts, f, info = self._no_acc if acc is None else acc
        var_a = None
        k = len(counts)
        if acc is not None:
            if self.time_offset_s is not None and frame.omega_S_rad_s is not None:
                # a reading stamped late by dt saw gravity (and the acceleration, as a vector in
                # the world) dt earlier: turn it to the stamp (what the acceleration changed by
                # over dt is left: neither a world-fixed nor a body-fixed one is right for all)
                f = f - self.time_offset_s[sel][:, None] * cross_rows(frame.omega_S_rad_s[sel], f)
            var_a = frame.accel_var_g2 if info.full else frame.accel_var_g2[sel]
        m = 3 * k + (3 if still else 0) + mag
        z = np.zeros(m)
        var = np.empty(m)
        if k:
            z[:3 * k] = f.reshape(-1)
            var[:3 * k] = var_a.reshape(-1)
        if still:
            var[3 * k:3 * k + 3] = self.still_var3
        return Stack(sel, counts, f, info, var_a, z, var)

    def selection(self, sel: np.ndarray) -> Selection:
        """For the accelerometers ``sel`` (cached): its key, the IMU's position in it (-1:
        absent), whether it is every accelerometer in order, and their datasheet variances."""
        key = sel.tobytes()
        info = self._sel.get(key)
        if info is None:
            hit = np.flatnonzero(sel == self.imu_index)
            full = bool(len(sel) == len(self.accel_streams) and np.array_equal(sel, np.arange(len(sel))))
            info = self._sel[key] = Selection(key, int(hit[0]) if len(hit) else -1, full,
                                              self.accel_var_g2[sel].copy())
        return info

    def readings(self, sel: np.ndarray, counts: np.ndarray, g: np.ndarray) -> AccelReadings:
        """The accelerometers ``sel``'s admitted samples of one instant as a record."""
        return AccelReadings(sel, counts, g, self.selection(sel))

    def plan(self, sel_key: bytes, k: int, still: bool, mag: bool) -> GroupPlan:
        """The update's groups: each accelerometer, the still chair, the heading (cached)."""
        key = (sel_key, still, mag)
        plan = self._plans.get(key)
        if plan is None:
            sel = np.frombuffer(sel_key, dtype=np.int64)
            groups = [MeasurementGroup(self.names[sel[i]], self.rows[i], self._gate3) for i in range(k)]
            if still:
                groups.append(MeasurementGroup("base_still", np.arange(3 * k, 3 * k + 3), self._gate3))
            if mag:
                groups.append(MeasurementGroup(MAG, np.array([3 * k + (3 if still else 0)]), self._gate1))
            plan = self._plans[key] = GroupPlan(groups)
        return plan

    def heading_mask(self, m: int) -> np.ndarray:
        """The gain mask of an update of ``m`` rows whose last is the heading: it corrects
        only yaw, the gyro's vertical bias and its scale about z (where a state), never the
        tilt (a steel door must not tilt gravity), the arm, or the chair's acceleration."""
        mask = self._masks.get(m)
        if mask is None:
            L = self.layout
            mask = np.ones((L.size, m))
            mask[:, -1] = 0.0
            mask[L.yaw, -1] = 1.0
            mask[L.bias.start + 2, -1] = 1.0
            if L.scale >= 0:
                mask[L.scale, -1] = 1.0
            self._masks[m] = mask
        return mask
