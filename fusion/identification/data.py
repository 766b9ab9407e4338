"""What a fit sees of a recording: window means of every stream on the encoders' time grid
(:class:`FitData`, :func:`data_from_recording`), the chair's parked stances, the pose the
recording starts from, one-time joint references, and the unknown encoder zeros the model
gains for it (:func:`with_encoder_zeros`).

The encoders are relative: the joint angles of the fit are ``q_ref + encoder angle``, and
every joint's ``joint_offset`` block absorbs the unknown zero ``q_true(0) - q_ref``. That is
why joint offsets are a property of the recording, not of the arm.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.effects import Model, build_effect
from armfusion.models.motion import MotionState
from armfusion.models.rotations import DEG, wrap_angle
from armfusion.models.sensor_models import stream_models

FIT_STREAMS_EXCLUDED = ("enc", "imu_temp")
"""Streams a fit reads but does not fit: the encoders (the joint angles) and the IMU's
temperature (an input of the temperature drift)."""
ENCODER_ZERO_SIGMA_RAD = 10 * DEG
"""Prior σ of a joint's ``joint_offset`` when it carries the recording's unknown encoder zero."""
REFERENCE_SIGMA_RAD = 0.05 * DEG
"""Default σ of a one-time joint reference (a mechanical index, a pose the installer confirms)."""
ENCODER_FIT_HALF_WIDTH_S = 0.08
"""Half the span of encoder samples a fit point's joint angle, rate and acceleration are
read from (:func:`encoder_motion`)."""
ENCODER_FIT_ORDER = 4
"""The degree of the polynomial fitted to them: a minimum-jerk move (a quintic in time) keeps
its acceleration to ~1e-3 of its peak (the moves' starts and ends, where its jerk jumps, to
~2 %)."""


@dataclass(frozen=True)
class JointReference:
    """A joint's true geometric angle, given once, over a still stretch of the recording:
    the joint at a mechanical index, or a pose the installer confirms (``calibrate sensors
    --reference j7=0``). In the fit it is a pseudo-measurement of the joint's geometric angle
    there (encoder angle plus the joint stage: zero offset, sag, play), which pins the
    joint's zero; on a joint whose zero is a gauge (the last joint and the last sensor's
    mount about its axis; the first joint and the IMU's mount about its axis) it is what
    defines the gauge."""

    joint: str
    angle_rad: float
    sigma_rad: float
    t_start_s: float
    t_end_s: float
    encoder_rad: np.ndarray
    """Every joint's relative encoder angle there (mean over the stretch), rad."""
    where: str = "the first still segment"

    def as_dict(self) -> dict[str, Any]:
        return {"joint": self.joint, "angle_deg": round(float(np.degrees(self.angle_rad)), 6),
                "sigma_deg": round(float(np.degrees(self.sigma_rad)), 6),
                "t_start_s": round(float(self.t_start_s), 3), "t_end_s": round(float(self.t_end_s), 3),
                "where": self.where}


