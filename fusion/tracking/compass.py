"""The compass inside the tracker: how far the config says its readings may be from
Earth's field (the iron it leaves unmodelled), the map that undoes the iron it models,
and :class:`Compass`, the part of the filter that averages the magnetometer over a
period, checks the field (:class:`fusion.tracking.heading.MagneticGuard`), sets the heading
measurement's noise and decides whether it is used."""

from __future__ import annotations

import math

import numpy as np

from fusion.tracking.calibrated import hard_iron_sigma_ut, has_effect
from fusion.tracking.heading import FieldCheck, FieldReference, MagneticGuard, heading_sigma_rad
from fusion.tracking.innovations import InnovationRing
from fusion.tracking.settings import MAG, TrackerSettings
from models.arm import ArmModel
from models.effects import Model
from models.rotations import DEG, exp_so3_one


def compass_unmodelled_ut(arm: ArmModel, model: Model | None = None) -> float:
    """How far the compass's horizontal reading may be from Earth's field, µT, by what the
    config says: the σ of a hard iron it holds (the tracker undoes the hard and soft iron,
    :data:`fusion.identification.identify.COMPASS_MAP_EFFECTS`, so what stays is how well they are known),
    else ``calibration.mag_unmodelled_ut``, else 0. ``model``: the config's effects
    (:func:`fusion.tracking.calibrated.config_model`), when the caller has it."""
    if model is None and arm.effects:
        from fusion.tracking.calibrated import config_model

        model = config_model(arm)
    s = hard_iron_sigma_ut(model)
    if s is not None:
        return float(np.sqrt(np.sum(s[:2] ** 2)))
    return arm.calibration.mag_unmodelled_ut


def compass_unmodelled_rad(arm: ArmModel, field: FieldReference, model: Model | None = None) -> float:
    """:func:`compass_unmodelled_ut` as a heading error (rad) against the horizontal field;
    at or past the field itself the compass says nothing about the heading (π)."""
    u = compass_unmodelled_ut(arm, model)
    h = max(field.horizontal_ut, 1e-6)
    return float(np.pi if u >= h else np.arcsin(u / h))


def compass_map(arm: ArmModel, correction=None, model: Model | None = None
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """The config's soft and hard iron as the map that undoes them, ``(A, c)``: the field
    in the compass's axes is ``(y - c) @ A`` for readings ``y (N, 3)`` µT; None without them.
    ``correction``: the config's :class:`fusion.identification.identify.StartupCorrection`, if
    made already."""
    if correction is None:
        if model is None and arm.effects:
            from fusion.tracking.calibrated import config_model

            model = config_model(arm)
        if not (has_effect(model, "mag_hard_iron") or has_effect(model, "mag_soft_iron")):
            return None
        from fusion.identification.identify import startup_correction

        correction = startup_correction(arm)
    from fusion.tracking.calibrated import undo_map

    return undo_map(correction, MAG)


class Compass:
    """The magnetometer's part of the filter, from the startup's field reference (``None``:
    no reference, the compass is not fused).

    Its samples are averaged over ``mag_fuse_period_s`` and fused as one heading; each is
    first turned, with the gyro, into the base's axes at the period's end, so that a turning
    chair does not smear the average. A compass whose config leaves more unmodelled iron
    than ``compass_max_unmodelled_deg`` is not fused (:attr:`usable` False)."""

    def __init__(self, arm: ArmModel, model: Model | None, field: FieldReference | None,
                 settings: TrackerSettings, t_s: float):
        st = settings
        self.field = field
        self.guard = MagneticGuard(field, st.heading) if field is not None else None
        self.sigma_psi = heading_sigma_rad(field, st.heading.noise_ut) if field else np.inf
        # an unmodelled hard iron turns every compass heading by up to asin(h / B_h), a
        # different amount at every heading: taken as noise of that size on each update
        self.iron_var = compass_unmodelled_rad(arm, field, model) ** 2 if field else 0.0
        self.usable = self.iron_var <= (st.compass_max_unmodelled_deg * DEG) ** 2
        self.period_s = st.mag_fuse_period_s
        self.recovery_interval_s = st.heading.recovery_interval_s
        self.ring = InnovationRing(1, st.innovation_capacity)
        self.flags = (False, False)
        """(disturbance, recovery) at the last fused heading."""
        self.recovery_t = -np.inf
        self._sum = None
        self._n = 0
        self._t0 = float(t_s)
        self._rot = np.eye(3)  # the base's turn since the averaging period began

    @property
    def fused(self) -> bool:
        return self.guard is not None and self.usable

    def turn(self, w: np.ndarray, bias: tuple[float, float, float], dt: float) -> None:
        """The base turned at ``w - bias`` (rad/s, base axes) for ``dt``."""
        if self._n:
            wx, wy, wz = w.tolist()
            bx, by, bz = bias
            self._rot = self._rot @ exp_so3_one(((wx - bx) * dt, (wy - by) * dt, (wz - bz) * dt))

    def average(self, t: float, m_B: np.ndarray):
        """Take one field sample (µT, base axes): ``(count, mean field)`` when a period is
        complete, else None."""
        m = self._rot @ m_B  # in the base's axes at the period's start
        self._sum = m if self._n == 0 else self._sum + m
        self._n += 1
        if t - self._t0 < self.period_s - 1e-9:
            return None
        out = (self._n, self._rot.T @ (self._sum / self._n))
        self._n = 0
        self._t0 = t
        self._rot = np.eye(3)
        return out

    def variance(self, m_B: np.ndarray, up_B: np.ndarray, count: int) -> tuple[FieldCheck, float]:
        """The field check of the averaged field ``m_B`` and the heading measurement's
        variance (rad²): the average's noise, the unmodelled iron, and a disturbed field's doubt."""
        check = self.guard.check_field(m_B, up_B)
        v = self.sigma_psi**2 / count + self.iron_var
        if check.disturbed:
            v += check.doubt_rad(self.field) ** 2
        return check, v

    def verdict(self, t: float, gate_ok: bool, check: FieldCheck, innovation, S, nis: float) -> bool:
        """Whether the heading is used (the guard's rejection and recovery: a doubtful field
        once per ``recovery_interval_s``); the innovation is kept."""
        passed = gate_ok and not check.disturbed
        use = self.guard.record(t, passed, check.disturbed)
        if use and not passed:
            use = t - self.recovery_t >= self.recovery_interval_s
            if use:
                self.recovery_t = t
        self.ring.add(t, innovation, S, nis, use, count_stats=not check.disturbed)
        self.flags = (check.disturbed, self.guard.last_recovering)
        return use

    def heading_shift_rad(self) -> float:
        """What the measurement model adds to the tilt-compensated heading: the declination less π."""
        return self.field.declination_rad - math.pi

    def snapshot(self) -> dict:
        return {"field": None if self.field is None else {
                    "magnitude_ut": self.field.magnitude_ut, "dip_rad": self.field.dip_rad,
                    "declination_rad": self.field.declination_rad},
                "guard": None if self.guard is None else self.guard.snapshot()}

    @staticmethod
    def field_from(snap: dict) -> FieldReference | None:
        fld = snap.get("field")
        return None if fld is None else FieldReference(fld["magnitude_ut"], fld["dip_rad"],
                                                       fld["declination_rad"])

    def restore(self, snap: dict) -> None:
        if self.guard is not None and snap.get("guard") is not None:
            self.guard.restore(snap["guard"])
