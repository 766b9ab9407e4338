"""The compass inside the tracker: how far the config says its readings may be from
Earth's field (the iron it leaves unmodelled), the map that undoes the iron it models,
the field of the arm's own steel at the joint angles the tracker knows (:class:`ArmSteel`),
and :class:`Compass`, the part of the filter that averages the magnetometer over a
period, calibrates the iron the config leaves unknown from the chair's turns
(:class:`armfusion.fusion.tracking.compass_calibration.IronEstimator`), checks the field
(:class:`armfusion.fusion.tracking.heading.MagneticGuard`), sets the heading measurement's noise and
decides whether it is used; its :attr:`Compass.status` is the heading feed's."""

from __future__ import annotations

import math

import numpy as np
from armfusion.fusion.tracking.calibrated import effect_blocks, hard_iron_sigma_ut, has_effect
from armfusion.fusion.tracking.compass_calibration import IronEstimator, detilt
from armfusion.fusion.tracking.compass_iron import FixedIron, iron_axes_ut
from armfusion.fusion.tracking.estimate import HEADING_STATUS
from armfusion.fusion.tracking.heading import FieldCheck, FieldReference, MagneticGuard, heading_sigma_rad
from armfusion.fusion.tracking.innovations import InnovationRing
from armfusion.fusion.tracking.settings import MAG, TrackerSettings
from armfusion.fusion.tracking.turn_kernels import turned_back
from armfusion.models.arm import ArmModel
from armfusion.models.effects import Model
from armfusion.models.effects.imu import dipole_field
from armfusion.models.effects.library import BaseMount, MagArmDisturbance, MagHardIron, MagSoftIron
from armfusion.models.kinematics import chain_poses
from armfusion.models.rotations import DEG, exp_so3_one


