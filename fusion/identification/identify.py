"""Sensor and model identification: the arm calibrates its own sensors.

From a recording in which the arm moves through many orientations, estimate the
parameters of the model's effects (``models.effects``: biases, scales, axis directions,
mounts, joint zeros, sag, the IMU's gyro and compass errors…) and the base attitude (the
gravity and Earth-field directions in the base frame, as the sensor-calibration article's
φ, ψ; one per parked stance of the chair, :func:`parked_stances`, optionally with an
inclinometer's reading of the first stance's tilt), by weighted nonlinear least squares:

* residuals: every reading's prediction minus the measurement, divided by its noise
  (window means of ``window`` samples: the noise of a mean);
* priors as pseudo-measurements ``(x - x0) / σ0`` (each block's prior, from the config or
  the effect's datasheet-typical magnitude);
* analytic Jacobians from :meth:`Model.predict_with_jacobian`; the base attitude's three
  columns by forward differences of the model (the only numerical ones);
* identifiability first: the weighted Jacobian, scaled by the prior σ, says which
  combinations of parameters the data know no better than their priors. Each such
  combination is reported in words and one element of it (the one that carries most of
  it) is **held** at its prior, as Ceres holds a parameter block (here element by
  element, like a subset manifold). The other elements then carry the combination; their
  σ includes the held ones' prior uncertainty (a consider covariance), so it stays honest.

The encoders are relative: the joint angles of the fit are ``q_ref + encoder angle``, and
every joint's ``joint_offset`` block absorbs the unknown zero ``q_true(0) - q_ref``. That is
why joint offsets are a property of the recording, not of the arm, and
:func:`config_with_estimates` leaves them out by default.

For the startup calibration, :class:`StartupCorrection` (``startup_correction(arm)``)
applies a calibrated config's effects to averaged still readings and joint angles.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from models.arm import ArmModel
from models.effects import Model, build_effect, entries_from_model, model_from_arm
from models.effects.base import Context, JointEffect, SensorEffect
from models.motion import MotionState
from models.rotations import DEG, R_from_rpy, wrap_angle
from models.sensor_models import stream_models

FIT_STREAMS_EXCLUDED = ("enc", "imu_temp")
ATTITUDE = "base.attitude"
ATTITUDE_LABELS = ("roll", "pitch", "yaw")
ATTITUDE_SIGMA_RAD = np.array([10 * DEG, 10 * DEG, 180 * DEG])
ENCODER_ZERO_SIGMA_RAD = 10 * DEG
"""Prior σ of a joint's ``joint_offset`` when it carries the recording's unknown encoder zero."""


# --------------------------------------------------------------------------------------
# settings, data, results
@dataclass(frozen=True)
class IdentifySettings:
    hold_ratio: float = 1.0
    """Hold a combination whose data-only σ exceeds this many prior σ (data know it no
    better than the prior)."""
    partner_weight: float = 0.25
    """An element is named as part of a combination when its share exceeds this."""
    report_correlation: float = 0.9
    """Pairs of estimates more correlated than this are listed."""
    max_nfev: int = 100
    """Most Jacobians (Levenberg-Marquardt iterations) per solve."""
    estimate_attitude: bool = True
    encoder_scale: bool = False
    """Let ``encoder_scale`` effects act on the fit's joint angles (they come from the
    encoders: ``q_ref + encoder angle / (1 + s)``). ``calibrate sensors`` turns it on; off,
    an encoder's scale is invisible to the fit (the workbench's candidate tests, on window
    means evaluated at one node, keep it off: there it would absorb the window-mean bias)."""
    """Estimate the base attitude (gravity and Earth-field directions); else take it as zero
    (the base level and facing magnetic north) or as the data's state says."""


REFERENCE_SIGMA_RAD = 0.05 * DEG
"""Default σ of a one-time joint reference (a mechanical index, a pose the installer confirms)."""
REFERENCE_CONTRADICTION_SIGMA = 4.0
"""A reference farther than this many σ from where the rest of the fit (data and priors) puts
the joint contradicts it."""


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
class ReferenceCheck:
    """A reference against the rest of the fit: where the data and the priors alone put the
    joint's geometric angle at the reference (leave-one-out, ``without_rad ± without_sigma_rad``;
    an infinite σ when nothing but the reference knows it) and the reference's distance from
    it in σ of their difference."""

    reference: JointReference
    fitted_rad: float
    fitted_sigma_rad: float
    without_rad: float
    without_sigma_rad: float
    z: float

    @property
    def contradicted(self) -> bool:
        return bool(abs(self.z) > REFERENCE_CONTRADICTION_SIGMA)

    def message(self) -> str:
        r = self.reference
        head = (f"reference {r.joint} = {np.degrees(r.angle_rad):.3f}° ± {np.degrees(r.sigma_rad):.3g}° "
                f"({r.where}, t {r.t_start_s:.1f}-{r.t_end_s:.1f} s)")
        if not np.isfinite(self.without_sigma_rad):
            return (f"{head}: nothing else in the fit knows {r.joint} there, so nothing can check "
                    "the reference; the calibration rests on it")
        rest = (f"the data and the priors alone put {r.joint} at {np.degrees(self.without_rad):.3f}° "
                f"± {np.degrees(self.without_sigma_rad):.3g}° there")
        if self.contradicted:
            return (f"{head} contradicts the calibration: {rest} ({self.z:+.1f} σ of their difference); "
                    f"check that {r.joint} stood at that angle then (the index, the pose confirmed, the "
                    "sign and the time)")
        blind_deg = REFERENCE_CONTRADICTION_SIGMA * np.degrees(np.hypot(self.without_sigma_rad, r.sigma_rad))
        return (f"{head}: {rest} ({self.z:+.1f} σ), consistent; a reference wrong by less than about "
                f"{blind_deg:.2g}° would not be detected")

    def as_dict(self) -> dict[str, Any]:
        fin = np.isfinite(self.without_sigma_rad)
        return {**self.reference.as_dict(),
                "fitted_deg": float(np.degrees(self.fitted_rad)),
                "fitted_sigma_deg": float(np.degrees(self.fitted_sigma_rad)),
                "without_reference_deg": float(np.degrees(self.without_rad)) if fin else None,
                "without_reference_sigma_deg": float(np.degrees(self.without_sigma_rad)) if fin else None,
                "z": float(self.z) if fin else None, "contradicted": self.contradicted,
                "message": self.message()}


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


@dataclass(frozen=True)
class Hold:
    """One element held at its prior, and why."""

    element: str
    partners: tuple[tuple[str, float], ...]
    data_to_prior: float
    message: str
    suggestion: str


@dataclass(frozen=True)
class StreamFit:
    stream: str
    unit: str
    rms: np.ndarray
    noise: np.ndarray

    def excess(self) -> np.ndarray:
        """RMS beyond the noise, per axis (0 where the fit is at the noise)."""
        return np.sqrt(np.maximum(self.rms**2 - self.noise**2, 0.0))