@dataclass(frozen=True)
class FitData:
    """What a fit sees: the motion (window means), the measured counts and their σ."""

    state: MotionState
    counts: dict[str, np.ndarray]
    sigma_counts: dict[str, np.ndarray]
    q_ref_rad: np.ndarray
    window: int = 1
    note: str = ""
    nodes: int = 1
    """Instants per fit point: 2 means the state holds each window's two Gauss-Legendre
    nodes (t̄ ± T/(2√3)) one after the other, and a prediction is their mean (exact for a
    reading that is a cubic in time over the window)."""
    stance: np.ndarray | None = None
    """Per point, the parked stretch (stance) of the chair it belongs to, 0…K-1: each stance
    has its own base attitude in the fit. ``None``: one stance (a parked chair)."""
    used: np.ndarray | None = None
    """Per point, whether it enters the fit (``False`` while the chair moves between stances:
    its attitude is not constant there). ``None``: every point."""
    saturated_samples: dict[str, int] = field(default_factory=dict)
    """Per stream, the samples at a register limit; the windows holding them (or interpolated
    from them) are not in the data (``saturated_windows`` of them)."""
    saturated_windows: int = 0
    base_tilt_reference: tuple[np.ndarray, float] | None = None
    """The arm base's roll and pitch (rad, as the base attitude's) in the first stance,
    measured independently (an inclinometer on the base), and that measurement's σ (rad).
    Without it the base's angle about the first joint's axis, that joint's zero and the
    IMU's mount about that axis are one unknown (any set of tilts leaves them so)."""
    joint_references: tuple[JointReference, ...] = ()
    """One-time references of joints' geometric angles (:func:`joint_references`)."""
    sample_excess_counts: dict[str, np.ndarray] = field(default_factory=dict)
    """Per stream and axis, the fast error one sample carries beyond its noise model, in
    counts (:func:`sample_excess`: vibration, say, which a window's mean averages away but a
    filter that reads every sample meets); absent where the scatter is the noise's."""
    start_rivals_rad: tuple[np.ndarray, ...] = ()
    """Other joint angles the recording's still start fits as well as ``q_ref_rad`` (rival
    branches of the startup solve: :func:`start_poses`), for a fit to try; empty where the
    start is unambiguous or ``q_ref_rad`` was given."""

    @property
    def n(self) -> int:
        return self.state.N // self.nodes

    @property
    def n_stances(self) -> int:
        return 1 if self.stance is None else int(self.stance.max()) + 1

    def stance_of_instants(self) -> np.ndarray:
        """The stance of every instant of the state (``nodes`` per point)."""
        st = np.zeros(self.n, int) if self.stance is None else self.stance
        return np.repeat(st, self.nodes)

    def shifted(self, dq_rad: np.ndarray) -> FitData:
        """The same data with ``q_ref`` moved by ``dq_rad`` (after a fit found the zeros)."""
        dq = np.asarray(dq_rad, float)
        return replace(self, state=self.state.replace(q_rad=self.state.q_rad + dq),
                       q_ref_rad=self.q_ref_rad + dq)

    def subset(self, idx: np.ndarray | slice) -> FitData:
        per_point = {k: getattr(self, k)[idx] for k in ("stance", "used") if getattr(self, k) is not None}
        return replace(self._subset_state(idx), **per_point)

    def _subset_state(self, idx: np.ndarray | slice) -> FitData:
        s = self.state
        if self.nodes > 1:  # the nodes of the chosen points
            pts = np.arange(self.n)[idx]
            sidx = (pts[:, None] * self.nodes + np.arange(self.nodes)).ravel()
            st = MotionState(s.t_s[sidx], s.q_rad[sidx], s.qd_rad_s[sidx], s.qdd_rad_s2[sidx],
                             s.R_WB[sidx], s.omega_B_rad_s[sidx], s.omega_dot_B_rad_s2[sidx],
                             s.accel_B_mps2[sidx] if np.ndim(s.accel_B_mps2) > 1 else s.accel_B_mps2,
                             s.temperature_c[sidx] if np.ndim(s.temperature_c) else s.temperature_c)
            return replace(self, state=st, counts={k: v[idx] for k, v in self.counts.items()})
        st = MotionState(s.t_s[idx], s.q_rad[idx], s.qd_rad_s[idx], s.qdd_rad_s2[idx], s.R_WB[idx],
                         s.omega_B_rad_s[idx], s.omega_dot_B_rad_s2[idx], s.accel_B_mps2[idx],
                         s.temperature_c[idx])
        return replace(self, state=st, counts={k: v[idx] for k, v in self.counts.items()})