def compass_unmodelled_ut(arm: ArmModel, model: Model | None = None) -> float:
    """How far the compass's horizontal reading may be from Earth's field, µT, by what the
    config says: the σ of a hard iron it holds (the tracker undoes the hard and soft iron,
    :data:`armfusion.fusion.identification.identify.COMPASS_MAP_EFFECTS`, so what stays is how
    well they are known),
    else ``calibration.mag_unmodelled_ut``, else 0. ``model``: the config's effects
    (:func:`armfusion.fusion.tracking.calibrated.config_model`), when the caller has it."""
    if model is None and arm.effects:
        from armfusion.fusion.tracking.calibrated import config_model

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
    ``correction``: the config's :class:`armfusion.fusion.identification.identify.StartupCorrection`, if
    made already."""
    if correction is None:
        if model is None and arm.effects:
            from armfusion.fusion.tracking.calibrated import config_model

            model = config_model(arm)
        if not (has_effect(model, MagHardIron.name) or has_effect(model, MagSoftIron.name)):
            return None
        from armfusion.fusion.identification.identify import startup_correction

        correction = startup_correction(arm)
    from armfusion.fusion.tracking.calibrated import undo_map

    return undo_map(correction, MAG)


SOFT_IRON_TYPICAL = np.array([0.05, 0.05, 0.05, 0.02, 0.02, 0.02])
"""The soft iron's datasheet-typical sigma (the ``mag_soft_iron`` effect's prior), used when
the config holds no soft iron but says its compass is not exact."""

COMPASS_FUSED, GYRO_ONLY, DISTURBED, CALIBRATING = HEADING_STATUS
STATUS_CODE = {s: i for i, s in enumerate(HEADING_STATUS)}


class ArmSteel:
    """The field of the arm's own steel and motors at the compass (the config's
    ``mag_arm_disturbance`` dipoles, each fixed in the link after its joint), at the joint
    angles the tracker knows, with its covariance from the dipoles' sigmas."""

    def __init__(self, arm: ArmModel, model: Model | None):
        self.arm = arm
        self.dipoles = [(arm.joint_names.index(e.target), value, sigma)
                        for e, value, sigma in effect_blocks(model, MagArmDisturbance.name)]
        if not self.dipoles and arm.imu is not None and arm.calibration.imu_accel_floor_g > 0.0:
            # a config that says nothing of the arm's steel and whose IMU is not exact (sensors
            # as they come): every link's steel unknown at the library's typical size, so its
            # field's change with the pose is doubt on the heading, not a surprise
            self.dipoles = typical_steel(arm)
        imu = arm.imu
        self.R_0I = imu.R_LS if imu is not None else np.eye(3)
        self.p_I = np.asarray(imu.p_L_m, float) if imu is not None else np.zeros(3)
        self.sigma = np.concatenate([s for _, _, s in self.dipoles]) if self.dipoles else np.zeros(0)
        self.J_mean = None  # the dipoles' mean Jacobian over the readings the iron was fitted on
        self.n_mean = 0.0

    def __bool__(self) -> bool:
        return bool(self.dipoles)


    def field_ut(self, q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The steel's field at the compass ``b (3,)`` (µT, compass axes) and its Jacobian in
        the dipoles' moments ``(3, 3 n)`` (µT per A·m²)."""
        poses = chain_poses(self.arm, np.asarray(q_rad, float)[None])
        b, J = np.zeros(3), np.zeros((3, 3 * len(self.dipoles)))
        for k, (j, moment, _) in enumerate(self.dipoles):
            R_0L, p_d = poses.R_0L[0, j + 1], poses.p_0L_m[0, j + 1]
            B, D, _ = dipole_field((self.p_I - p_d)[None], (R_0L @ moment)[None])
            b += self.R_0I.T @ B[0]
            J[:, 3 * k:3 * k + 3] = self.R_0I.T @ D[0] @ R_0L
        return b, J

    def absorbed(self, J: np.ndarray, forget: float) -> None:
        """A reading at Jacobian ``J`` went into the iron's fit: whatever field the dipoles'
        error makes at the poses it was fitted on, the hard iron took on as its mean."""
        self.n_mean = self.n_mean * forget + 1.0
        self.J_mean = J.copy() if self.J_mean is None else self.J_mean + (J - self.J_mean) / self.n_mean

    def covariance(self, J: np.ndarray) -> np.ndarray:
        """The covariance (µT², compass axes) of the steel's field error at a pose of Jacobian
        ``J``, less the part the hard iron took on (its mean over the fitted readings)."""
        D = J if self.J_mean is None else J - self.J_mean
        return (D * self.sigma**2) @ D.T


def typical_steel(arm: ArmModel) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(joint index, moment, sigma)`` of an unknown ``mag_arm_disturbance`` on every joint
    it can model (its link's origin far enough from the IMU): zero moment, the effect's
    datasheet-typical sigma."""
    from armfusion.models.effects.base import TargetError
    from armfusion.models.effects.entries import build_effect

    out = []
    for j, name in enumerate(arm.joint_names):
        try:
            sigma = build_effect(arm, MagArmDisturbance.name, name).default_sigma()
        except TargetError:
            continue
        out.append((j, np.zeros(3), np.asarray(sigma, float)))
    return out


def iron_prior_sigma(arm: ArmModel, model: Model | None) -> np.ndarray | None:
    """The prior sigma of the iron the compass's readings may still hold, hard (µT, 3) then
    soft (6): the config's ``mag_hard_iron`` and ``mag_soft_iron`` sigmas, else its
    ``calibration.mag_unmodelled_ut`` with a datasheet-typical soft iron; None when the config
    says its compass is exact (neither)."""
    hard = hard_iron_sigma_ut(model)
    soft = next((sigma for _, _, sigma in effect_blocks(model, MagSoftIron.name)), None)
    if hard is None:
        u = arm.calibration.mag_unmodelled_ut
        if u <= 0:
            return None
        hard = np.full(3, u)
    soft = SOFT_IRON_TYPICAL if soft is None else soft
    return np.concatenate([np.maximum(hard, 1e-3), np.maximum(soft, 1e-5)])


def mount_heading_sigma_rad(arm: ArmModel, model: Model | None) -> float:
    """The heading's sigma (rad) from the IMU's mount about the vertical (the config's
    ``base_mount`` of the IMU, its sigma turned into the base's axes): gravity cannot see
    it and the compass reads the IMU's heading, so it is a constant bias of every heading
    the tracker gives, whatever the compass and the gyro do. A config without one whose IMU
    is not exact (its unmodelled error above zero: sensors as they come, glued on by hand)
    has the effect's datasheet-typical prior; an exact one, none."""
    if arm.imu is None:
        return 0.0
    sigma = None
    for e, _, s in effect_blocks(model, BaseMount.name):
        if e.target == arm.imu.name:
            sigma = s
    if sigma is None:
        if arm.calibration.imu_accel_floor_g <= 0.0:
            return 0.0
        from armfusion.models.effects.entries import build_effect

        sigma = build_effect(arm, BaseMount.name, arm.imu.name).default_sigma()
    return float(math.sqrt(np.sum((np.asarray(arm.imu.R_LS)[2] * sigma) ** 2)))


class Compass:
    """The magnetometer's part of the filter, from the startup's field reference (``None``:
    no reference, the compass is not fused).

    Its samples are averaged over ``mag_fuse_period_s``; each is first turned, with the
    gyro, into the base's axes at the period's end, so that a turning chair does not smear
    the average. Each average has the arm's steel (:class:`ArmSteel`) and the estimated
    iron (:class:`~armfusion.fusion.tracking.compass_calibration.IronEstimator`) taken out, and is
    fused as one heading once the iron's doubt is below ``heading.fuse_below_deg``."""

    def __init__(self, arm: ArmModel, model: Model | None, field: FieldReference | None,
                 settings: TrackerSettings, t_s: float, R_0I: np.ndarray | None = None,
                 delay_s: float = 0.0):
        """``delay_s``: how long before its stamp the magnetometer's reading stands for the
        field (its part's delay, its description's; :meth:`average` turns it to the stamp)."""
        st = settings
        self.delay_s = float(delay_s)
        self.settings = st.heading
        self.field = field
        self.R_0I = np.eye(3) if R_0I is None else np.asarray(R_0I, float)
        self.guard = MagneticGuard(field, st.heading) if field is not None else None
        self.sigma_psi = heading_sigma_rad(field, st.heading.noise_ut) if field else np.inf
        self.steel = ArmSteel(arm, model)
        prior = iron_prior_sigma(arm, model) if field is not None else None
        self.iron = None
        # a config that knows its compass well enough to fuse it as it is (a factory-calibrated
        # module) keeps its word: its iron's doubt is noise on every heading; one that does not
        # (a parked fit's hard iron) has it learnt from the turns
        doubt_rad = compass_unmodelled_rad(arm, field, model) if field is not None else 0.0
        if prior is not None and doubt_rad > st.heading.fuse_below_deg * DEG:
            V = field.magnitude_ut * math.sin(field.dip_rad)
            self.iron = IronEstimator(prior[:9], field.horizontal_ut, V,
                                      float(np.linalg.norm(prior[:3])) + 0.1 * field.magnitude_ut,
                                      st.heading, t_s)
        self.corr_count = max(st.heading.steel_correlation_s / st.mag_fuse_period_s, 1.0)
        self._visit = (None, 0)  # (the heading a visit began at, rad; fused headings since)
        self.forget_per_period = math.exp(-st.mag_fuse_period_s / st.heading.iron_forget_s)
        self.period_s = st.mag_fuse_period_s
        self.recovery_interval_s = st.heading.recovery_interval_s
        self.ring = InnovationRing(1, st.innovation_capacity)
        self.flags = (False, False)
        """(disturbance, recovery) at the last fused heading."""
        self.status = CALIBRATING if self.iron is not None else GYRO_ONLY
        """The heading feed's status (:data:`HEADING_STATUS`)."""
        self.iron_sigma_rad = np.inf if self.iron is not None else doubt_rad
        # the config's iron where nothing estimates it: a field fixed in the compass's axes
        # (σ per axis, µT), whose heading error turns with the sensor (:meth:`_iron_var`)
        self.fixed_iron = (None if self.iron is not None or doubt_rad <= 0.0
                           else FixedIron(iron_axes_ut(arm, model)))
        self._extra_var = 0.0  # the last prepared reading's extra variance (rad²)
        self._noise_var = 0.0  # the last field check's measurement variance (rad²)
        """The heading's sigma from the iron still unknown (the estimate's at the last period,
        or the config's own doubt where nothing is estimated)."""
        self.steel_sigma_rad = 0.0
        """The heading's sigma from the arm's steel as the config knows it, at the last period."""
        self.mount_var = mount_heading_sigma_rad(arm, model) ** 2 if field is not None else 0.0
        # a tilt wrong by d about the field's horizontal direction turns the compass's heading
        # by d tan(dip). The IMU accelerometer's unmodelled error (the config's floor) is such a
        # d, and a state of the filter (its prior σ the floor): the filter's tilt covariance
        # holds it as far as the motion has not revealed it (:meth:`tilt_seen`). Until the
        # filter has said, the floor itself.
        floor_g = min(arm.calibration.imu_accel_floor_g, 1.0) if arm.imu is not None else 0.0
        self.tilt_var = ((math.asin(floor_g) * math.tan(min(abs(field.dip_rad), 1.4))) ** 2
                         if field is not None else 0.0)
        """The heading's variance from the tilt's error (rad²), at the last prepared reading."""
        self._fused_floor_var = 0.0  # the compass's biases at the last fused period (rad²)
        self.recovery_t = -np.inf
        self._sum = None
        self._n = 0
        self._t0 = float(t_s)
        self._rot = np.eye(3)  # the base's turn since the averaging period began

    @property
    def listening(self) -> bool:
        """Whether the compass's readings are averaged and prepared (a field reference exists;
        they are fused only once the iron is known: :meth:`prepare`)."""
        return self.guard is not None

    @property
    def averaging(self) -> bool:
        """A period's samples are being averaged: :meth:`turn` needs the base's rate (it does
        nothing otherwise)."""
        return self._n > 0

    def turn(self, om: np.ndarray, dt: float) -> None:
        """The base turned at ``om`` (rad/s, base axes) for ``dt``."""
        if self._n:
            wx, wy, wz = om.tolist()
            self._rot = self._rot @ exp_so3_one((wx * dt, wy * dt, wz * dt))

    def average(self, t: float, m_B: np.ndarray, om: np.ndarray | None = None):
        """Take one field sample (µT, base axes), the base turning at ``om`` (rad/s, base
        axes; None: not known): ``(count, mean field)`` when a period is complete, else None.
        A reading that stands for the field :attr:`delay_s` before its stamp is first turned to
        the stamp by the base's turn over the delay (the accelerometers' alike:
        :meth:`armfusion.fusion.tracking.measurement.Measurements.stack`)."""
        if self.delay_s and om is not None:
            m_B = turned_back(m_B, om, self.delay_s)
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

    def tilt_seen(self, C_tilt: np.ndarray) -> None:
        """The filter's covariance ``C_tilt (2, 2)`` (rad²) of the attitude's world-axis
        rotation about x and y (its tangent space's) at a reading: the heading's share of the
        tilt is its part about the field's horizontal direction, times tan²(dip)."""
        if self.field is None:
            return
        d = self.field.declination_rad
        n = np.array([math.cos(d), math.sin(d)])
        v = max(float(n @ np.asarray(C_tilt, float) @ n), 0.0)
        self.tilt_var = v * math.tan(min(abs(self.field.dip_rad), 1.4)) ** 2

    def prepare(self, t: float, count: int, m_B: np.ndarray, roll_rad: float, pitch_rad: float,
                q_rad: np.ndarray):
        """One period's average ``m_B`` (µT, base axes) with the arm's steel and the estimated
        iron taken out, ready to fuse: ``(count, field in base axes, extra heading variance
        (rad²))``; None while the iron is too little known (status ``calibrating``)."""
        R = self.R_0I
        m_S = R.T @ m_B
        b_arm = J_arm = None
        if self.steel:
            b_arm, J_arm = self.steel.field_ut(q_rad)
        T = detilt(roll_rad, pitch_rad, R)
        extra = 0.0
        if self.iron is not None:
            iron = self.iron
            ready = self.iron_sigma_rad <= self.settings.fuse_below_deg * DEG
            h = T @ iron.corrected(m_S, b_arm)
            disturbed = ready and self._off_field(h)
            if iron.add(t, m_S, T, self.sigma_psi_ut2(count), b_arm, disturbed) and J_arm is not None:
                self.steel.absorbed(J_arm, self.forget_per_period)
            if iron.refit(t):
                self._adopt_field()
            self.iron_sigma_rad = iron.heading_sigma_rad(m_S, T, b_arm)
            if self.iron_sigma_rad > self.settings.fuse_below_deg * DEG:
                self.status = CALIBRATING
                return None
            m_S = iron.corrected(m_S, b_arm)
        elif b_arm is not None:
            m_S = m_S - b_arm
        h = T @ m_S  # the corrected field, de-tilted
        if self.iron_sigma_rad > 0.0:  # the iron's doubt: one reading's worth per heading visit
            psi = math.atan2(-h[1], h[0])
            anchor, k = self._visit
            if anchor is None or abs(math.remainder(psi - anchor, 2 * math.pi)) > \
                    math.radians(self.settings.iron_decorrelation_deg):
                anchor, k = psi, 0
            self._visit = (anchor, k + 1)
            extra += self.iron_sigma_rad**2 * (k + 1) ** 2
            if self.fixed_iron is not None:
                self.fixed_iron.read(h, T)
        if J_arm is not None:
            C_arm = self.steel.covariance(J_arm)
            n2 = max(h[0] ** 2 + h[1] ** 2, 1e-12)
            g = np.array([h[1], -h[0], 0.0]) / n2 @ T  # d psi / d b_arm (compass axes), sign aside
            self.steel_sigma_rad = math.sqrt(max(float(g @ C_arm @ g), 0.0))
            extra += self.steel_sigma_rad**2 * self.corr_count
        self._extra_var = extra
        return count, R @ m_S, extra

    @property
    def heading_floor_var(self) -> float:
        """What no averaging removes from the heading (rad²), added to its reported variance:
        the IMU's mount about the vertical and, while the compass is fused, the heading error
        the IMU accelerometer's unmodelled error makes through the tilt, and the errors of the
        arm's steel as modelled at the present pose and of the iron as estimated at the
        present heading (biases for as long as the arm and the chair stay as they are); while
        the gyro carries a heading the compass once set (``disturbed``, ``gyro_only``), those
        of the last fused period."""
        if self.status == COMPASS_FUSED:
            return self.mount_var + self._biases_var()
        # once fused, the compass's biases stay in the heading while the gyro carries it
        # (disturbed, gone quiet): the last fused heading held them, and the gyro turns it on
        return self.mount_var + self._fused_floor_var

    def _biases_var(self) -> float:
        """The compass's biases in a heading it sets now (rad²): the tilt's share, the arm's
        steel at the present pose, the iron at the present heading."""
        return self.tilt_var + self.steel_sigma_rad**2 + self._iron_var()

    def _iron_var(self) -> float:
        """The iron's share of the heading's variance (rad²): an iron the compass estimates,
        its estimate's doubt at the present heading; the config's own word, what the heading
        holds of it (:class:`armfusion.fusion.tracking.compass_iron.FixedIron`)."""
        v = None if self.fixed_iron is None else self.fixed_iron.var_rad2()
        return self.iron_sigma_rad**2 if v is None else v

    def sigma_psi_ut2(self, count: int) -> float:
        """One averaged reading's noise variance per axis, µT²."""
        return self.settings.noise_ut**2 / max(count, 1)

    def _off_field(self, h: np.ndarray) -> bool:
        """Whether a de-tilted, corrected field ``h`` is off Earth's as estimated by more
        than the guard's tolerances (a disturbance: not binned)."""
        H, V = self.iron.field_ut
        mag = math.hypot(H, V)
        st = self.settings
        got = float(np.linalg.norm(h))
        dip = math.asin(max(-1.0, min(1.0, -h[2] / max(got, 1e-9))))
        return (abs(got - mag) > st.magnitude_tolerance * mag
                or abs(dip - math.atan2(V, H)) > st.dip_tolerance_deg * DEG)

    def _adopt_field(self) -> None:
        """Earth's field as the estimate has it becomes the guard's reference."""
        H, V = self.iron.field_ut
        if H <= 0:
            return
        ref = FieldReference(math.hypot(H, V), math.atan2(V, H), self.field.declination_rad)
        self.field = ref
        self.guard.reference = ref
        self.sigma_psi = heading_sigma_rad(ref, self.settings.noise_ut)

    def variance(self, m_B: np.ndarray, up_B: np.ndarray, count: int) -> tuple[FieldCheck, float]:
        """The field check of the averaged field ``m_B`` and the heading measurement's
        variance (rad²): the average's noise and a disturbed field's doubt (the iron's and
        the steel's are :meth:`prepare`'s)."""
        check = self.guard.check_field(m_B, up_B)
        v = self.sigma_psi**2 / count
        if check.disturbed:
            v += check.doubt_rad(self.field) ** 2
        self._noise_var = v
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
        self.status = COMPASS_FUSED if use else DISTURBED
        if use:
            if self.fixed_iron is not None:
                self.fixed_iron.fused(self._noise_var + self._extra_var, float(np.asarray(S).reshape(-1)[-1]))
            self._fused_floor_var = self._biases_var()
        return use

    def heading_shift_rad(self) -> float:
        """What the measurement model adds to the tilt-compensated heading: the declination less π."""
        return self.field.declination_rad - math.pi

    def snapshot(self) -> dict:
        return {"field": None if self.field is None else {
                    "magnitude_ut": self.field.magnitude_ut, "dip_rad": self.field.dip_rad,
                    "declination_rad": self.field.declination_rad},
                "guard": None if self.guard is None else self.guard.snapshot(),
                "iron": None if self.iron is None else self.iron.snapshot(),
                "status": self.status, "fused_floor_var": self._fused_floor_var,
                "iron_gain": None if self.fixed_iron is None else self.fixed_iron.snapshot()}

    @staticmethod
    def field_from(snap: dict) -> FieldReference | None:
        fld = snap.get("field")
        return None if fld is None else FieldReference(fld["magnitude_ut"], fld["dip_rad"],
                                                       fld["declination_rad"])

    def restore(self, snap: dict) -> None:
        """Resume from :meth:`snapshot` (its field is taken at construction: :meth:`field_from`)."""
        if self.guard is not None and snap.get("guard") is not None:
            self.guard.restore(snap["guard"])
        self.restore_iron(snap.get("iron"))
        if snap.get("status") in STATUS_CODE:
            self.status = snap["status"]
        floor = snap.get("fused_floor_var")
        if isinstance(floor, (int, float)) and math.isfinite(floor) and floor >= 0.0:
            self._fused_floor_var = float(floor)
        if self.fixed_iron is not None:
            self.fixed_iron.restore(snap.get("iron_gain"))

    def restore_iron(self, iron: dict | None) -> bool:
        """Start the iron's estimate from a saved one (the compass's calibration outlives the
        tracker: the chair's iron does not change when it is switched off); False where
        there is none to restore or this compass estimates none."""
        if self.iron is None or iron is None:
            return False
        self.iron.restore(iron)
        return True