@dataclass(frozen=True)
class Identification:
    """The result of a fit. ``x``/``sigma`` over ``names`` (model elements, then the base
    attitude if estimated); held elements sit at their prior with their prior σ."""

    model: Model
    names: tuple[str, ...]
    x: np.ndarray
    x0: np.ndarray
    sigma: np.ndarray
    prior_sigma: np.ndarray
    covariance: np.ndarray
    held: np.ndarray
    holds: tuple[Hold, ...]
    fits: tuple[StreamFit, ...]
    chi2_red: float
    n_samples: int
    n_residuals: int
    iterations: int
    seconds: float
    attitude_rad: np.ndarray | None
    q_ref_rad: np.ndarray
    mode: str = "simultaneous"
    notes: tuple[str, ...] = ()
    attitudes_rad: np.ndarray | None = None
    """Roll, pitch, yaw of every parked stance ``(K, 3)`` (``attitude_rad`` is the first)."""
    reference_checks: tuple[ReferenceCheck, ...] = ()
    """Each one-time joint reference of the data against the rest of the fit."""

    @property
    def references_contradicted(self) -> list[ReferenceCheck]:
        return [c for c in self.reference_checks if c.contradicted]

    @property
    def model_x(self) -> np.ndarray:
        return self.x[: self.model.size]

    def correlation(self) -> np.ndarray:
        d = np.sqrt(np.clip(np.diag(self.covariance), 1e-300, None))
        return self.covariance / np.outer(d, d)

    def correlated_pairs(self, limit: float = 0.9) -> list[tuple[str, str, float]]:
        C = self.correlation()
        free = ~self.held
        out = []
        idx = np.flatnonzero(free)
        for a in range(len(idx)):
            for b in range(a + 1, len(idx)):
                i, j = idx[a], idx[b]
                if abs(C[i, j]) > limit:
                    out.append((self.names[i], self.names[j], float(C[i, j])))
        return sorted(out, key=lambda p: -abs(p[2]))

    def calibrated_model(self) -> Model:
        """The model with the estimates as values and their σ as the new priors."""
        m = self.model
        sig = {b.name: np.maximum(self.sigma[m.index[b.name]], 1e-12) for b in m.blocks}
        return Model(m.arm, m.effects, m.unpack(self.model_x), sig, m.earth_field_W_ut, m.masses)

    def value(self, element: str) -> tuple[float, float]:
        i = self.names.index(element)
        return float(self.x[i]), float(self.sigma[i])

    def unmodelled_g(self) -> dict[str, float]:
        """Per accelerometer: what the fit leaves beyond the noise (the worst axis), in g."""
        out = {}
        for f in self.fits:
            if f.unit == "g":
                name = self.model.arm.imu.name if f.stream == "imu_acc" else f.stream
                out[name] = float(np.max(f.excess()))
        return out

    def as_dict(self) -> dict[str, Any]:
        params = []
        for i, n in enumerate(self.names):
            params.append({"name": n, "value": float(self.x[i]), "sigma": float(self.sigma[i]),
                           "prior": float(self.x0[i]), "prior_sigma": float(self.prior_sigma[i]),
                           "held": bool(self.held[i])})
        return {
            "mode": self.mode, "parameters": params,
            "holds": [{"element": h.element, "partners": [p for p, _ in h.partners],
                       "message": h.message, "suggestion": h.suggestion} for h in self.holds],
            "correlated_pairs": [{"a": a, "b": b, "rho": r} for a, b, r in self.correlated_pairs()],
            "fit": [{"stream": f.stream, "unit": f.unit, "rms": f.rms.tolist(), "noise": f.noise.tolist()}
                    for f in self.fits],
            "chi2_red": self.chi2_red, "n_samples": self.n_samples, "n_residuals": self.n_residuals,
            "iterations": self.iterations, "seconds": round(self.seconds, 3),
            "attitude_deg": None if self.attitude_rad is None else np.degrees(self.attitude_rad).tolist(),
            "stance_attitudes_deg": None if self.attitudes_rad is None
            else np.degrees(self.attitudes_rad).tolist(),
            "q_ref_rad": self.q_ref_rad.tolist(), "notes": list(self.notes),
            "references": [c.as_dict() for c in self.reference_checks],
            "unmodelled_g": self.unmodelled_g(),
        }

    def summary(self) -> str:
        nf = int((~self.held).sum())
        return (f"{self.mode} fit: {nf} parameters estimated, {int(self.held.sum())} held at their "
                f"priors; {self.n_samples:,} samples, reduced chi-square {self.chi2_red:.2f}, "
                f"{self.iterations} Jacobians, {self.seconds:.1f} s")


# --------------------------------------------------------------------------------------
# data
def fit_streams(arm: ArmModel) -> list[str]:
    """The streams a fit (calibrate sensors, diagnose) needs of a recording: the encoders and
    every stream of the config's sensors that it fits."""
    return ["enc", *(s for s in stream_models(arm) if s not in FIT_STREAMS_EXCLUDED)]


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

    Joint angles are ``q_ref + encoder angle`` (default ``q_ref``: :func:`start_pose`).
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
    if q_ref_rad is None:
        q_ref_rad = start_pose(arm, rec)
    q = np.asarray(q_ref_rad, float) + q_enc
    names = [s for s in models if s not in FIT_STREAMS_EXCLUDED] if streams is None else list(streams)
    counts, sig = {}, {}
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
        state = MotionState.from_samples(mean(t), mean(q), None, 0.0, temp)
        data = FitData(state, counts, sig, np.asarray(q_ref_rad, float), w,
                       f"window means of {w} samples" + note, stance=stance, used=used)
    else:
        tw = t[: n * w].reshape(n, w)
        dt = (tw[:, -1] - tw[:, 0]) * w / max(w - 1, 1)  # the window's length
        tn = (tw.mean(1)[:, None] + dt[:, None] / (2 * np.sqrt(3)) * np.array([-1.0, 1.0])).ravel()
        qn = np.stack([np.interp(tn, t, q[:, j]) for j in range(q.shape[1])], 1)
        tempn = np.repeat(np.broadcast_to(temp, (n,)), 2)
        state = MotionState.from_samples(tn, qn, None, 0.0, tempn)
        data = FitData(state, counts, sig, np.asarray(q_ref_rad, float), w,
                       f"window means of {w} samples (model at two nodes per window)" + note, nodes=2,
                       stance=stance, used=used)
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
    from fusion.startup.solve import readings_from_recording, solve_still

    q = np.array(arm.ready_pose_rad, float)
    try:
        t0 = rec.t_start_s
        readings, _ = readings_from_recording(arm, rec, t0, t0 + window_s, window_s)
        res = solve_still(arm, readings, propose_unlock=False)
    except Exception:  # noqa: BLE001 - no still start: the ready pose
        return q
    enc = rec.get("enc")
    models = stream_models(arm)
    e = models["enc"].from_counts(enc.values[:1])[0] if enc is not None and len(enc) else 0.0
    geo = np.array([je.angle_rad if je.angle_rad is not None else np.nan for je in res.joints])
    if res.candidates_rad is not None and len(res.candidates_rad) > 1:
        # rival branches the still start cannot tell apart: this is only where the fit
        # starts, and a calibration maneuver starts from the arm's ready pose: the candidate
        # nearest it (the fit's residuals then say whether it was the right one)
        amb = np.array([je.flag == "ambiguous" for je in res.joints])
        d = np.abs(wrap_angle(res.candidates_rad - q))[:, amb].sum(1)
        geo[amb] = res.candidates_rad[int(np.argmin(d))][amb]
    for j in np.flatnonzero(np.isfinite(geo)):
        q[j] = geo[j] - (e[j] if np.ndim(e) else 0.0)
    return q


def joint_references(arm: ArmModel, rec, specs: Sequence[tuple[str, float, float, float | int | None]]
                     ) -> tuple[JointReference, ...]:
    """One-time references from ``specs``: ``(joint, angle_rad, sigma_rad, when)``, ``when``
    ``None`` (the recording's first still segment), an ``int`` k (its k-th still segment,
    from 1) or a ``float`` time (s, on the recording's clock; the still segment that holds
    it). The arm must be still there (``fusion.startup.static.find_static_segments``); the encoder
    angles are their mean over that segment."""
    from fusion.startup.static import find_static_segments

    if not specs:
        return ()
    enc = rec.get("enc")
    if enc is None or len(enc) == 0:
        raise ValueError("a joint reference needs the recording's encoder samples ('enc')")
    segs = find_static_segments(rec)
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


# --------------------------------------------------------------------------------------
# identifiability
_SUGGEST = {
    "joint_offset": "move the joints between {j} and the sensor so that {j}'s axis turns in the "
                    "sensor's frame, or tilt {j}'s axis away from vertical",
    "mount_rotation": "turn the sensor about each of its axes (move the joints just before it)",
    "accel_axes": "turn the sensor so that every axis points up and down in turn",
    "accel_bias": "turn the sensor so that each axis sees gravity both up (+1 g) and down (-1 g)",
    "accel_scale": "turn the sensor so that each axis sees gravity both up (+1 g) and down (-1 g)",
    "temperature_drift": "record while the electronics warm up (a temperature change of 10 °C or more)",
    "base_mount": "park the chair on a ramp facing up, down and across (renk-ramp) so the base "
                  "attitude and the IMU's mount separate; its angle about the first joint's axis no "
                  "tilt can separate from that joint's zero: read the base's tilt with an "
                  "inclinometer in the first stance (calibrate sensors --base-tilt)",
    "gyro_bias": "hold the chair still for a while (the gyro bias is its reading at rest)",
    "gyro_scale": "turn the chair on the spot (a full turn both ways at 30 °/s or more)",
    "mag_hard_iron": "turn the chair on the spot through a full circle (the compass readings "
                     "trace a circle around the hard iron)",
    "mag_soft_iron": "turn the chair through a full circle and tilt it (the readings trace an "
                     "ellipsoid)",
    "mag_arm_disturbance": "move {j} through its range while the chair is still",
    "link_compliance": "move {j} so that its gravity torque changes sign and size",
    "backlash": "move {j} so that its gravity torque changes sign",
    "encoder_scale": "move {j} through most of its range",
    "motion_acceleration": "swing the joints before the sensor fast (centripetal and tangential "
                           "acceleration)",
    "time_offset": "move faster: a time offset is seen only through the rate of change",
    "attitude": "the base attitude: tilt the chair, or turn it on the spot for the heading",
}