def encoder_motion(t_s: np.ndarray, q_rad: np.ndarray, t_at_s: np.ndarray,
                   half_width_s: float = ENCODER_FIT_HALF_WIDTH_S, order: int = ENCODER_FIT_ORDER,
                   chunk: int = 20000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint angles, rates and accelerations ``(M, n)`` at the instants ``t_at_s`` from the
    encoders' samples ``t_s (N,)``, ``q_rad (N, n)``: a polynomial of degree ``order`` fitted
    by least squares to the samples within ``half_width_s`` of each instant (at least
    ``order + 1`` of them), its value and derivatives there.

    The fit's accelerometer predictions need the joints' accelerations at its window nodes;
    ``np.gradient`` applied twice to the nodes themselves (0.125 s apart) reads them over
    half a second, which cuts a 1-3 s minimum-jerk move's peaks by up to 15 % (its fourth
    derivative times the span squared over 12): the fit then takes the missing tangential
    acceleration for a lever-arm error (``motion_acceleration``). The encoders' own rate
    reads them over a span a few times shorter, and the quartic follows the move's shape."""
    t = np.asarray(t_s, float)
    q = np.asarray(q_rad, float)
    ta = np.asarray(t_at_s, float)
    N = len(t)
    if N < 3:
        z = np.zeros((len(ta), q.shape[1]))
        return np.stack([np.interp(ta, t, q[:, j]) for j in range(q.shape[1])], 1) if N else z, z, z.copy()
    h = float(np.median(np.diff(t)))
    order = int(min(order, N - 1))
    half = int(min(max(round(half_width_s / h), (order + 2) // 2), (N - 1) // 2))
    order = min(order, 2 * half)
    out = [np.empty((len(ta), q.shape[1])) for _ in range(3)]
    for a in range(0, len(ta), chunk):
        tc = ta[a:a + chunk]
        i = np.clip(np.searchsorted(t, tc), half, N - 1 - half)
        idx = i[:, None] + np.arange(-half, half + 1)
        V = ((t[idx] - tc[:, None]) / h)[..., None] ** np.arange(order + 1)
        coef = np.einsum("mpk,mkj->mpj", np.linalg.pinv(V), q[idx])  # (M, order + 1, n)
        out[0][a:a + chunk] = coef[:, 0]
        out[1][a:a + chunk] = coef[:, 1] / h
        out[2][a:a + chunk] = 2.0 * coef[:, 2] / h ** 2 if order >= 2 else 0.0
    return out[0], out[1], out[2]


def fit_streams(arm: ArmModel) -> list[str]:
    """The streams a fit (calibrate sensors, diagnose) needs of a recording: the encoders and
    every stream of the config's sensors that it fits."""
    return ["enc", *fitted_streams(stream_models(arm))]


def fitted_streams(models: dict) -> list[str]:
    """Of the count models ``models`` (by stream), the streams a fit compares with the model:
    all but :data:`FIT_STREAMS_EXCLUDED` and a link's gyroscope (``link_gyro``: recorded and
    imported, but the model does not predict it yet, so the fit and the workbench leave it out)."""
    return [s for s, m in models.items() if s not in FIT_STREAMS_EXCLUDED and m.kind != "link_gyro"]


def data_from_recording(arm: ArmModel, rec, window: int = 25, q_ref_rad: np.ndarray | None = None,
                        streams: Sequence[str] | None = None,
                        t_range_s: tuple[float, float] | None = None, nodes: int = 1,
                        stances: bool = False) -> FitData:
    """Window means of every stream on the encoders' time grid.

    ``stances=True`` finds where the chair stands parked (:func:`parked_stances`, from the
    IMU's gyro and accelerometer): each parked stretch gets its own base attitude in the fit
    and the windows while the chair moves between them are left out. A recording on a chair
    that never moves gives one stance and every window, as ``stances=False``.

    ``nodes=2`` evaluates the model at each window's two Gauss-Legendre nodes and averages
    them (twice the model evaluations): the mean of a reading over its window then carries
    no bias from the motion within the window (``nodes=1``: a sinusoid's mean is its middle
    value times ``1 - (Δq)²/24``, which a fit takes for a scale error of that size).

    Joint angles are ``q_ref + encoder angle`` (default ``q_ref``: :func:`start_pose`); their
    rates and accelerations at each fit instant come from the encoders' samples around it
    (:func:`encoder_motion`).
    Averaging ``window`` samples divides the noise by √window; the model is evaluated at the
    window's mean angles, which differs from the mean of the readings by about
    ``(Δq)²/24`` of a joint's sweep Δq over the window (for the article's 13.9 °/s roll and
    0.25 s windows: 1.5e-4 g, below the noise of a mean).
    """
    enc = rec.get("enc")
    if enc is None or len(enc) == 0:
        raise ValueError("the recording has no encoder samples ('enc'): the joint angles of the "
                         "maneuver are needed")
    models = stream_models(arm, {s: (rec.get(s).rate_hz or 100.0) if rec.get(s) is not None else 100.0
                                 for s in stream_models(arm)})
    t = np.asarray(enc.t_s, float)
    keep = np.ones(len(t), bool)
    if t_range_s is not None:
        keep = (t >= t_range_s[0]) & (t <= t_range_s[1])
    t = t[keep]
    q_enc = models["enc"].from_counts(enc.values[keep])
    rivals: tuple[np.ndarray, ...] = ()
    if q_ref_rad is None:
        q_ref_rad, *rest = start_poses(arm, rec)
        rivals = tuple(rest)
    q = np.asarray(q_ref_rad, float) + q_enc
    names = fitted_streams(models) if streams is None else list(streams)
    counts, sig, excess = {}, {}, {}
    w = max(1, int(window))
    n = len(t) // w
    if n < 2:
        raise ValueError(f"too few samples ({len(t)}) for windows of {w}")

    def mean(a: np.ndarray) -> np.ndarray:
        a = a[: n * w]
        return a.reshape(n, w, *a.shape[1:]).mean(1)

    reach = np.zeros(len(t) + 1, int)  # instants a saturated sample reaches (below)
    saturated: dict[str, int] = {}
    for s in names:
        st = rec.get(s)
        if st is None or len(st) == 0:
            continue
        v = np.asarray(st.values, float)
        ts = np.asarray(st.t_s, float)
        inside = (ts >= t[0]) & (ts <= t[-1]) if len(t) else np.zeros(len(ts), bool)
        fast = sample_excess(v[inside], models[s].sigma_counts)
        if fast is not None:
            excess[s] = fast
        sat = np.flatnonzero(models[s].saturated(v).any(axis=1))
        if len(sat):  # its window is left out: the instants strictly between its neighbours
            saturated[s] = len(sat)
            before = np.where(sat > 0, ts[np.maximum(sat - 1, 0)], -np.inf)
            after = np.where(sat < len(ts) - 1, ts[np.minimum(sat + 1, len(ts) - 1)], np.inf)
            i0, i1 = np.searchsorted(t, before, "right"), np.searchsorted(t, after, "left")
            np.add.at(reach, i0[i1 > i0], 1)
            np.add.at(reach, i1[i1 > i0], -1)
        if len(ts) != len(enc.t_s) or not np.allclose(ts, enc.t_s):
            v = np.stack([np.interp(t, ts, v[:, k]) for k in range(v.shape[1])], 1)
        else:
            v = v[keep]
        counts[s] = mean(v)
        sig[s] = models[s].sigma_counts / np.sqrt(w)
    temp = 25.0
    ts = rec.get("imu_temp")
    if ts is not None and len(ts):
        tc = models["imu_temp"].from_counts(np.asarray(ts.values, float))[:, 0]
        temp = mean(np.interp(t, np.asarray(ts.t_s, float), tc))
    stance = used = None
    note = ""
    if stances:
        stance, used = parked_stances(arm, rec, mean(t), w)
        if stance is not None:
            note = (f"; {int(stance.max()) + 1} parked stances, each its own base attitude "
                    f"({int((~used).sum())} windows left out while the chair moved)")
    if nodes not in (1, 2):
        raise ValueError(f"nodes must be 1 or 2, not {nodes!r}")
    if nodes == 1:
        _, qd, qdd = encoder_motion(t, q, mean(t))
        state = replace(MotionState.static(mean(q), temperature_c=temp, t_s=mean(t)), qd_rad_s=qd,
                        qdd_rad_s2=qdd)
        data = FitData(state, counts, sig, np.asarray(q_ref_rad, float), w,
                       f"window means of {w} samples" + note, stance=stance, used=used,
                       sample_excess_counts=excess, start_rivals_rad=rivals)
    else:
        tw = t[: n * w].reshape(n, w)
        dt = (tw[:, -1] - tw[:, 0]) * w / max(w - 1, 1)  # the window's length
        tn = (tw.mean(1)[:, None] + dt[:, None] / (2 * np.sqrt(3)) * np.array([-1.0, 1.0])).ravel()
        qn, qd, qdd = encoder_motion(t, q, tn)
        tempn = np.repeat(np.broadcast_to(temp, (n,)), 2)
        state = replace(MotionState.static(qn, temperature_c=tempn, t_s=tn), qd_rad_s=qd, qdd_rad_s2=qdd)
        data = FitData(state, counts, sig, np.asarray(q_ref_rad, float), w,
                       f"window means of {w} samples (model at two nodes per window)" + note, nodes=2,
                       stance=stance, used=used, sample_excess_counts=excess, start_rivals_rad=rivals)
    if saturated:  # a window holding a saturated sample (or interpolated from one) is left out
        bad = (np.cumsum(reach)[: n * w] > 0).reshape(n, w).any(axis=1)
        if int((~bad).sum()) < 2:
            raise ValueError(f"every window of {w} samples holds a saturated sample (a channel at its "
                             f"register limit: " + ", ".join(f"{s} {k:,}" for s, k in saturated.items())
                             + "): nothing left to fit")
        data = replace(data.subset(np.flatnonzero(~bad)), saturated_samples=saturated,
                       saturated_windows=int(bad.sum()),
                       note=data.note + f"; {int(bad.sum()):,} of {n:,} windows left out: they hold "
                       "saturated samples (" + ", ".join(f"{s} {k:,}" for s, k in saturated.items()) + ")")
    return data


def sample_excess(values: np.ndarray, sigma_counts: np.ndarray) -> np.ndarray | None:
    """Per axis, the scatter of single samples ``values (N, k)`` beyond ``sigma_counts`` (the
    noise model's σ of one sample), from their second differences (``v[i+1] - 2 v[i] +
    v[i-1]``: 6σ² for white noise, and nearly nothing of a motion that is smooth over two
    sample intervals, so what is left is noise and what moves faster: vibration). The excess
    is ``√(scatter² − σ²)`` where the scatter exceeds the noise by more than three standard
    errors of the estimate (about 2σ²/√N for white noise); 0 on the other axes; None when no
    axis has one, or there are fewer than 50 samples."""
    v = np.asarray(values, float)
    if v.ndim != 2 or len(v) < 50:
        return None
    d2 = v[2:] - 2.0 * v[1:-1] + v[:-2]
    ok = np.isfinite(d2).all(axis=1)
    n = int(ok.sum())
    if n < 50:
        return None
    var = np.mean(d2[ok] ** 2, axis=0) / 6.0
    s2 = np.asarray(sigma_counts, float) ** 2
    beyond = var - s2 > 3.0 * 2.0 * s2 / np.sqrt(n)
    if not beyond.any():
        return None
    return np.where(beyond, np.sqrt(np.maximum(var - s2, 0.0)), 0.0)


def parked_stances(arm: ArmModel, rec, t_windows_s: np.ndarray, window: int,
                   rate_threshold_rad_s: float = 0.3 * DEG, accel_threshold_g: float = 0.005,
                   margin_s: float = 1.0, min_stance_s: float = 10.0):
    """Where the chair stands parked: per window (``t_windows_s``, means of ``window``
    encoder samples), the stance it belongs to and whether it is parked.

    The chair moves where the IMU's gyro departs from its median (the gyro bias: a
    calibration stands parked most of the time) by more than ``rate_threshold_rad_s`` on
    some axis, or where its accelerometer's window mean changes from one window to the next
    by more than ``accel_threshold_g`` (rolling onto a slope, driving); the arm's own motion
    moves neither. Those windows, ``margin_s`` either side and parked stretches shorter than
    ``min_stance_s`` are left out. Every window gets the nearest stance (so a time
    derivative across the edge of a stance sees one attitude). Returns ``(stance, used)``,
    or ``(None, None)`` when the chair never moves (one stance, every window).
    """
    if arm.imu is None:
        raise ValueError("finding the parked stances needs the base IMU's gyro and accelerometer")
    models = stream_models(arm)
    n = len(t_windows_s)
    moving = np.zeros(n, bool)
    for name, thr, diff in (("imu_gyro", rate_threshold_rad_s, False), ("imu_acc", accel_threshold_g, True)):
        st = rec.get(name)
        if st is None or len(st) == 0:
            raise ValueError(f"finding the parked stances needs the IMU's {name!r} stream")
        v = models[name].from_counts(np.asarray(st.values, float))
        ts = np.asarray(st.t_s, float)
        # the stream's mean over each window, on the windows' own instants
        half = 0.5 * window * np.median(np.diff(ts)) if len(ts) > 1 else 0.0
        cs = np.vstack([np.zeros((1, v.shape[1])), np.cumsum(v, 0)])
        a = np.searchsorted(ts, t_windows_s - half)
        b = np.maximum(np.searchsorted(ts, t_windows_s + half), a + 1)
        b = np.minimum(b, len(ts))
        m = (cs[b] - cs[a]) / np.maximum(b - a, 1)[:, None]
        if diff:
            d = np.zeros(n)
            d[1:] = np.max(np.abs(np.diff(m, axis=0)), 1)
            moving |= d > thr
            moving[:-1] |= d[1:] > thr
        else:
            moving |= np.max(np.abs(m - np.median(m, 0)), 1) > thr
    if not moving.any():
        return None, None
    dt = float(np.median(np.diff(t_windows_s))) if n > 1 else 1.0
    pad = int(np.ceil(margin_s / dt))
    grown = moving.copy()
    for k in range(1, pad + 1):
        grown[k:] |= moving[:-k]
        grown[:-k] |= moving[k:]
    parked = ~grown
    # runs of parked windows
    edges = np.flatnonzero(np.diff(np.concatenate([[0], parked.astype(int), [0]])))
    runs = [(a, b) for a, b in zip(edges[::2], edges[1::2], strict=True) if (b - a) * dt >= min_stance_s]
    if not runs:
        raise ValueError("the chair never stands parked for "
                         f"{min_stance_s:g} s: no stance to calibrate on")
    used = np.zeros(n, bool)
    for a, b in runs:
        used[a:b] = True
    # every window to its nearest run (by index distance to the run's ends)
    idx = np.arange(n)
    dist = np.stack([np.where(idx < a, a - idx, np.where(idx >= b, idx - b + 1, 0)) for a, b in runs])
    return np.argmin(dist, 0), used


def start_pose(arm: ArmModel, rec, window_s: float = 1.0) -> np.ndarray:
    """The joint angles at the recording's first sample: the startup calibration on its first
    ``window_s`` (the arm must be still), the ready pose for joints it cannot tell."""
    return start_poses(arm, rec, window_s)[0]


def start_poses(arm: ArmModel, rec, window_s: float = 1.0) -> list[np.ndarray]:
    """:func:`start_pose`, then its rivals: where the fit may start. First the startup's
    branches on the first still ``window_s`` (its candidates, nearest the ready pose first),
    joints it cannot tell (gimbal lock) at the ready pose: a calibration maneuver starts from
    the ready pose, so that comes first and is right there. Then, where a joint was untold,
    the same branches with it taken from the later still stretches
    (:func:`_later_still_angles`): for a recording that starts elsewhere (random still poses).
    Which one is right the fit's residuals say (:func:`armfusion.fusion.workbench.diagnose.diagnose`
    tries the rivals when the first does not fit the noise).

    Those first starts come from the startup with the config's unmodelled-error floors,
    which leave a branch the data barely prefer open (nearest the ready pose first: right
    for a maneuver that starts there, with effects still to be found). The same starts
    solved with the floors left out (:func:`_nominal`: the pose the nominal model fits best,
    however unsure the config is of it) follow as rivals: with the shipped WMRA's 45 mg every
    joint is ``ill_conditioned``, some with no angle, and a recording that starts at a
    random pose was left in a wrong basin (a clean 60 s ``static-poses`` recording at 3e5
    times its noise). Then, where the still start cannot settle the pose, each later still
    pose's own answer (:func:`_later_still_starts`); at most :data:`MAX_STARTS` in all."""
    q = np.array(arm.ready_pose_rad, float)
    enc = rec.get("enc")
    models = stream_models(arm)
    e = models["enc"].from_counts(enc.values[:1])[0] if enc is not None and len(enc) else 0.0
    nominal = _nominal(arm)
    segments = functools.cache(lambda: _still_segments(rec))  # found once, where needed
    out: list[np.ndarray] = []
    unsettled = False
    # an untold joint starts at the ready pose (as the tracker's startup takes it): its q_ref is
    # the ready angle less the encoder's first reading, which an absolute encoder (a UR's
    # controller angles) does not give as zero
    ready_ref = q - e
    for solver_arm in (arm, nominal):
        found = _still_start_branches(solver_arm, rec, window_s, q, e, models, segments)
        if found is None:
            continue
        branches, settled = found
        unsettled |= not settled
        for b in branches:
            qb = np.where(np.isfinite(b), b - e, ready_ref)
            _add_start(out, qb)
    if not out:  # no still start: the ready pose
        return [ready_ref]
    if enc is not None and len(enc) and unsettled:
        # a start the still start cannot settle: each later still pose's own answer too
        for qb in _later_still_starts(nominal, rec, out[0], window_s, models, segments):
            _add_start(out, qb)
    return out


def _add_start(out: list[np.ndarray], q_ref_rad: np.ndarray) -> None:
    """``q_ref_rad`` appended to the starts ``out`` unless one is there already or they are full."""
    if len(out) < MAX_STARTS and not any(np.allclose(q_ref_rad, o) for o in out):
        out.append(q_ref_rad)


def _still_start_branches(solver_arm: ArmModel, rec, window_s: float, q_ready_rad: np.ndarray,
                          enc0_rad, models, segments) -> tuple[list[np.ndarray], bool] | None:
    """The startup on the recording's first still ``window_s`` solved for ``solver_arm``: its
    branches as geometric angles (NaN where untold; ambiguous joints each way, nearest the
    ready pose first, untold joints filled from later stretches where those tell them), and
    whether it settled the pose (no joint untold, one branch). None without a still start."""
    res = _solve_still_at(solver_arm, rec, rec.t_start_s, window_s)
    if res is None:
        return None
    enc = rec.get("enc")
    geo, branches = _branches(res, q_ready_rad)
    settled = not np.isnan(geo).any() and len(branches) == 1
    if np.isnan(geo).any() and enc is not None and len(enc):
        told = _later_still_angles(solver_arm, rec, geo, enc0_rad, window_s, models, segments)
        untold = np.isnan(geo) & np.isfinite(told)
        if untold.any():
            branches += [np.where(untold, told, b) for b in branches]
    return branches, settled


MAX_STARTS = 16
"""At most this many starts (the first and its rivals) from :func:`start_poses`: each rival
costs the diagnosis a short trial fit (about 0.2 s) where the first does not reach the noise."""


def _later_still_starts(nominal: ArmModel, rec, fallback_ref_rad: np.ndarray, window_s: float, models,
                        segments) -> list[np.ndarray]:
    """Starts (``q_ref``, rad) from the later still stretches, each on its own: the startup's
    angles there (each of its branches where it has several) less the encoder angles there,
    joints it cannot tell from ``fallback_ref_rad``. Where the still start leaves the arm's
    middle joints to a twin or untold (a shoulder at gimbal lock: the elbow and the forearm
    read alike either way), a later pose that tells them all gives a start in the right
    basin, which filling the untold joints one by one (:func:`_later_still_angles`) cannot."""
    out = []
    for res, e in _later_still_solutions(nominal, rec, window_s, models, segments):
        _, sets = _branches(res)
        out += [np.where(np.isfinite(g), g - e, fallback_ref_rad) for g in sets]
    return out


def _still_segments(rec) -> list:
    """The recording's still stretches (:func:`armfusion.fusion.startup.static.find_static_segments`);
    none where it finds none."""
    from armfusion.fusion.startup.static import find_static_segments

    try:
        return list(find_static_segments(rec))
    except Exception:  # noqa: BLE001 - no stretch found
        return []


def _solve_still_at(arm: ArmModel, rec, t0_s: float, window_s: float):
    """The startup's answer on ``rec``'s still ``window_s`` from ``t0_s``; None where it has none."""
    from armfusion.fusion.startup.solve import readings_from_recording, solve_still

    try:
        readings, _ = readings_from_recording(arm, rec, t0_s, t0_s + window_s, window_s)
        return solve_still(arm, readings, propose_unlock=False)
    except Exception:  # noqa: BLE001 - this stretch tells nothing
        return None


def _branches(res, q_near_rad: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """A startup answer's angles (NaN where untold) and its branches: the ambiguous joints
    taken from each candidate (nearest ``q_near_rad`` first, where given)."""
    geo = np.array([je.angle_rad if je.angle_rad is not None else np.nan for je in res.joints])
    if res.candidates_rad is None or len(res.candidates_rad) <= 1:
        return geo, [geo]
    cands = np.asarray(res.candidates_rad, float)
    amb = np.array([je.flag == "ambiguous" for je in res.joints])
    order = (np.argsort(np.abs(wrap_angle(cands - q_near_rad))[:, amb].sum(1), kind="stable")
             if q_near_rad is not None else range(len(cands)))
    return geo, [np.where(amb, cands[int(k)], geo) for k in order]


def _later_still_solutions(arm: ArmModel, rec, window_s: float, models, segments, max_segments: int = 8):
    """For each later still stretch (after the first, up to ``max_segments``) long enough and
    with an answer: the startup's answer there and the encoder angles at its start (rad)."""
    enc = rec.get("enc")
    t_enc = np.asarray(enc.t_s, float)
    for seg in segments()[1:max_segments + 1]:
        if seg.t_end_s - seg.t_start_s < window_s:
            continue
        res = _solve_still_at(arm, rec, seg.t_start_s, window_s)
        if res is None:
            continue
        i = int(np.searchsorted(t_enc, seg.t_start_s))
        yield res, models["enc"].from_counts(enc.values[min(i, len(enc) - 1):][:1])[0]


def _nominal(arm: ArmModel) -> ArmModel:
    """``arm`` with nothing unmodelled (its calibration's floors left out): where a fit starts
    (:func:`start_poses`), not how sure anything is."""
    return replace(arm, calibration=arm.calibration.as_exact())


def _later_still_angles(arm: ArmModel, rec, geo: np.ndarray, enc0_rad: np.ndarray, window_s: float,
                        models, segments) -> np.ndarray:
    """Joints the still start cannot tell (a joint at gimbal lock, a wrist whose roll gravity
    does not see there): their angle at the start from the first later still stretch that
    tells them, carried back through the encoders (``angle there - encoder there + encoder at
    the start``). Joints no stretch tells stay NaN. ``segments``: the recording's still
    stretches, a call (found once per recording: :func:`start_poses`)."""
    geo = geo.copy()
    for res, e in _later_still_solutions(arm, rec, window_s, models, segments):
        for j, je in enumerate(res.joints):
            if np.isnan(geo[j]) and je.angle_rad is not None and je.flag != "ambiguous":
                geo[j] = je.angle_rad - e[j] + enc0_rad[j]
        if not np.isnan(geo).any():
            break
    return geo


def joint_references(arm: ArmModel, rec, specs: Sequence[tuple[str, float, float, float | int | None]]
                     ) -> tuple[JointReference, ...]:
    """One-time references from ``specs``: ``(joint, angle_rad, sigma_rad, when)``, ``when``
    ``None`` (the recording's first still segment), an ``int`` k (its k-th still segment,
    from 1) or a ``float`` time (s, on the recording's clock; the still segment that holds
    it). The arm must be still there (``armfusion.fusion.startup.static.find_static_segments``); the encoder
    angles are their mean over that segment."""
    from armfusion.fusion.startup.static import find_static_segments

    if not specs:
        return ()
    enc = rec.get("enc")
    if enc is None or len(enc) == 0:
        raise ValueError("a joint reference needs the recording's encoder samples ('enc')")
    segs = find_static_segments(rec, models=stream_models(arm))
    q_enc = stream_models(arm)["enc"].from_counts(np.asarray(enc.values, float))
    t_enc = np.asarray(enc.t_s, float)
    seen: set[str] = set()
    out = []
    for joint, angle, sigma, when in specs:
        if joint not in arm.joint_names:
            raise ValueError(f"--reference: no joint {str(joint)[:20]!r} on {arm.name} "
                             f"(joints: {', '.join(arm.joint_names)})")
        if joint in seen:
            raise ValueError(f"--reference: {joint} given twice")
        seen.add(joint)
        j = arm.joint_names.index(joint)
        lo, hi = float(arm.min_rad[j]), float(arm.max_rad[j])
        if not (np.isfinite(angle) and lo - 1e-9 <= angle <= hi + 1e-9):
            raise ValueError(f"--reference {joint}: {np.degrees(angle):.6g}° is outside its limits "
                             f"({np.degrees(lo):.1f}° to {np.degrees(hi):.1f}°)")
        if not (np.isfinite(sigma) and 0 < sigma < 10 * DEG):
            raise ValueError(f"--reference {joint}: σ must be a positive number of degrees below 10, "
                             f"got {np.degrees(sigma):.3g}")
        listing = ", ".join(f"{s.t_start_s:.1f}-{s.t_end_s:.1f} s" for s in segs[:6]) + (
            " …" if len(segs) > 6 else "")
        if not segs:
            raise ValueError(f"--reference {joint}: the recording has no still segment (every sensor "
                             "and encoder quiet for 1 s): the reference must hold while the arm is still")
        if when is None:
            seg, where = segs[0], "the first still segment"
        elif isinstance(when, (int, np.integer)) and not isinstance(when, bool):
            if not 1 <= when <= len(segs):
                raise ValueError(f"--reference {joint}: still segment {when} does not exist (the "
                                 f"recording has {len(segs)}: {listing})")
            seg, where = segs[when - 1], f"still segment {when}"
        else:
            t = float(when)
            inside = [s for s in segs if s.t_start_s <= t <= s.t_end_s]
            if not inside:
                raise ValueError(f"--reference {joint}: the arm is not still at t = {t:.6g} s (still "
                                 f"segments: {listing})")
            seg, where = inside[0], f"the still segment at t = {t:g} s"
        m = (t_enc >= seg.t_start_s) & (t_enc <= seg.t_end_s)
        out.append(JointReference(joint, float(angle), float(sigma), seg.t_start_s, seg.t_end_s,
                                  q_enc[m].mean(0), where))
    return tuple(out)


def with_encoder_zeros(model: Model, sigma_rad: float = ENCODER_ZERO_SIGMA_RAD) -> Model:
    """The model plus a ``joint_offset`` on every joint that lacks one (the recording's unknown
    encoder zeros), prior σ ``sigma_rad`` on all of them."""
    arm = model.arm
    extra = [build_effect(arm, "joint_offset", j) for j in arm.joint_names
             if f"{j}.joint_offset" not in model.index]
    sig = {f"{j}.joint_offset": np.array([sigma_rad]) for j in arm.joint_names}
    return model.with_effects(extra, sigmas=sig)
