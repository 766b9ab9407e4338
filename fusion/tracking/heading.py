"""Heading from the gyro and a tilt-compensated magnetometer, guarded against magnetic
disturbances the way x-io's Fusion AHRS guards its magnetometer.

The tracker's filter holds yaw and integrates it with the gyro. The magnetometer corrects
it through one scalar measurement: the heading that the measured field gives once the
base tilt is taken out (:func:`tilt_compensated_heading`). The magnetometer never
corrects roll or pitch (a steel door must not tilt the arm's estimate of gravity).

Before a magnetometer sample may correct the heading, :class:`MagneticGuard` checks it:

1. **Field checks.** The field's magnitude and its dip (inclination below the horizon)
   are compared with the expected Earth field (:class:`FieldReference`, learned from the
   still startup window or taken from the model). Steel, motors and cables near the
   chair change both; a sample outside the tolerances is a *disturbed* sample.
2. **Innovation check.** The heading innovation's NIS against the chi-square gate (done
   by the tracker, which owns the filter).
3. **Rejection and recovery** (Fusion's scheme, in seconds rather than samples): a
   trigger grows by dt with every rejected sample and shrinks by 9·dt with every
   accepted one, clamped to [0, ``recovery_trigger_s``]. Once it exceeds the timeout
   (``recovery_trigger_s``, or zero while recovery lasts), the magnetometer is used
   again even though it looks wrong: after a long disturbance the gyro's drift is the
   larger risk, or the reference itself was wrong. Unlike Fusion, a sample used in
   recovery carries its doubt: its noise is raised by the heading error that the
   measured field error could cause (``|ΔB| / B_horizontal``), and a disturbed field is
   used only once per ``recovery_interval_s`` (a disturbance is a bias: a hundred samples
   of it are not a hundred independent readings), so a still-disturbed field pulls the
   heading only as much as the gyro's own drift has made it uncertain.

Conventions: world z up, yaw about z from magnetic north (world x) unless the reference
carries a declination; ``R_WB = Rz(yaw) Ry(pitch) Rx(roll)``; fields in µT.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from armfusion.models.rotations import DEG, wrap_angle
from armfusion.models.sensor_kernels import magnetic_heading
from armfusion.models.sensor_models import AK8975_NOISE_UT_RMS, EARTH_FIELD_TAMPA_UT


# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HeadingSettings:
    magnitude_tolerance: float = 0.08
    """A field whose magnitude differs from the reference by more than this fraction is disturbed."""
    dip_tolerance_deg: float = 4.0
    """A field whose dip differs from the reference by more than this (deg) is disturbed."""
    recovery_trigger_s: float = 20.0
    """Fusion's recovery trigger period, in seconds of (net) rejection; 0 disables recovery."""
    recovery_interval_s: float = 1.0
    """In recovery, a disturbed field is used once per this interval, its noise raised by the
    heading error its field error could cause: a disturbance is a bias, not white noise, so
    its samples are not averaged as if independent."""
    noise_ut: float = AK8975_NOISE_UT_RMS
    """Magnetometer noise per axis, µT rms (AK8975: about 2 LSB)."""
    reference: str = "startup"
    """Where the expected field comes from: "startup" (the still window) or "model"."""
    # the compass calibrated by driving (:mod:`armfusion.fusion.tracking.compass_calibration`)
    fuse_below_deg: float = 10.0
    """The compass is fused once the iron it leaves unknown (the config's, narrowed by the
    turns the chair has made) would turn its heading by less than this (1 sigma); until
    then the heading is the gyro's and its status ``calibrating``."""
    iron_decorrelation_deg: float = 30.0
    """The unknown iron's heading error is a bias that changes only as the heading does:
    while the heading stays within this of where a visit began, the k-th fused heading's
    iron variance is counted k² times (together about one reading's worth per visit)."""
    steel_correlation_s: float = 5.0
    """The arm's steel's modelled error changes as the arm moves: its variance is counted
    once per this time, not once per fused heading."""
    iron_bin_deg: float = 5.0
    """Readings are binned by the de-tilted field's direction, this wide."""
    iron_bin_max_count: int = 20
    """A bin counts as at most this many independent readings (the model's own errors do
    not average away by sitting at one heading)."""
    iron_forget_s: float = 7200.0
    """A bin's weight fades with this time constant: a slow change of the chair's iron is followed."""
    iron_refit_period_s: float = 1.0
    """The estimate is refitted from the bins at most this often."""
    iron_model_floor_ut: float = 1.0
    """What one averaged reading's model leaves besides its noise, µT rms per axis (the arm's
    steel as modelled, the tilt, the averaging)."""