def attitude_names(n_stances: int) -> tuple[str, ...]:
    """The base attitude's element names: ``base.attitude[roll]``… for one stance,
    ``base.attitude[2.roll]``… (stance 2 of K, from 1) for several."""
    if n_stances == 1:
        return tuple(f"{ATTITUDE}[{k}]" for k in ATTITUDE_LABELS)
    return tuple(f"{ATTITUDE}[{i + 1}.{k}]" for i in range(n_stances) for k in ATTITUDE_LABELS)


def _element_effect(name: str) -> tuple[str, str]:
    """``'acc3.mount_rotation[z]'`` -> (effect, target)."""
    block = name.split("[")[0]
    target, _, effect = block.partition(".")
    return ("attitude" if block == ATTITUDE else effect), target


def suggestion_for(element: str, partners: Sequence[str] = ()) -> str:
    effect, target = _element_effect(element)
    text = _SUGGEST.get(effect, "a motion that changes these parameters' effects differently")
    j = target
    if "{j}" in text and not target.startswith("j"):
        js = [_element_effect(p)[1] for p in partners if _element_effect(p)[1].startswith("j")]
        j = js[0] if js else "the joint"
    zeros = [_element_effect(p)[1] for p in partners if _element_effect(p)[0] == "joint_offset"]
    if effect == "joint_offset" and any(_element_effect(p)[0] == "mount_rotation" for p in partners):
        zeros = [target]
        effect = "mount_rotation"
    if effect == "mount_rotation" and zeros:
        # a gauge: the sensor turned about the joint's axis and the joint's zero turned back
        # read the same in every motion; only an outside reference of the angle separates them
        return (f"no motion separates it from {zeros[0]}'s zero: give {zeros[0]}'s angle once, at a "
                f"mechanical index or a pose the installer confirms (calibrate sensors --reference "
                f"{zeros[0]}=DEG)")
    if effect == "base_mount" and zeros:
        text += f", or give {zeros[0]}'s angle once (calibrate sensors --reference {zeros[0]}=DEG)"
    return text.format(j=j)


def analyse_identifiability(Jw: np.ndarray, sigma0: np.ndarray, names: Sequence[str],
                            free: np.ndarray, settings: IdentifySettings | None = None) -> list[Hold]:
    """Which free elements the data cannot tell from their priors or from each other.

    ``Jw`` is the noise-weighted Jacobian (rows: readings; columns: ``names``), ``sigma0``
    the prior σ. In prior-σ units the data's information is ``H = (Jw σ0)ᵀ(Jw σ0)``. A
    pivoted Cholesky factorisation takes the best-known element first, then the one best
    known given those taken, and so on (a rank-revealing order); an element whose
    information given the others is below ``1/hold_ratio²`` (data σ above ``hold_ratio``
    prior σ) is held, and its partners are the taken elements it is a combination of
    (regression of its column on theirs).
    """
    return analyse_information(Jw.T @ Jw, sigma0, names, free, settings)


def analyse_information(H_data: np.ndarray, sigma0: np.ndarray, names: Sequence[str],
                        free: np.ndarray, settings: IdentifySettings | None = None) -> list[Hold]:
    """:func:`analyse_identifiability` from the data's information ``JwᵀJw`` (as the
    estimator accumulates it chunk by chunk)."""
    st = settings or IdentifySettings()
    free = np.array(free, bool)
    H = H_data * np.outer(sigma0, sigma0)
    idx = np.flatnonzero(free)
    # pivoted Cholesky: take the most informative element first; an element whose
    # information, given every element already taken, is below 1/hold_ratio² is held
    taken: list[int] = []
    left = list(idx)
    d = {j: H[j, j] for j in left}
    L = np.zeros((len(H), 0))
    limit = 1.0 / st.hold_ratio**2
    while left:
        j = max(left, key=lambda c: d[c])
        if d[j] < limit:
            break
        col = (H[:, j] - L @ L[j]) / np.sqrt(d[j])
        L = np.hstack([L, col[:, None]])
        taken.append(j)
        left.remove(j)
        for c in left:
            d[c] = H[c, c] - float(L[c] @ L[c])
    holds: list[Hold] = []
    Ht = H[np.ix_(taken, taken)] if taken else np.zeros((0, 0))
    for j in sorted(left, key=lambda c: -H[c, c]):
        ratio = 1.0 / np.sqrt(max(d[j], 1e-300))
        partners: tuple[tuple[str, float], ...] = ()
        if taken and H[j, j] >= limit:
            beta = np.linalg.lstsq(Ht, H[taken, j], rcond=None)[0]
            big = np.max(np.abs(beta)) if len(beta) else 0.0
            order = np.argsort(-np.abs(beta))
            partners = tuple((names[taken[m]], float(beta[m])) for m in order
                             if big > 0 and abs(beta[m]) >= st.partner_weight * big)[:6]
        if partners:
            msg = (f"{names[j]} cannot be separated from {', '.join(p for p, _ in partners[:4])}"
                   f"{' …' if len(partners) > 4 else ''}: the data see only their combination "
                   f"(alone it would be known to {min(ratio, 1e6):.3g} prior σ); held at its prior")
        else:
            msg = (f"{names[j]} is not seen by the data (its effect on the readings is below the "
                   f"noise: known to {min(ratio, 1e6):.3g} prior σ); held at its prior")
        holds.append(Hold(names[j], partners, float(ratio), msg,
                          suggestion_for(names[j], [p for p, _ in partners])))
    return holds


