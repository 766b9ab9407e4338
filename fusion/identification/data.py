"""What a fit sees of a recording: window means of every stream on the encoders' time grid
(:class:`FitData`, :func:`data_from_recording`), one-time joint references, and the unknown
encoder zeros the model gains for it (:func:`with_encoder_zeros`). The chair's parked
stances are :mod:`~armfusion.fusion.identification.stances`'s, the pose the recording starts
from :mod:`~armfusion.fusion.identification.starts`'s (both names importable from here too).

The encoders are relative: the joint angles of the fit are ``q_ref + encoder angle``, and
every joint's ``joint_offset`` block absorbs the unknown zero ``q_true(0) - q_ref``. That is
why joint offsets are a property of the recording, not of the arm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from armfusion.fusion.identification.stances import parked_stances  # importable from here too
from armfusion.fusion.identification.starts import start_poses  # importable from here too
from armfusion.models.arm import ArmModel
from armfusion.models.effects import Model, build_effect
from armfusion.models.effects.library import JointOffset
from armfusion.models.motion import MotionState
from armfusion.models.rotations import DEG
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


class _Windows(NamedTuple):
    """The fit's windows: ``n`` of ``size`` consecutive encoder samples each (the samples past
    the last whole window left out)."""

    n: int
    size: int

    def mean(self, a: np.ndarray) -> np.ndarray:
        """Each window's mean of ``a`` (one row per encoder sample)."""
        a = a[: self.n * self.size]
        return a.reshape(self.n, self.size, *a.shape[1:]).mean(1)


class _StreamMeans(NamedTuple):
    """Every stream's window means on the encoders' grid (counts) and their σ, the fast error
    of its single samples where it has one (:func:`sample_excess`), its saturated samples'
    count, and per encoder instant how many saturated samples reach it (a running sum of
    ``reach``: the instants strictly between a saturated sample's neighbours)."""

    counts: dict[str, np.ndarray]
    sigma: dict[str, np.ndarray]
    excess: dict[str, np.ndarray]
    saturated: dict[str, int]
    reach: np.ndarray


def _stream_means(rec, names: Sequence[str], models: dict, t: np.ndarray, keep: np.ndarray,
                  windows: _Windows) -> _StreamMeans:
    """Each stream of ``names`` that ``rec`` holds, on the encoders' instants ``t`` (the
    encoder samples ``keep`` of the recording's; a stream sampled elsewhere interpolated),
    as window means."""
    enc = rec.get("enc")
    counts, sig, excess = {}, {}, {}
    reach = np.zeros(len(t) + 1, int)
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
        counts[s] = windows.mean(v)
        sig[s] = models[s].sigma_counts / np.sqrt(windows.size)
    return _StreamMeans(counts, sig, excess, saturated, reach)


def _temperature_c(rec, models: dict, t: np.ndarray, windows: _Windows) -> float | np.ndarray:
    """Each window's mean of the IMU's temperature (°C), or 25 °C without one."""
    ts = rec.get("imu_temp")
    if ts is None or not len(ts):
        return 25.0
    tc = models["imu_temp"].from_counts(np.asarray(ts.values, float))[:, 0]
    return windows.mean(np.interp(t, np.asarray(ts.t_s, float), tc))


def _motion(t: np.ndarray, q: np.ndarray, temperature_c, windows: _Windows, nodes: int) -> MotionState:
    """The fit's instants: each window's mean (``nodes=1``) or its two Gauss-Legendre nodes
    (``nodes=2``), with the joints' angles, rates and accelerations there from the encoders
    (:func:`encoder_motion`)."""
    if nodes == 1:
        _, qd, qdd = encoder_motion(t, q, windows.mean(t))
        return replace(MotionState.static(windows.mean(q), temperature_c=temperature_c, t_s=windows.mean(t)),
                       qd_rad_s=qd, qdd_rad_s2=qdd)
    n, w = windows
    tw = t[: n * w].reshape(n, w)
    dt = (tw[:, -1] - tw[:, 0]) * w / max(w - 1, 1)  # the window's length
    tn = (tw.mean(1)[:, None] + dt[:, None] / (2 * np.sqrt(3)) * np.array([-1.0, 1.0])).ravel()
    qn, qd, qdd = encoder_motion(t, q, tn)
    tempn = np.repeat(np.broadcast_to(temperature_c, (n,)), 2)
    return replace(MotionState.static(qn, temperature_c=tempn, t_s=tn), qd_rad_s=qd, qdd_rad_s2=qdd)


def _without_saturated(data: FitData, means: _StreamMeans, windows: _Windows) -> FitData:
    """``data`` without the windows holding a saturated sample (or interpolated from one)."""
    n, w = windows
    saturated = means.saturated
    bad = (np.cumsum(means.reach)[: n * w] > 0).reshape(n, w).any(axis=1)
    if int((~bad).sum()) < 2:
        raise ValueError(f"every window of {w} samples holds a saturated sample (a channel at its "
                         f"register limit: " + ", ".join(f"{s} {k:,}" for s, k in saturated.items())
                         + "): nothing left to fit")
    return replace(data.subset(np.flatnonzero(~bad)), saturated_samples=saturated,
                   saturated_windows=int(bad.sum()),
                   note=data.note + f"; {int(bad.sum()):,} of {n:,} windows left out: they hold "
                   "saturated samples (" + ", ".join(f"{s} {k:,}" for s, k in saturated.items()) + ")")


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
    w = max(1, int(window))
    windows = _Windows(len(t) // w, w)
    if windows.n < 2:
        raise ValueError(f"too few samples ({len(t)}) for windows of {w}")
    means = _stream_means(rec, names, models, t, keep, windows)
    temp = _temperature_c(rec, models, t, windows)
    stance = used = None
    note = ""
    if stances:
        stance, used = parked_stances(arm, rec, windows.mean(t), w)
        if stance is not None:
            note = (f"; {int(stance.max()) + 1} parked stances, each its own base attitude "
                    f"({int((~used).sum())} windows left out while the chair moved)")
    if nodes not in (1, 2):
        raise ValueError(f"nodes must be 1 or 2, not {nodes!r}")
    how = f"window means of {w} samples" + (" (model at two nodes per window)" if nodes == 2 else "")
    data = FitData(_motion(t, q, temp, windows, nodes), means.counts, means.sigma,
                   np.asarray(q_ref_rad, float), w, how + note, nodes=nodes, stance=stance, used=used,
                   sample_excess_counts=means.excess, start_rivals_rad=rivals)
    if means.saturated:  # a window holding a saturated sample (or interpolated from one) is left out
        data = _without_saturated(data, means, windows)
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
    extra = [build_effect(arm, JointOffset.name, j) for j in arm.joint_names
             if f"{j}.joint_offset" not in model.index]
    sig = {f"{j}.joint_offset": np.array([sigma_rad]) for j in arm.joint_names}
    return model.with_effects(extra, sigmas=sig)
