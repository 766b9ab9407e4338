"""Which joints the sensors can read now, and what the calibration's own uncertainty does
to them.

:class:`Observability` recomputes, every ``observability_period_s`` and whenever the set of
working sensors changes: each joint axis's angle to vertical (gimbal lock), the
information the usable link accelerometers give about the offsets in
``observability_window_s`` (its eigen-decomposition), the hold projection that keeps the
update's gain at zero along directions they cannot read (Schmidt), and the consider
sensitivity: how far each of a calibrated config's correction spreads (and each stated
unmodelled error, and each encoder scale's sigma) has pulled the offsets' estimate, whose
square joins the reported sigmas and the ``ill_conditioned`` test.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking import fixed_base
from armfusion.fusion.tracking.consider import ConsiderColumns
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.observability_kernels import offsets_observability
from armfusion.fusion.tracking.settings import (
    F_AMBIGUOUS,
    F_CONVERGING,
    F_GIMBAL,
    F_ILL,
    F_OUT,
    F_REACQ,
    F_UNOBSERVED,
    S_REJECTING,
    G,
    StateLayout,
    TrackerSettings,
)
from armfusion.models.rotations import DEG


class LinkSensors(NamedTuple):
    """A tracker's link accelerometers as the observability reads them, and the joints'
    limits its flags test."""

    names: tuple[str, ...]
    links: list[int]
    """The link each is on."""
    sees: np.ndarray
    """``(S, n)``: accelerometer s sees joint j (the IMU's row last, where there is one)."""
    min_rad: list[float]
    max_rad: list[float]
    """Each joint's limits."""


class FilterNow(NamedTuple):
    """What the filter holds at the instant of an observability update."""

    x: np.ndarray
    """The state."""
    P: np.ndarray
    """Its covariance."""
    P0: np.ndarray
    """The startup's covariance."""
    q_enc: np.ndarray
    """The encoders' angles (rad)."""


class Observability:
    """The observability of the offsets and the consider sensitivity (its columns:
    ``columns``), for a tracker's link accelerometers ``sensors``."""

    def __init__(self, settings: TrackerSettings, layout: StateLayout, sensors: LinkSensors,
                 columns: ConsiderColumns):
        self.settings, self.layout = settings, layout
        self.link_names, self.sees, self.columns = sensors.names, sensors.sees, columns
        self._links, self._lo, self._hi = sensors.links, sensors.min_rad, sensors.max_rad
        self.spread_m = columns.m
        self._eye_state = np.eye(layout.size)
        n = layout.n_joints  # the kernel's outputs (copied out: their holders keep them)
        self._axis_deg, self._achievable = np.empty(n), np.empty(n)
        self._locked, self._wide = np.empty(n, np.bool_), np.empty(n, np.bool_)
        self._blind = np.zeros(n, np.bool_)  # gravity-blind by the IMU's own up (see update)
        self.tilt_floor_var = 0.0
        """What the accelerometers' floors leave in the base's tilt (rad²;
        :func:`armfusion.fusion.tracking.fixed_base.floor_var_rad2`), bolted or moving."""
        self.tilt_start_holds = False
        """Whether the startup's tilt variance may stand below that floor (a bolted base's:
        its level's prior or the installer's, :mod:`armfusion.fusion.tracking.fixed_base`); a
        moving base's start is a still average, which the floor bounds as any other."""
        self.reset()

    def reset(self) -> None:
        """Nothing read yet (a tracker's initialisation)."""
        n = self.layout.n_joints
        self.axis_deg = np.full(n, 90.0)
        self.locked = np.zeros(n, bool)
        self.observed = np.zeros(n, bool)
        self.ill = np.zeros(n, bool)
        self.hold: np.ndarray | None = None
        """The projection that holds the unreadable directions (None: nothing held)."""
        self.held_wide: np.ndarray | None = None
        """The offsets of the gimbal-locked joints (held) that the filter knows no better than
        ``mean_state_held_sigma_deg``, as unit columns ``(n, h)`` (None: none): the tracker
        takes the innovation without the sigma points' spread along them (see
        ``TrackerSettings.innovation_at_mean_state``)."""
        self.sys_var = np.zeros(n)
        """Per joint, the variance the filter's own does not hold (rad²): the calibration's
        (``diag(S S^T)``) and, while a joint is unread, what covers its limits."""
        self.unread_var = np.zeros(n)
        self._read_since: dict[int, float] = {}  # per unread joint, since when it has been readable
        """Per joint the startup could not read and gravity has not read since: the variance
        that covers every angle inside its limits (0 once read; see :meth:`set_unread`)."""
        self.consider = np.zeros((n, self.spread_m))
        self.consider_t: float | None = None
        self._consider_q_enc = None
        self._consider_used: set[int] = set()
        self.tilt_var = np.zeros(2)
        """A bolted base's: the variance (rad², roll and pitch) the reported tilt adds to the
        filter's (:func:`armfusion.fusion.tracking.fixed_base.tilt_shortfall_var`)."""
        self._key = None
        self._cache: dict = {}

    def set_rates(self, accel_sigma_g: np.ndarray, accel_rate_hz: np.ndarray) -> None:
        """The accelerometers' noise ``(S, 3)`` (g) and rates (Hz)."""
        self._accel_sigma_g, self._accel_rate = accel_sigma_g, accel_rate_hz
        self._cache = {}  # per set of link accelerometers: see _obs_sel

    def snapshot(self) -> list:
        return self.consider.tolist()

    def restore(self, consider: list, t_s: float) -> None:
        c = np.array(consider, dtype=float)
        if c.shape == self.consider.shape:
            self.consider = c
            self._set_sys_var()
            self.consider_t = float(t_s)

    def set_unread(self, var_rad2: np.ndarray) -> None:
        """The joints nothing has read yet, and per joint the variance that covers its limits
        (0 for the others): added to the joints' reported variance until gravity reads them."""
        self.unread_var = np.asarray(var_rad2, float).copy()
        self._set_sys_var()

    def _set_sys_var(self) -> None:
        """:attr:`sys_var` from the consider sensitivity and the unread joints' cover (a new
        array each time: its holders compare identities to see a change)."""
        self.sys_var = (self.consider**2).sum(axis=1) + self.unread_var

    def update(self, t: float, frame: Frames, used: tuple[int, ...], now: FilterNow,
               slips_calibration: np.ndarray, imu_up: np.ndarray | None = None) -> None:
        """Each joint axis's angle to vertical, and the information the usable link
        accelerometers give about the offsets in ``observability_window_s``; sets the hold
        projection (Schmidt) and the inputs of the joint flags, at ``t``, from what the filter
        holds ``now`` (the state, its covariance, the startup's, the encoders' angles). Writes
        into ``slips_calibration`` what the calibration leaves in the link accelerometers'
        innovations (see :class:`armfusion.fusion.tracking.slips.SlipDetector`).

        A joint is gravity-blind (``gimbal_lock``, held) when its axis is within the lock angle
        (``gimbal_lock_deg`` and three of the tilt's sigmas) of the filter's vertical, or of
        ``imu_up`` (base axes: the base IMU's own averaged reading of up, its bias removed)
        for a joint the filter knows no better than ``mean_state_held_sigma_deg``, whichever
        says so. The filter's tilt is pulled by every accelerometer it reads: on a
        shaking frame, a link accelerometer beyond a vertical joint whose angle is unknown
        reads the frame's acceleration turned by that unknown angle, and the filter's tilt
        wandered by degrees in it (5-8° on a simulated rig spun at 300 °/s with its frame
        shaking at 0.1 g, the true tilt 0.1°). Past the lock angle the joint then read that
        wandering tilt's horizontal gravity as information about its angle and grew
        confidently wrong. The IMU's average is what the base's own accelerometer says, which
        no link accelerometer pulls. A joint the filter knows is not pulled that way (the
        readings beyond it are turned by a known angle), and the IMU's average leans with a
        chair's accelerations: its angle is judged by the filter's tilt alone."""
        st, L, n = self.settings, self.layout, self.layout.n_joints
        x, P, P0 = now.x, now.P, now.P0
        key = self._key
        if key is not None and key[1] == used and t - key[0] < st.observability_period_s:
            return
        self._key = (t, used)
        if self.tilt_floor_var > 0.0:
            ix = [L.roll, L.pitch]
            start = P0[ix, ix] if self.tilt_start_holds else np.full(2, np.inf)
            self.tilt_var = fixed_base.tilt_shortfall_var(self.tilt_floor_var, P[ix, ix], start)
        sr, cr = math.sin(x[L.roll]), math.cos(x[L.roll])
        sp, cp = math.sin(x[L.pitch]), math.cos(x[L.pitch])
        up = np.array([-sp, sr * cp, cr * cp])
        # within the lock angle of vertical, or maybe so: the base's tilt is known only to its
        # sigma, and a gravity reading through a tilt that uncertain is not a reading
        tilt_sigma_deg = math.degrees(math.sqrt(max(P[L.roll, L.roll], P[L.pitch, L.pitch], 0.0)))
        base = x[L.accel] + G * up
        sel, coef = self._obs_sel(used)
        P_off = np.ascontiguousarray(P[:n, :n])
        self._blind[:] = False
        if imu_up is not None:  # (only a joint the filter does not know: see above)
            lock_deg = st.gimbal_lock_deg + 3.0 * tilt_sigma_deg
            c = np.minimum(np.abs(frame.axes @ imu_up), 1.0)
            unknown = np.diagonal(P_off) > (st.mean_state_held_sigma_deg * DEG) ** 2
            self._blind[:] = (np.degrees(np.arccos(c)) < lock_deg) & unknown
        W, U = self._kernel(frame, up, tilt_sigma_deg, base, sel, coef, P_off)
        self.locked = self._locked.copy()
        self.axis_deg = self._axis_deg.copy()
        self.observed = self.sees[sel].any(axis=0) if len(sel) else np.zeros(n, bool)
        if U.shape[1]:
            T = self._eye_state.copy()
            T[:n, :n] -= U @ U.T
            self.hold = T
        else:
            self.hold = None
        self.held_wide = self._eye_state[:n, :n][:, self._wide] if self._wide.any() else None
        achievable = self._achievable.copy()
        if self.spread_m:
            # the calibration's pull, over every link accelerometer used since the last time
            # (the sets of the updates since: sensors read lately, or each alone where a caller
            # passes the sets of single updates)
            self._consider_used.update(used)
            if self.consider_t is None:  # the first time: the startup read every one of them
                self._consider_used.update(range(len(self.link_names)))
            if self.consider_t is None or t - self.consider_t >= st.observability_period_s:
                both = tuple(sorted(self._consider_used))
                self._consider_used = set()
                if both:
                    sel_c, coef_c = self._obs_sel(both)
                    if both == tuple(used):
                        W_c, hold_c = W, self.hold
                    else:  # what the filter holds, judged on the information of them all
                        W_c, U_c = self._kernel(frame, up, tilt_sigma_deg, base, sel_c, coef_c, P_off)
                        hold_c = None if not U_c.shape[1] else self._eye_state[:n, :n] - U_c @ U_c.T
                    self._consider_update(t, frame, sel_c, base, W_c, hold_c, now, slips_calibration)
        self.ill = np.sqrt(achievable**2 + self.sys_var) > st.sigma_limit_deg * DEG

    def _kernel(self, frame: Frames, up: np.ndarray, tilt_sigma_deg: float, base: np.ndarray,
                sel: np.ndarray, coef: np.ndarray, P_off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`armfusion.fusion.tracking.observability_kernels.offsets_observability` for the link
        accelerometers ``sel``: the information rows ``W (3S', n)`` and the held span
        ``U (n, h)``; the axes' angles to vertical, the locked and wide joints and each
        offset's achievable sigma into this object's scratch arrays."""
        st = self.settings
        return offsets_observability(
            frame.axes, up, st.gimbal_lock_deg + 3.0 * tilt_sigma_deg, frame.motion_mps2, base, frame.K,
            frame.R_0S, sel, coef, P_off, 1.0 / (st.sigma_limit_deg * DEG) ** 2,
            (st.mean_state_held_sigma_deg * DEG) ** 2, self._blind, self._axis_deg, self._locked, self._wide,
            self._achievable)

    def _consider_update(self, t: float, frame: Frames, sel: np.ndarray, base: np.ndarray, W: np.ndarray,
                         hold: np.ndarray | None, now: FilterNow, slips_calibration: np.ndarray) -> None:
        """The calibration's own uncertainty in the offsets, carried as the filter carries
        what it learnt (a consider, or Schmidt, sensitivity). Each of a calibrated config's
        correction spreads (every calibrated element moved by its sigma along a principal
        direction, ``StartupCorrection.spread``) is a constant error in a sensor's corrected
        reading; ``self.consider`` (n, m) is how far each spread has pulled the offsets'
        estimate so far. Since the last update the filter took the information ``A`` that
        the used readings gave (the window's ``W``, scaled to the time elapsed, without the
        held directions) and, with it, each spread's pull ``B``; the estimate moved by the
        same gain: ``S += P (B - A S)``, with P the filter's offset covariance, which already
        holds ``A``. What the filter learnt from a pose keeps that pose's calibration error
        until new readings replace it (a joint read once in a poorly conditioned pose, then
        held, keeps its doubt). Reported sigmas and the ``ill_conditioned`` flag include
        ``diag(S S^T)``; the filter's own covariance does not. ``sel``: the link accelerometers
        read since the last time, ``W`` their information rows and ``hold`` the projection
        the filter held them with; ``base``: the base's specific force."""
        n = self.layout.n_joints
        P_now, P0, q_enc = now.P, now.P0, now.q_enc
        window = self.settings.observability_window_s
        # the first time: the startup's answer already rests on at least a window of these
        # readings (its still stretch), so it carries a whole window's pull
        first = self.consider_t is None
        dt = window if first else max(t - self.consider_t, 0.0)
        self.consider_t = t
        w = min(dt, window) / window
        if w <= 0.0:
            return
        k = len(sel)
        E = self.columns.errors(frame, sel, frame.motion_mps2[sel] + base, base, self._accel_sigma_g,
                                self._accel_rate, window).reshape(3 * k, -1)  # (3k, m)
        Wn = W if hold is None else W @ hold[:n, :n]
        A = (Wn.T @ Wn) * w
        B = (Wn.T @ E) * w
        # the information the filter held before these readings: its covariance's inverse
        # less what they gave (clipped: a gated reading gave less than the window says); the
        # first time, the startup's (the filter has taken a few of these readings already)
        P = P0[:n, :n] if first else P_now[:n, :n]
        lam, V = np.linalg.eigh(np.linalg.inv(P) - A)
        prior = (V * np.clip(lam, 0.0, None)) @ V.T
        S = self.consider
        cols = self.columns
        if len(cols.scale_joints):  # the true offsets moved with the encoders since
            if self._consider_q_enc is not None:
                travel = q_enc[cols.scale_joints] - self._consider_q_enc[cols.scale_joints]
                S[cols.scale_joints, cols.scale_cols] += cols.scale_sigma * travel
            self._consider_q_enc = q_enc.copy()
        self.consider = np.linalg.solve(prior + A + 1e-12 * np.eye(n), prior @ S + B)
        self._set_sys_var()
        # what each spread leaves in the readings once the offsets have taken their pull: a
        # lasting shift of the innovations the slip test must not take for a slip
        links = sel < len(self.link_names)
        if links.any():
            D = E.reshape(k, 3, -1)[links]
            scale = self._accel_rate[sel[links]] * self.settings.observability_window_s
            slips_calibration[sel[links]] = (D @ D.transpose(0, 2, 1)) / scale[:, None, None]

    def _obs_sel(self, used: tuple[int, ...]):
        """The link accelerometers ``used`` as an index array, and the factor that turns
        their Jacobian rows into information rows: ``-sees / sigma * sqrt(rate * window) / g``
        (cached per set)."""
        hit = self._cache.get(used)
        if hit is None:
            sel = np.array(used, dtype=int)
            w = np.sqrt(self._accel_rate[sel] * self.settings.observability_window_s)
            coef = -(self.sees[sel][:, None, :] / self._accel_sigma_g[sel][:, :, None])
            coef *= (w / G)[:, None, None]
            hit = self._cache[used] = (sel, coef)
        return hit

    def joint_flags(self, t: float, codes: list[int], P: np.ndarray, q: np.ndarray,
                    ambiguous: np.ndarray, reacquiring_until: np.ndarray) -> np.ndarray:
        """Each joint's flag (:data:`armfusion.fusion.tracking.settings.JOINT_FLAGS`: the most severe
        condition wins) from the link accelerometers' status ``codes``, the covariance ``P``,
        the joint angles ``q`` (against the joints' limits), the joints with rival branches
        and until when each is re-acquired. A few joints: plain Python."""
        st, n = self.settings, self.layout.n_joints
        links, lo, hi = self._links, self._lo, self._hi
        nl = len(self.link_names)
        # a joint is seen by a usable link accelerometer on a later link
        reach = max((links[i] for i in range(nl) if codes[i] <= S_REJECTING), default=-1)
        sig = [math.sqrt(max(p, 0.0) + v)
               for p, v in zip(P.diagonal()[:n].tolist(), self.sys_var.tolist(), strict=True)]
        ql = q.tolist()
        lim, margin = st.sigma_limit_deg * DEG, st.limit_margin_deg * DEG
        flags = []
        for j in range(n):
            if ambiguous[j]:
                f = F_AMBIGUOUS
            elif self.locked[j]:
                f = F_GIMBAL
            elif reach <= j:
                f = F_UNOBSERVED
            elif self.ill[j] and self.observed[j]:
                f = F_ILL
            elif reacquiring_until[j] > t:
                f = F_REACQ
            elif ql[j] < lo[j] - margin or ql[j] > hi[j] + margin:
                f = F_OUT
            elif sig[j] > lim:
                f = F_CONVERGING
            else:
                f = 0
            flags.append(f)
        if self.unread_var.any():  # a joint read at last no longer needs its limits' cover:
            # read for a whole observability window (the information is the window's; and a
            # test of the axis at the first instants, before the base IMU's average holds,
            # is a test of one shaken sample)
            read = []
            for j in range(n):
                if self.unread_var[j] > 0 and flags[j] not in (F_GIMBAL, F_UNOBSERVED):
                    since = self._read_since.setdefault(j, t)
                    if t - since >= st.observability_window_s:
                        read.append(j)
                else:
                    self._read_since.pop(j, None)
            if read:
                self.unread_var = self.unread_var.copy()
                self.unread_var[read] = 0.0
                self._set_sys_var()
        return np.array(flags, dtype=np.int8)