# --------------------------------------------------------------------------------------
# the estimator
class _Problem:
    def __init__(self, model: Model, data: FitData, streams: Sequence[str], attitude: bool,
                 attitude0: np.ndarray, encoder_scale: bool = False):
        self.model = model
        self.data = data
        self.streams = [s for s in streams if s in data.counts]
        if not self.streams:
            raise ValueError("no measured stream to fit (streams: " + ", ".join(streams) + ")")
        self.attitude = attitude
        self.P = model.size
        # one attitude per parked stance (the chair tilted differently in each)
        self.K = data.n_stances
        K = self.K if attitude else 0
        self.size = model.size + 3 * K
        self.names = tuple(model.element_names()) + attitude_names(K)
        att0 = np.broadcast_to(np.asarray(attitude0, float).reshape(-1, 3)
                               if np.size(attitude0) else np.zeros((1, 3)), (max(K, 1), 3))
        self.x0 = np.concatenate([model.x0, att0[:K].ravel()])
        self.sigma0 = np.concatenate([model.prior_sigma, np.tile(ATTITUDE_SIGMA_RAD, K)])
        self.lower = np.concatenate([model.lower, np.tile([-np.pi / 2, -np.pi / 2, -4 * np.pi], K)])
        self.upper = np.concatenate([model.upper, np.tile([np.pi / 2, np.pi / 2, 4 * np.pi], K)])
        ref = data.base_tilt_reference
        if K and ref is not None:  # an independent measurement of the first stance's tilt
            tilt, sig = np.asarray(ref[0], float).reshape(2), float(ref[1])
            if not sig > 0 or not np.all(np.abs(tilt) < np.pi / 2):
                raise ValueError(f"base tilt reference: roll and pitch within ±90° and a positive σ, "
                                 f"got {np.degrees(tilt)} deg ± {np.degrees(sig)} deg")
            self.x0[self.P:self.P + 2] = tilt
            self.sigma0[self.P:self.P + 2] = sig
        self.meas = np.concatenate([data.counts[s].ravel() for s in self.streams])
        self.w = self._rows(None, None)[1]
        self.base_rpy = np.zeros(3)
        self._R0 = data.state.R_WB
        # encoder scale errors: the fit's joint angles come from the encoders, so a joint whose
        # encoder counts too fast stands at q_ref + (encoder angle)/(1 + s); its column is the
        # joint's sensitivity (its joint_offset column, where the model has one) times
        # -(encoder angle)/(1 + s)²
        self.enc_scale: list[tuple[int, int, str | None]] = []
        for e in model.effects:
            if encoder_scale and e.name == "encoder_scale":
                off = f"{e.target}.joint_offset"
                self.enc_scale.append((model.index[e.block_name].start, e.j,
                                       off if off in model.index else None))
        self._init_references(encoder_scale)

    # one-time joint references: pseudo-measurements of a joint's geometric angle
    def _init_references(self, encoder_scale: bool) -> None:
        m, d = self.model, self.data
        arm = m.arm
        self.refs = tuple(d.joint_references)
        self.ref_cols = np.zeros(0, int)
        if not self.refs:
            return
        if not arm.link_accelerometers:
            raise ValueError("a joint reference needs the arm's link accelerometers")
        for r in self.refs:
            if r.joint not in arm.joint_names:
                raise ValueError(f"joint reference: no joint {r.joint[:20]!r} on this arm")
        self._ref_j = np.array([arm.joint_names.index(r.joint) for r in self.refs])
        self._ref_angle = np.array([r.angle_rad for r in self.refs], float)
        self._ref_sigma = np.array([r.sigma_rad for r in self.refs], float)
        self._ref_enc = np.array([np.asarray(r.encoder_rad, float) for r in self.refs])
        # the stance each reference stands in (its nearest point's), for the base attitude
        # its sag and play see
        t_pts = d.state.t_s.reshape(d.n, d.nodes).mean(1)
        near = np.array([int(np.argmin(np.abs(t_pts - 0.5 * (r.t_start_s + r.t_end_s)))) for r in self.refs])
        self._ref_point = near
        self._ref_stance = np.zeros(len(near), int) if d.stance is None else d.stance[near]
        # what moves a joint's geometric angle at a still instant: the joint stage (offsets,
        # sag, play), the encoder scales, the base attitude (sag follows the tilt)
        cols: list[int] = []
        for e in m.effects:
            if isinstance(e, JointEffect) or (encoder_scale and e.name == "encoder_scale"):
                sl = m.index[e.block_name]
                cols += range(sl.start, sl.stop)
        cols += range(m.size, self.size)
        self.ref_cols = np.array(sorted(cols), int)
        self._ref_stream = arm.link_accelerometers[0].name

    def reference_angles(self, z: np.ndarray) -> np.ndarray:
        """Each reference's joint's geometric angle at the reference, as the fit at ``z`` has it."""
        q = self.data.q_ref_rad + self._ref_enc
        st = self._scaled_joints(MotionState.static(q), z)
        if self.attitude:
            a = z[self.P:].reshape(-1, 3)[self._ref_stance]
            st = st.replace(R_WB=R_from_rpy(a[:, 0], a[:, 1], a[:, 2]))
        else:
            st = st.replace(R_WB=np.asarray(self._R0)[self._ref_point * self.data.nodes])
        ctx = self.model.context(st, z[: self.P], (self._ref_stream,))
        return np.asarray(ctx.q_geom, float)[np.arange(len(self.refs)), self._ref_j]

    def reference_residual(self, z: np.ndarray) -> np.ndarray:
        if not self.refs:
            return np.zeros(0)
        dq = wrap_angle(self.reference_angles(z) - self._ref_angle)
        return dq / self._ref_sigma

    def reference_rows(self, z: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The references' weighted residuals and their Jacobian over columns ``cols`` (forward
        differences: one still instant per reference, only the columns that can move it)."""
        r = self.reference_residual(z)
        J = np.zeros((len(r), len(cols)))
        if not len(r):
            return r, J
        moving = set(self.ref_cols.tolist())
        for i, c in enumerate(cols):
            if int(c) in moving:
                h = 1e-3 * self.sigma0[c]
                zz = np.array(z, float)
                zz[c] += h
                J[:, i] = (self.reference_residual(zz) - r) / h
        return r, J

    def _scaled_joints(self, st: MotionState, z: np.ndarray) -> MotionState:
        if not self.enc_scale:
            return st
        f = np.ones(self.model.arm.n_joints)
        for c, j, _ in self.enc_scale:
            f[j] = 1.0 / (1.0 + z[c])
        if np.all(f == 1.0):
            return st
        q_ref = self.data.q_ref_rad
        return st.replace(q_rad=q_ref + (st.q_rad - q_ref) * f, qd_rad_s=st.qd_rad_s * f,
                          qdd_rad_s2=st.qdd_rad_s2 * f)

    def state(self, z: np.ndarray, rows: slice | None = None) -> MotionState:
        return self._state_of(self.data if rows is None else self.data.subset(rows), z)

    def _state_of(self, d: FitData, z: np.ndarray) -> MotionState:
        st = self._scaled_joints(d.state, z)
        if not self.attitude:
            return st
        a = z[self.P:].reshape(-1, 3)
        R = R_from_rpy(a[:, 0], a[:, 1], a[:, 2])
        if len(a) == 1:
            return st.replace(R_WB=np.broadcast_to(R[0], st.R_WB.shape).copy())
        return st.replace(R_WB=R[d.stance_of_instants()])

    def _mean_nodes(self, a: np.ndarray) -> np.ndarray:
        k = self.data.nodes
        return a if k == 1 else a.reshape(a.shape[0] // k, k, *a.shape[1:]).mean(1)

    def predict(self, z: np.ndarray) -> np.ndarray:
        p = self.model.predict(self.state(z), z[: self.P], self.streams)
        return np.concatenate([self._mean_nodes(p[s]).ravel() for s in self.streams])

    def residual(self, z: np.ndarray) -> np.ndarray:
        return (self.predict(z) - self.meas) * self.w

    def jacobian(self, z: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted residual and Jacobian columns ``cols`` (indices into z)."""
        return self._jacobian_rows(z, cols, None, None, self.w)

    def _rows(self, rows: slice | None, keep: slice | None, w_stream: dict[str, float] | None = None):
        """Measurements and weights of the points ``rows`` (then ``keep`` of them), stream-major."""
        d = self.data
        meas, w = [], []
        used = None
        if d.used is not None:
            used = d.used if rows is None else d.used[rows]
            if keep is not None:
                used = used[keep]
        for s in self.streams:
            c = d.counts[s] if rows is None else d.counts[s][rows]
            if keep is not None:
                c = c[keep]
            ws = np.broadcast_to(1.0 / d.sigma_counts[s], c.shape) * (1.0 if w_stream is None
                                                                      else w_stream[s])
            if used is not None:  # points while the chair moves weigh nothing
                ws = ws * used[:, None]
            meas.append(c.ravel())
            w.append(ws.ravel())
        return np.concatenate(meas), np.concatenate(w)

    def _jacobian_rows(self, z, cols, rows, keep, w, meas=None):
        m = self.model
        mcols = cols[cols < self.P]
        want = set(b.name for b in m.blocks
                   if np.any((mcols >= m.index[b.name].start) & (mcols < m.index[b.name].stop)))
        enc_cols = {c: (j, off) for c, j, off in self.enc_scale if c in set(mcols.tolist())}
        want |= {off for _, off in enc_cols.values() if off is not None}
        blocks = [b.name for b in m.blocks if b.name in want]
        st = self.state(z, rows)
        pred, jac = m.predict_with_jacobian(st, z[: self.P], self.streams, blocks=blocks)
        if self.data.nodes > 1:
            pred = {s: self._mean_nodes(pred[s]) for s in self.streams}
            jac = {s: {b: self._mean_nodes(v) for b, v in jac.get(s, {}).items()} for s in self.streams}
        if keep is not None:
            pred = {s: pred[s][keep] for s in self.streams}
            jac = {s: {b: v[keep] for b, v in jac.get(s, {}).items()} for s in self.streams}
        else:
            pred = {s: pred[s] for s in self.streams}
        D = m.dense_jacobian(jac, pred, blocks)
        bcols = np.concatenate([np.arange(m.index[b].start, m.index[b].stop) for b in blocks]) \
            if blocks else np.zeros(0, int)
        pos = {c: i for i, c in enumerate(bcols)}
        y = np.concatenate([pred[s].ravel() for s in self.streams])
        if meas is None:
            meas = self.meas
        r = (y - meas) * w
        J = np.zeros((len(r), len(cols)))
        enc = None
        for i, c in enumerate(cols):
            if c in enc_cols:
                j, off = enc_cols[c]
                if enc is None:  # each point's encoder angle, repeated over the stream's axes
                    q_pts = self._mean_nodes(st.q_rad)
                    q = q_pts if keep is None else q_pts[keep]
                    enc = (q - self.data.q_ref_rad)
                    enc = np.concatenate([np.repeat(enc, pred[s].shape[1], axis=0).reshape(
                        len(q), pred[s].shape[1], -1).reshape(-1, enc.shape[1]) for s in self.streams])
                if off is not None:
                    J[:, i] = D[:, pos[m.index[off].start]] * w * (-enc[:, j] / (1.0 + z[c]))
                else:
                    J[:, i] = self._numeric_column(z, c, y, w, rows, keep)
            elif c < self.P:
                J[:, i] = D[:, pos[c]] * w
            elif self.K == 1:  # base attitude: forward differences of the model
                J[:, i] = self._numeric_column(z, c, y, w, rows, keep)
            else:  # one stance's attitude: forward differences on that stance's points only
                J[:, i] = self._stance_column(z, c, y, w, rows, keep, {s: pred[s].shape[1]
                                                                      for s in self.streams})
        return r, J

    def _stance_column(self, z, c, y, w, rows, keep, dims, h=1e-6):
        """An attitude column of stance k: only its points change. The model is evaluated on
        them with two points either side (so a time derivative there uses the same
        neighbours as the whole chunk's) and the column is zero elsewhere."""
        d = self.data if rows is None else self.data.subset(rows)
        pts = np.arange(d.n) if keep is None else np.arange(d.n)[keep]
        k = (c - self.P) // 3
        sel = np.flatnonzero(d.stance[pts] == k)  # positions among the kept points
        col = np.zeros(len(y))
        if not len(sel):
            return col
        a, b = max(0, pts[sel[0]] - 2), min(d.n, pts[sel[-1]] + 3)
        zz = np.array(z, float)
        zz[c] += h
        sub = d.subset(slice(a, b))
        p = self.model.predict(self._state_of(sub, zz), zz[: self.P], self.streams)
        at = pts[sel] - a
        off = 0
        for s in self.streams:
            m = dims[s]
            ps = self._mean_nodes(p[s])[at]
            idx = off + (sel[:, None] * m + np.arange(m)).ravel()
            col[idx] = (ps.ravel() - y[idx]) * w[idx] / h
            off += len(pts) * m
        return col

    def _numeric_column(self, z, c, y, w, rows, keep, h=1e-6):
        zz = np.array(z, float)
        zz[c] += h
        p = self.model.predict(self.state(zz, rows), zz[: self.P], self.streams)
        p = {s: self._mean_nodes(p[s]) for s in self.streams}
        if keep is not None:
            p = {s: p[s][keep] for s in self.streams}
        return (np.concatenate([p[s].ravel() for s in self.streams]) - y) * w / h

    def normal_equations(self, z: np.ndarray, cols: np.ndarray, w_stream: dict[str, float] | None = None,
                         chunk: int = 1500) -> tuple[np.ndarray, np.ndarray, float]:
        """``JᵀJ``, ``Jᵀr`` and ``rᵀr`` over columns ``cols``, accumulated ``chunk`` points at a
        time (memory stays bounded whatever the recording's length). Chunks overlap by two
        points on each side so the time derivatives of the time offsets are those of the
        whole series; ``w_stream`` scales each stream's weights."""
        n = self.data.n
        H = np.zeros((len(cols), len(cols)))
        g = np.zeros(len(cols))
        rr = 0.0
        pad = 2
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            lo, hi = max(0, a - pad), min(n, b + pad)
            keep = slice(a - lo, a - lo + (b - a))
            meas, w = self._rows(slice(lo, hi), keep, w_stream)
            r, J = self._jacobian_rows(z, cols, slice(lo, hi), keep, w, meas)
            H += J.T @ J
            g += J.T @ r
            rr += float(r @ r)
        if self.refs:
            r, J = self.reference_rows(z, np.asarray(cols))
            H += J.T @ J
            g += J.T @ r
            rr += float(r @ r)
        return H, g, rr