@dataclass(frozen=True)
class FieldReference:
    """The expected Earth field: magnitude (µT), dip below the horizon (rad, positive
    in the northern hemisphere) and declination (rad, east of world x)."""

    magnitude_ut: float
    dip_rad: float
    declination_rad: float = 0.0

    @property
    def horizontal_ut(self) -> float:
        return self.magnitude_ut * float(np.cos(self.dip_rad))

    @classmethod
    def from_world_field(cls, B_W_ut: np.ndarray = EARTH_FIELD_TAMPA_UT) -> FieldReference:
        B = np.asarray(B_W_ut, dtype=float)
        mag = float(np.linalg.norm(B))
        return cls(mag, float(np.arcsin(-B[2] / mag)), float(np.arctan2(B[1], B[0])))

    @classmethod
    def from_samples(cls, m_B_ut: np.ndarray, up_B: np.ndarray, declination_rad: float = 0.0
                     ) -> FieldReference:
        """From still samples ``m_B_ut (N, 3)`` in base axes and world-up in base axes."""
        m = np.asarray(m_B_ut, dtype=float).reshape(-1, 3).mean(axis=0)
        mag, dip = field_magnitude_and_dip(m, up_B)
        return cls(float(mag), float(dip), declination_rad)

    def world_field(self) -> np.ndarray:
        """The reference as a world-frame vector (µT)."""
        h = self.horizontal_ut
        return np.array([h * np.cos(self.declination_rad), h * np.sin(self.declination_rad),
                         -self.magnitude_ut * np.sin(self.dip_rad)])