def _solve(pb: _Problem, z0: np.ndarray, fcols: np.ndarray, w_stream: dict[str, float], max_jac: int,
           progress: Callable[[int, float], None]) -> tuple[np.ndarray, bool]:
    """Levenberg-Marquardt on the normal equations (accumulated chunk by chunk), the priors
    as pseudo-measurements, bounds by projection: an element at a bound whose gradient
    pushes it out stays there for that step. Returns the estimate and whether it converged
    (the cost lowered by less than 0.05, a tenth of a unit of χ², or every step below 1e-3
    of its prior σ)."""
    mu, sd = pb.x0[fcols], pb.sigma0[fcols]
    lo, hi = pb.lower[fcols], pb.upper[fcols]
    meas, w = pb._rows(None, None, w_stream)

    def cost(z):
        r = (pb.predict(z) - meas) * w
        p = (z[fcols] - mu) / sd
        a = pb.reference_residual(z)
        return 0.5 * float(r @ r + p @ p + a @ a)

    z = np.array(z0, float)
    z[fcols] = np.clip(z[fcols], lo, hi)
    lam = 1e-3
    c = None
    for k in range(max(1, max_jac)):
        H, g, rr = pb.normal_equations(z, fcols, w_stream)
        x = z[fcols]
        H = H + np.diag(1.0 / sd**2)
        g = g + (x - mu) / sd**2
        c = 0.5 * (rr + float(np.sum(((x - mu) / sd) ** 2)))
        progress(k + 1, c)
        d = np.sqrt(np.clip(np.diag(H), 1e-300, None))
        while True:
            stuck = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
            move = ~stuck
            dx = np.zeros_like(x)
            Hm = H[np.ix_(move, move)] / np.outer(d[move], d[move])
            Hm[np.diag_indices_from(Hm)] += lam
            try:
                dx[move] = -np.linalg.solve(Hm, g[move] / d[move]) / d[move]
            except np.linalg.LinAlgError:
                dx[move] = -np.linalg.lstsq(Hm, g[move] / d[move], rcond=None)[0] / d[move]
            zn = z.copy()
            zn[fcols] = np.clip(x + dx, lo, hi)
            cn = cost(zn)
            if cn <= c:
                lam = max(lam / 5.0, 1e-9)
                step = np.max(np.abs(zn[fcols] - x) / sd)
                z = zn
                if c - cn <= max(1e-7 * c, 0.05) or step < 1e-3:
                    return z, True
                break
            lam *= 5.0
            if lam > 1e10:
                return z, True  # no step lowers the cost: at the minimum (to rounding)
    return z, False


def _stream_scales(pb: _Problem, z: np.ndarray) -> dict[str, float]:
    """Per stream: how many times its (weighted) residual exceeds what white noise at the
    weights would give, counting its lag-1 autocorrelation ρ (smooth, unmodelled errors) as
    fewer independent readings, ``√(χ²/n · (1 + ρ)/(1 - ρ))``; at least 1."""
    pred = pb.predict(z)
    out = {}
    i = 0
    used = pb.data.used
    for s in pb.streams:
        c = pb.data.counts[s]
        k = c.size
        r = ((pred[i:i + k] - c.ravel()).reshape(c.shape) / pb.data.sigma_counts[s])
        i += k
        if used is not None:
            r = r[used]
        chi2 = float(np.mean(r**2))
        rc = r - r.mean(0)
        den = np.sum(rc**2, 0)
        rho = float(np.mean(np.sum(rc[1:] * rc[:-1], 0) / np.where(den > 0, den, 1.0))) if len(r) > 2 else 0.0
        rho = min(max(rho, 0.0), 0.95)
        out[s] = float(np.sqrt(max(chi2, 1.0) * (1.0 + rho) / (1.0 - rho))) if chi2 > 1.0 else \
            float(np.sqrt((1.0 + rho) / (1.0 - rho)))
    return out


def identify(model: Model, data: FitData, streams: Sequence[str] | None = None,
             settings: IdentifySettings | None = None, hold: Iterable[str] = (),
             attitude0_rad: np.ndarray | None = None,
             progress: Callable[[int, float], None] | None = None,
             mode: str = "simultaneous") -> Identification:
    """Estimate every parameter of ``model`` (and the base attitude) from ``data``.

    ``hold`` names elements or whole blocks to keep at their priors (besides those the
    identifiability analysis holds). ``progress(k, cost)`` is called at every Jacobian.
    """
    st = settings or IdentifySettings()
    t0 = time.perf_counter()
    streams = [s for s in (data.counts if streams is None else streams) if s not in FIT_STREAMS_EXCLUDED]
    att0 = np.zeros(3) if attitude0_rad is None else np.asarray(attitude0_rad, float)
    pb = _Problem(model, data, streams, st.estimate_attitude, att0, encoder_scale=st.encoder_scale)
    names = pb.names
    free = np.ones(pb.size, bool)
    hold = set(hold)
    for i, n in enumerate(names):
        if n in hold or n.split("[")[0] in hold:
            free[i] = False
    notes = []
    if pb.attitude and "imu_mag" in pb.streams:
        # the heading of each stance: a coarse search (the compass decides), then the fit
        point_stance = np.zeros(data.n, int) if data.stance is None else data.stance
        rows_stance = np.concatenate([np.repeat(point_stance, data.counts[s].shape[1])
                                      for s in pb.streams])
        yaws = np.linspace(-np.pi, np.pi, 12, endpoint=False)
        cost = np.zeros((len(yaws), pb.K))
        for i, yaw in enumerate(yaws):
            z = pb.x0.copy()
            z[pb.P + 2::3] = yaw
            cost[i] = np.bincount(rows_stance, pb.residual(z) ** 2, minlength=pb.K)
        pb.x0[pb.P + 2::3] = yaws[np.argmin(cost, 0)]
    z0 = pb.x0.copy()
    # identifiability at the prior
    all_cols = np.arange(pb.size)
    H0, _, _ = pb.normal_equations(z0, all_cols)
    holds = analyse_information(H0, pb.sigma0, names, free, st)
    for h in holds:
        free[names.index(h.element)] = False
    fcols = np.flatnonzero(free)
    n_jac = [0]

    def counted(k, cost):
        n_jac[0] += 1
        if progress is not None:
            progress(n_jac[0], cost)

    z = z0.copy()
    w_stream = {s_: 1.0 for s_ in pb.streams}
    scale: dict[str, float] = {}
    if len(fcols):
        z, converged = _solve(pb, z0, fcols, w_stream, st.max_nfev, counted)
        # bilinear effects (a compass dipole's field and the IMU's position, a soft-iron matrix
        # on that field) are invisible at the prior, where the other factor is zero: analyse
        # again at the estimate and free what the data now see
        H1, _, _ = pb.normal_equations(z, all_cols)
        free1 = np.ones(pb.size, bool)
        for i, n in enumerate(names):
            if n in hold or n.split("[")[0] in hold:
                free1[i] = False
        # a bilinear element is freed only when the data know it well (to half its prior σ):
        # one barely above the line makes a long flat valley the solver creeps along
        holds1 = analyse_information(H1, pb.sigma0, names, free1, replace(st, hold_ratio=0.5 * st.hold_ratio))
        before = {h.element for h in holds}
        holds1 = [h for h in holds1 if h.element in before]
        if {h.element for h in holds1} != before:
            free = free1
            for h in holds1:
                free[names.index(h.element)] = False
            holds = holds1
            fcols = np.flatnonzero(free)
            z[~free] = z0[~free]
            z, converged = _solve(pb, z, fcols, w_stream, st.max_nfev, counted)
        # each stream at its own scale: a stream the model fits worse than its noise (or with
        # smooth, correlated residuals) counts for fewer independent readings; weight it so
        # and fit again (one pass), so its errors neither pull the others' estimates nor
        # shrink their σ
        scale = _stream_scales(pb, z)
        if any(v > 1.05 for v in scale.values()):
            w_stream = {s_: 1.0 / scale[s_] for s_ in pb.streams}
            z, converged = _solve(pb, z, fcols, w_stream, st.max_nfev, counted)
            scale = _stream_scales(pb, z)
        w_stream = {s_: 1.0 / scale[s_] for s_ in pb.streams}
        if not converged:
            notes.append(f"the solver stopped before converging (after {n_jac[0]} Jacobians)")
    # covariance: free elements from data + priors, held ones as consider parameters
    H, grad, rr = pb.normal_equations(z, all_cols, w_stream)
    r = pb.residual(z)
    hcols = np.flatnonzero(~free)
    # in prior units the priors make A the identity plus the data's information: a plain
    # inverse there. (A pseudo-inverse of A itself cuts every direction whose information is
    # below 1e-15 of the largest, i.e. exactly the ones the data barely see, and reports
    # them known perfectly: a heading and the hard iron it trades with came out 10x too sure.)
    D = pb.sigma0[fcols]
    A = H[np.ix_(fcols, fcols)] * np.outer(D, D) + np.eye(len(fcols))
    Sff = np.linalg.inv(A) * np.outer(D, D)
    m_res = int(np.count_nonzero(pb.w))
    dof = max(m_res - len(fcols), 1)
    chi2 = float(np.sum(r**2) / dof)
    worse = {s_: v for s_, v in scale.items() if v > 1.05}
    if worse:
        notes.append("σ scaled per stream by its residual's size and correlation (some effect is not "
                     "modelled, or the noise is larger than the datasheet's): "
                     + ", ".join(f"{s_} {v:.2f}x" for s_, v in worse.items()))
    S = -Sff @ H[np.ix_(fcols, hcols)]
    Shh = np.diag(pb.sigma0[hcols] ** 2)
    C = np.zeros((pb.size, pb.size))
    C[np.ix_(fcols, fcols)] = Sff + S @ Shh @ S.T
    C[np.ix_(fcols, hcols)] = S @ Shh
    C[np.ix_(hcols, fcols)] = (S @ Shh).T
    C[np.ix_(hcols, hcols)] = Shh
    C = 0.5 * (C + C.T)
    sigma = np.sqrt(np.clip(np.diag(C), 0, None))
    checks = _reference_checks(pb, z, H, grad, C)
    notes += [c.message() for c in checks]
    # fit quality per stream, in physical units
    sm = model.stream_models()
    fits = []
    pred = pb.predict(z)
    i = 0
    for s in pb.streams:
        k = data.counts[s].shape
        d = (pred[i:i + data.counts[s].size] - pb.meas[i:i + data.counts[s].size]).reshape(k)
        i += data.counts[s].size
        if data.used is not None:
            d = d[data.used]
        g = np.abs(sm[s].gain)
        fits.append(StreamFit(s, sm[s].unit, np.sqrt(np.mean(d**2, 0)) / g,
                              data.sigma_counts[s] / g))
    return Identification(
        model=model, names=names, x=z, x0=pb.x0.copy(), sigma=sigma, prior_sigma=pb.sigma0.copy(),
        covariance=C, held=~free, holds=tuple(holds), fits=tuple(fits), chi2_red=chi2,
        n_samples=data.n if data.used is None else int(data.used.sum()), n_residuals=m_res,
        iterations=n_jac[0], seconds=time.perf_counter() - t0,
        attitude_rad=z[pb.P:pb.P + 3] if pb.attitude else None, q_ref_rad=data.q_ref_rad, mode=mode,
        notes=tuple(notes), attitudes_rad=z[pb.P:].reshape(-1, 3) if pb.attitude else None,
        reference_checks=checks)


def _reference_checks(pb: _Problem, z: np.ndarray, H: np.ndarray, grad: np.ndarray, C: np.ndarray
                      ) -> tuple[ReferenceCheck, ...]:
    """Each reference against the rest of the fit, leave-one-out: ``H`` and ``grad`` are the
    information and the cost's data gradient (the references' rows included) over every
    element at the fit ``z``, with the fit's weights. Without reference k, every prior
    counted (held elements' too, as if free), one Gauss-Newton step from ``z`` reaches the
    rest's own optimum: ``δ = -A⁻¹ ∇``; the joint's geometric angle there is
    ``Y = q + g δ`` (``g`` its gradient), known to ``S² = g A⁻¹ gᵀ``; ``z = (Y - v) / √(S² + σ²)``.
    A step, not the posterior's algebra: the fit stops on a flat valley (a gauge) before its
    last hundredth of a σ, and a reference 100× sharper than the rest would magnify that.
    The fitted angle's σ is the fit's own (``C``: held elements as consider parameters)."""
    if not pb.refs:
        return ()
    r, J = pb.reference_rows(z, np.arange(pb.size))
    D = pb.sigma0
    prior_grad = (z - pb.x0) / D**2
    out = []
    for k, ref in enumerate(pb.refs):
        s_r = ref.sigma_rad
        g = J[k] * s_r  # d q_geom / d z
        A = (H - np.outer(J[k], J[k])) * np.outer(D, D) + np.eye(pb.size)  # prior units
        rest = (grad - J[k] * r[k] + prior_grad) * D
        gd = g * D
        S2 = float(gd @ np.linalg.solve(A, gd))
        d = float(r[k]) * s_r  # fitted minus the reference
        P = float(g @ C @ g)
        if S2 > (10.0 * np.pi) ** 2:  # nothing but the reference knows it
            out.append(ReferenceCheck(ref, ref.angle_rad + d, np.sqrt(P), np.nan, np.inf, 0.0))
            continue
        dy = d - float(gd @ np.linalg.solve(A, rest))
        out.append(ReferenceCheck(ref, ref.angle_rad + d, np.sqrt(P), ref.angle_rad + dy, np.sqrt(S2),
                                  dy / np.sqrt(S2 + s_r**2)))
    return tuple(out)