# --------------------------------------------------------------------------------------
def field_magnitude_and_dip(m_B_ut: np.ndarray, up_B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Magnitude (µT) and dip (rad below the horizon) of fields ``(..., 3)`` in base axes,
    given world-up in base axes ``(..., 3)``."""
    m = np.asarray(m_B_ut, dtype=float)
    u = np.asarray(up_B, dtype=float)
    mag = np.linalg.norm(m, axis=-1)
    s = -np.sum(m * u, axis=-1) / np.maximum(mag, 1e-12)
    return mag, np.arcsin(np.clip(s, -1.0, 1.0))


def tilt_compensated_heading(m_B_ut: np.ndarray, roll_rad, pitch_rad,
                             declination_rad: float = 0.0) -> np.ndarray:
    """Yaw (rad) of a base at (roll, pitch) whose magnetometer reads ``m_B_ut (..., 3)``
    (base axes). Batched: the angles broadcast against the field's leading axes.

    With ``R_WB = Rz(ψ) Ry(θ) Rx(φ)`` and ``m_B = R_WB^T B_W``, the de-tilted field
    ``h = Ry(θ) Rx(φ) m_B = Rz(ψ)^T B_W`` has ``ψ = atan2(-h_y, h_x) + declination``.
    """
    m = np.asarray(m_B_ut, dtype=float)
    r = np.asarray(roll_rad, dtype=float)
    p = np.asarray(pitch_rad, dtype=float)
    psi = magnetic_heading(m[..., 0], m[..., 1], m[..., 2], np.sin(r), np.cos(r), np.sin(p), np.cos(p))
    return wrap_angle(psi + declination_rad)


def heading_sigma_rad(reference: FieldReference, noise_ut: float) -> float:
    """Heading noise of one sample: the horizontal field's noise across its direction."""
    return float(noise_ut / max(reference.horizontal_ut, 1e-6))


# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FieldCheck:
    """One magnetometer sample against the reference."""

    magnitude_ut: float
    dip_rad: float
    magnitude_error_ut: float
    dip_error_rad: float
    disturbed: bool

    def doubt_rad(self, reference: FieldReference) -> float:
        """The heading error this field error could cause (rad, 1 sigma)."""
        d = np.hypot(self.magnitude_error_ut, reference.magnitude_ut * self.dip_error_rad)
        return float(d / max(reference.horizontal_ut, 1e-6))


@dataclass(frozen=True)
class GuardState:
    """The guard's flags, returned by value (as Fusion's ``FusionAhrsFlags``)."""

    disturbed: bool = False
    """The last sample failed the field checks."""
    ignored: bool = False
    """The last sample was not used."""
    recovering: bool = False
    """Magnetic recovery: samples are used although they look wrong."""
    trigger_s: float = 0.0
    rejected_total: int = 0
    disturbed_total: int = 0


class MagneticGuard:
    """Decides, sample by sample, whether the magnetometer may correct the heading."""

    def __init__(self, reference: FieldReference, settings: HeadingSettings | None = None):
        self.reference = reference
        self.settings = settings or HeadingSettings()
        self._trigger = 0.0
        self._timeout = self.settings.recovery_trigger_s
        self._last_t: float | None = None
        self._last = (False, False, False)
        self._rejected = 0
        self._disturbed = 0

    @property
    def state(self) -> GuardState:
        d, i, r = self._last
        return GuardState(disturbed=d, ignored=i, recovering=r, trigger_s=self._trigger,
                          rejected_total=self._rejected, disturbed_total=self._disturbed)

    @property
    def last_recovering(self) -> bool:
        """Whether the last sample was used in recovery (cheap: no flags object)."""
        return self._last[2]

    @property
    def recovering(self) -> bool:
        """Whether the next sample will be used whatever it looks like."""
        period = self.settings.recovery_trigger_s
        return period > 0 and self._trigger > self._timeout

    def check_field(self, m_B_ut: np.ndarray, up_B: np.ndarray) -> FieldCheck:
        mx, my, mz = (float(v) for v in m_B_ut)
        ux, uy, uz = (float(v) for v in up_B)
        mag = math.sqrt(mx * mx + my * my + mz * mz)
        dip = math.asin(max(-1.0, min(1.0, -(mx * ux + my * uy + mz * uz) / max(mag, 1e-12))))
        em = mag - self.reference.magnitude_ut
        ed = dip - self.reference.dip_rad
        st = self.settings
        disturbed = (abs(em) > st.magnitude_tolerance * self.reference.magnitude_ut
                     or abs(ed) > st.dip_tolerance_deg * DEG)
        return FieldCheck(mag, dip, em, ed, disturbed)

    def record(self, t_s: float, passed: bool, disturbed: bool) -> bool:
        """Count one sample (``passed``: field checks and gate both fine) and return
        whether it is to be used (it passed, or recovery is on)."""
        dt = 0.0 if self._last_t is None else max(0.0, t_s - self._last_t)
        self._last_t = t_s
        period = self.settings.recovery_trigger_s
        if passed:
            self._trigger -= 9.0 * dt
        else:
            self._trigger += dt
        use = passed
        recovering = False
        if period > 0 and self._trigger > self._timeout:
            self._timeout = 0.0
            use = True
            recovering = not passed
        else:
            self._timeout = period
        self._trigger = min(max(self._trigger, 0.0), period)
        self._last = (disturbed, not use, recovering)
        self._rejected += 0 if use else 1
        self._disturbed += 1 if disturbed else 0
        return use

    def snapshot(self) -> dict:
        return {"trigger_s": self._trigger, "timeout_s": self._timeout, "last_t": self._last_t}

    def restore(self, snap: dict) -> None:
        self._trigger = float(snap["trigger_s"])
        self._timeout = float(snap["timeout_s"])
        self._last_t = snap["last_t"]