def identify_recentred(model: Model, data: FitData, streams: Sequence[str] | None = None,
                       settings: IdentifySettings | None = None, progress=None,
                       passes: int = 3) -> tuple[Identification, FitData]:
    """:func:`identify`, then, while a joint offset (the recording's encoder zero) ends near
    its bound, fold the offsets into ``q_ref`` and fit again. Returns the last fit and data."""
    res = identify(model, data, streams, settings, progress=progress)
    for _ in range(passes - 1):
        jo = [b for b in model.blocks if b.effect == "joint_offset"]
        near = [b for b in jo if abs(res.model_x[model.index[b.name]][0]) > 0.5 * b.upper[0]]
        if not near:
            break
        dq = np.zeros(model.arm.n_joints)
        for b in jo:
            dq[model.arm.joint_names.index(b.target)] = res.model_x[model.index[b.name]][0]
        data = data.shifted(dq)
        res = identify(model, data, streams, settings, progress=progress,
                       attitude0_rad=res.attitudes_rad)
        res = replace(res, notes=res.notes + (
            "encoder zeros re-centred on the previous fit (the start pose was "
            f"{np.degrees(np.max(np.abs(dq))):.1f}° off)",))
    return res, data


def identify_separately(model: Model, data: FitData, settings: IdentifySettings | None = None,
                        progress=None) -> dict[str, Identification]:
    """The article's "separate" calibration: each accelerometer (and the IMU) alone, each with
    its own base attitude (gravity direction), with only the blocks that reach it. If the
    gravity directions disagree by more than their σ, the model or a sensor is wrong."""
    out = {}
    arm = model.arm
    groups = [[s.name] for s in arm.link_accelerometers]
    if arm.imu is not None:
        groups.append([s for s in ("imu_acc", "imu_gyro", "imu_mag") if s in data.counts])
    for g in groups:
        g = [s for s in g if s in data.counts]
        if not g:
            continue
        _, jac = model.predict_with_jacobian(data.subset(slice(0, 2)).state, None, g)
        reach = {b for s in g for b in jac.get(s, {})}
        sub = model.without([b.name for b in model.blocks if b.name not in reach])
        key = arm.imu.name if g[0].startswith("imu") else g[0]
        # a joint reference pins a joint's zero in the one fit of every sensor; each sensor
        # alone compares gravity directions, which the reference does not touch
        out[key] = identify(sub, replace(data, joint_references=()), g, settings, progress=progress,
                            mode=f"separate ({key})")
    return out


def gravity_direction(attitude_rad: np.ndarray) -> np.ndarray:
    """Gravity's direction in the base frame (unit, pointing down) from roll, pitch, yaw."""
    R = R_from_rpy(np.array([attitude_rad[0]]), np.array([attitude_rad[1]]), np.array([attitude_rad[2]]))[0]
    return -R.T @ np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------------------
# results against a simulation's truth; configs
def truth_values(result: Identification, truth: dict) -> dict[str, float]:
    """The true value of every model element from a ``REC.truth.json`` dict (0 where the
    truth has no such effect). Joint offsets are shifted by the encoder-zero difference
    ``truth['encoder_zero_rad'] - q_ref`` that they absorb in the fit."""
    m = result.model
    vals = {}
    true_blocks = {f"{e['target']}.{e['effect']}": np.asarray(list(e['params'].values())[0], float).ravel()
                   for e in truth.get("effects", [])}
    zero = np.asarray(truth.get("encoder_zero_rad", np.zeros(m.arm.n_joints)), float)
    for b in m.blocks:
        v = true_blocks.get(b.name, np.zeros(b.size))
        if b.effect == "joint_offset":
            j = m.arm.joint_names.index(b.target)
            v = v + (zero[j] - result.q_ref_rad[j])
        for lab, x in zip(b.labels, v, strict=True):
            vals[f"{b.name}[{lab}]"] = float(x)
    return vals


def compare_with_truth(result: Identification, truth: dict) -> list[dict]:
    """Each model element: estimate, σ, truth and the error in σ (held ones included)."""
    tv = truth_values(result, truth)
    rows = []
    for i, n in enumerate(result.names):
        if n not in tv:
            continue
        z = (result.x[i] - tv[n]) / result.sigma[i] if result.sigma[i] > 0 else np.inf
        rows.append({"name": n, "estimate": float(result.x[i]), "sigma": float(result.sigma[i]),
                     "truth": tv[n], "z": float(z), "held": bool(result.held[i])})
    return rows


def joint_zero_conventions(result: Identification) -> list[str]:
    """Held elements that the data cannot tell from a joint's zero (the last sensor's mount
    rotation about the last joint's axis…): with relative encoders the startup defines the
    zeros with them at their priors, so they are a convention, not an error of the startup."""
    return [h.element for h in result.holds
            if any(p.split("[")[0].endswith(".joint_offset") for p, _ in h.partners)]


def correction_covariance(result: Identification) -> dict[str, dict]:
    """Per accelerometer stream, the covariance of the elements its still-reading correction
    uses (mount, axes, scale, bias, temperature drift), correlations included (a held axis
    angle and the mount rotation that carries it are known together far better than
    alone). The joint-zero conventions are in it too: a sensor's mount about the last
    joint's axis that no calibration can tell from that joint's zero is an uncertainty of
    the joint's real angle, which the startup's and the tracker's σ must carry
    (``StartupCorrection``)."""
    m = result.model
    conv: set[str] = set()
    arm = m.arm
    streams = [s.name for s in arm.link_accelerometers] + (["imu_acc"] if arm.imu is not None else [])
    out = {}
    for s in streams:
        idx = []
        for e in m.effects:
            if isinstance(e, SensorEffect) and s in e.streams:
                sl = m.index[e.block_name]
                idx += [i for i in range(sl.start, sl.stop) if result.names[i] not in conv]
        if idx:
            C = result.covariance[np.ix_(idx, idx)]
            out[s] = {"elements": [result.names[i] for i in idx],
                      "matrix": [[float(f"{v:.6g}") for v in row] for row in C]}
    return out


def config_with_estimates(config_data: dict, result: Identification,
                          include_joint_offsets: bool = False) -> dict:
    """A config dict (as loaded from YAML) with the effects replaced by the estimates and
    their σ, and ``calibration.accel_unmodelled_g`` lowered to what the fit leaves beyond
    the noise (per sensor in ``accel_unmodelled_g_per_sensor``).

    Joint offsets are left out unless asked: with relative encoders they are the
    recording's encoder zeros, not a property of the arm.
    """
    cm = result.calibrated_model()
    entries = entries_from_model(cm, cm.x0)
    if not include_joint_offsets:
        entries = [e for e in entries if e["effect"] != "joint_offset"]
    for e in entries:
        b = cm.block(f"{e['target']}.{e['effect']}")
        sl = cm.index[b.name]
        held = result.held[sl]
        e["note"] = (e["note"] + (" (held at its prior: the calibration data could not tell it)"
                                  if held.all() else ""))
    out = dict(config_data)
    out["effects"] = entries
    cal = dict(out.get("calibration") or {})
    un = result.unmodelled_g()
    if un:
        floor = max(un.values())
        cal["accel_unmodelled_g"] = round(max(floor, 1e-4), 6)
        cal["accel_unmodelled_g_per_sensor"] = {k: round(max(v, 1e-4), 6) for k, v in un.items()}
    cal["correction_covariance"] = correction_covariance(result)
    cal["identified"] = {"mode": result.mode, "samples": result.n_samples,
                         "chi2_red": round(result.chi2_red, 3),
                         "held": [h.element for h in result.holds],
                         "joint_zero_conventions": joint_zero_conventions(result),
                         "references": [c.as_dict() for c in result.reference_checks]}
    out["calibration"] = cal
    return out


# --------------------------------------------------------------------------------------
# what the startup calibration calls
@dataclass(frozen=True)
class StartupCorrection:
    """A calibrated config's effects, as the startup calibration needs them.

    * ``readings(r)``: averaged still readings (g, sensor axes) back to what an ideal sensor
      on its nominal mount would read: every sensor-stage effect of an accelerometer
      (mount, axes, scale, bias, temperature drift) is affine, ``y' = L y + c``; this
      inverts it, σ mapped through ``L⁻¹``;
    * ``controller_angles(q_geom)``: the startup solves the geometric joint angles; the
      joint-stage effects (offsets, sag, play) map the controller's angles to them, and
      this inverts that map (fixed point, three passes).
    """

    model: Model
    temperature_c: float = 25.0
    maps: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    spread: dict[str, list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)
    """Per stream, the map with each calibrated element moved by its σ: how uncertain the
    correction itself is, added to each reading's σ (along the reading's own direction)."""

    def readings(self, r):
        from fusion.startup.solve import StillReadings

        means, sigmas = {}, {}
        for name, m in r.accel_mean_g.items():
            means[name], sigmas[name] = self._undo(name, m, r.accel_sigma_g[name])
        imu_m, imu_s = r.imu_mean_g, r.imu_sigma_g
        if imu_m is not None and "imu_acc" in self.maps:
            imu_m, imu_s = self._undo("imu_acc", imu_m, imu_s)
        return StillReadings(means, sigmas, imu_m, imu_s, r.t_start_s, r.t_end_s)

    def readings_one(self, stream: str, mean_g: np.ndarray) -> np.ndarray:
        """One still reading of ``stream`` (g, sensor axes) corrected, as :meth:`readings`."""
        if stream not in self.maps:
            return np.asarray(mean_g, float)
        L, c = self.maps[stream]
        return np.linalg.solve(L, np.asarray(mean_g, float) - c)

    def _undo(self, stream, mean, sigma):
        if stream not in self.maps:
            return mean, sigma
        L, c = self.maps[stream]
        Li = np.linalg.inv(L)
        m = np.asarray(mean, float)
        y = Li @ (m - c)
        var = (Li**2) @ (np.asarray(sigma, float) ** 2)
        for L1, c1 in self.spread.get(stream, ()):
            var = var + (np.linalg.solve(L1, m - c1) - y) ** 2
        return y, np.sqrt(var)

    def controller_result(self, res, sigma_limit_rad: float | None = None):
        """A startup result (geometric angles, from ``solve_still``) on the controller's side:
        the config's joint effects (offsets, sag, play) undone at the chosen branch.

        Sag and play follow the gravity torque, which depends on where every joint stands.
        Where the startup cannot say (a rival branch it could not rule out, a gimbal-locked
        joint at any angle of its range), each numbered joint's σ grows to cover, at 2 σ,
        what its correction would be there; one pushed past ``sigma_limit_rad`` (default:
        the startup's limit) becomes ``ill_conditioned``."""
        from fusion.startup.solve import StartupSettings

        limit = (StartupSettings().sigma_limit_deg * np.pi / 180 if sigma_limit_rad is None
                 else sigma_limit_rad)
        q = np.asarray(res.q_rad, float)
        delta = q - self.controller_angles(q)
        if not np.any(delta):
            return res
        n = len(q)
        variants = []
        rivals = res.candidates_rad if res.candidates_rad is not None else res.branches_rad
        if any(j.flag == "ambiguous" for j in res.joints):
            variants += [b for b in np.asarray(rivals, float).reshape(-1, n)
                         if np.any(np.abs(b - q) > 1e-6)]
        arm = self.model.arm
        for i, j in enumerate(res.joints):
            if j.flag == "gimbal_lock":
                for v in np.linspace(arm.min_rad[i], arm.max_rad[i], 9):
                    qv = q.copy()
                    qv[i] = v
                    variants.append(qv)
        spread = np.zeros(n)
        if variants:
            V = np.array(variants)
            spread = np.max(np.abs((V - self.controller_angles(V)) - delta), axis=0)
        joints, cov = [], np.array(res.covariance, float, copy=True)
        for i, j in enumerate(res.joints):
            sig, flag = j.sigma_rad, j.flag
            if sig is not None and spread[i] / 2.0 > sig:
                grow = spread[i] / 2.0 / sig
                sig = sig * grow
                cov[i, :] *= grow
                cov[:, i] *= grow
                if flag == "ok" and sig > limit:
                    flag = "ill_conditioned"
            joints.append(replace(j, angle_rad=None if j.angle_rad is None else j.angle_rad - delta[i],
                                  sigma_rad=sig, flag=flag,
                                  alternatives_rad=tuple(a - delta[i] for a in j.alternatives_rad)))
        cands = (None if res.candidates_rad is None
                 else np.atleast_2d(self.controller_angles(np.asarray(res.candidates_rad, float))))
        return replace(res, joints=tuple(joints), q_rad=q - delta, covariance=cov, candidates_rad=cands)

    def controller_angles(self, q_geom_rad: np.ndarray) -> np.ndarray:
        joint = [e for e in self.model.effects if isinstance(e, JointEffect)]
        qg = np.atleast_2d(np.asarray(q_geom_rad, float))
        if not joint:
            return qg.reshape(np.shape(q_geom_rad))
        th = self.model.unpack()
        q = qg.copy()
        for _ in range(3):
            st = MotionState.static(q)
            ctx = Context(self.model.arm, st, self.model.masses)
            d = np.zeros_like(q)
            for e in joint:
                d[:, e.j] += e.delta(q, th[e.block_name], ctx)
            q = qg - d
        return q.reshape(np.shape(q_geom_rad))


COMPASS_MAP_EFFECTS = ("mag_soft_iron", "mag_hard_iron")
"""The compass effects that are a fixed affine map of its reading (the tracker undoes them)."""


def startup_correction(arm: ArmModel, temperature_c: float = 25.0,
                       include_joint_offsets: bool = False) -> StartupCorrection:
    """The correction the startup calibration applies for ``arm``'s config effects.

    Call once after loading the config; then ``corr.readings(readings)`` before
    ``solve_still`` and ``corr.controller_angles(q)`` on its joint angles. Joint offsets are
    skipped unless asked (relative encoders: the startup defines the zero).
    """
    model = model_from_arm(arm)
    if not include_joint_offsets:
        model = model.without([e.block_name for e in model.effects if e.name == "joint_offset"])
    accel = [s.name for s in arm.link_accelerometers] + (["imu_acc"] if arm.imu is not None else [])
    th = model.unpack()
    cov = (getattr(arm, "calibration", None) or {}).get("correction_covariance") or {}
    maps, spread = {}, {}
    for s in accel + (["imu_mag"] if arm.imu is not None else []):
        # the compass's own map is its soft and hard iron; the arm's steel (mag_arm_disturbance)
        # turns with the joints and is no fixed map
        effs = sorted((e for e in model.effects if isinstance(e, SensorEffect) and s in e.streams
                       and (s != "imu_mag" or e.name in COMPASS_MAP_EFFECTS)), key=lambda e: e.rank)
        if not effs:
            continue
        st = MotionState.static(np.zeros((4, arm.n_joints)), temperature_c=temperature_c)
        ctx = Context(arm, st, model.masses)

        def affine(theta, effs=effs, ctx=ctx, s=s):
            y = np.vstack([np.zeros(3), np.eye(3)])
            for e in effs:
                y = e.apply(y, theta[e.block_name], ctx, s)
            return (y[1:] - y[0]).T, y[0]

        maps[s] = affine(th)
        c = cov.get(s)
        if c:  # a calibrated config: the fit's covariance of this sensor's correction
            names = model.element_names()
            els = [n for n in c["elements"] if n in names]
            keep = [c["elements"].index(n) for n in els]
            C = np.asarray(c["matrix"], float)[np.ix_(keep, keep)]
            lam, V = np.linalg.eigh(0.5 * (C + C.T))
            spread[s] = []
            x0 = model.pack(th)
            for k in np.flatnonzero(lam > 0):  # each principal direction moved by its σ
                x1 = x0.copy()
                for i, n in enumerate(els):
                    x1[names.index(n)] += np.sqrt(lam[k]) * V[i, k]
                spread[s].append(affine(model.unpack(x1)))
    return StartupCorrection(model, temperature_c, maps, spread)
