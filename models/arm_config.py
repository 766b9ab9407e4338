"""Arm config validation: a parsed YAML mapping in, an :class:`ArmModel` out (its schema is
:mod:`armfusion.models.arm_config_schema`, its cross-checks :mod:`armfusion.models.arm_config_checks`).

Validation runs once, here, and reports every problem together, each naming the file,
the key and the bad value. File reading lives in ``armfusion.fusion.configfile`` (models do no I/O).

Units are in the key names: ``_deg``, ``_mm``. Inside the model everything is SI.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from armfusion.models.arm import (
    ArmCalibration,
    ArmModel,
    BaseMotion,
    CorrectionCovariance,
    DhTable,
    FixedBase,
    Joint,
    JointReference,
    SensorMount,
    joints_from_dh,
)
from armfusion.models.arm_config_checks import ConfigError, ConfigProblem, cross_checks
from armfusion.models.arm_config_schema import (
    COUNTS_PER_REV_RANGE,
    FEED_COUNTS,
    MAX_ANGLE_DEG,
    MAX_LENGTH_MM,
    STREAM_NAMES_TAKEN,
    ArmConfigFile,
    CalibrationSection,
    FixedBaseSection,
)
from armfusion.models.rotations import DEG
from armfusion.models.sensor_description import unmodelled_floor
from armfusion.sensors.csv_blocks import CsvLimits
from pydantic import ValidationError

__all__ = [
    "COUNTS_PER_REV_RANGE", "FEED_COUNTS", "MAX_ANGLE_DEG", "MAX_LENGTH_MM", "MAX_SENSORS",
    "STREAM_NAMES_TAKEN", "ArmConfigFile", "ConfigError", "ConfigProblem", "build_arm",
    "validate_config_dict",
]


def _loc(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


MAX_SENSORS = (CsvLimits.max_columns - 1) // 3
"""Sensors a config may hold: a recording of them fits the recording CSV's columns (``t`` and at
least three a sensor)."""


def _friendly(msg: str) -> str:
    return msg.removeprefix("Value error, ")


def validate_config_dict(
    data: Any, source: str, urdf_joints: tuple[Joint, ...] | None = None
) -> tuple[ArmConfigFile | None, list[ConfigProblem]]:
    """Structural (pydantic) and cross-field checks; returns the parsed file and problems."""
    problems: list[ConfigProblem] = []
    parsed: ArmConfigFile | None = None
    if not isinstance(data, dict):
        return None, [ConfigProblem(source, "(top level)", type(data).__name__,
                                    "an arm config is a mapping with keys arm, sensors")]
    sensors = data.get("sensors")
    if isinstance(sensors, list) and len(sensors) > MAX_SENSORS:  # (checking each would take minutes)
        return None, [ConfigProblem(source, "sensors", None, (
            f"{len(sensors)} sensors, more than a recording holds: each has at least 3 columns, and a "
            f"recording CSV at most {CsvLimits.max_columns} (so at most {MAX_SENSORS} sensors)"))]
    try:
        parsed = ArmConfigFile.model_validate(data)
    except ValidationError as e:
        for err in e.errors():
            key = _loc(err["loc"]) or "(top level)"
            value = err.get("input") if err["type"] != "missing" else None
            if err["type"] == "missing":
                problems.append(ConfigProblem(source, key, None, "required key is missing"))
            elif err["type"] == "extra_forbidden":
                problems.append(ConfigProblem(source, key, value, "unknown key"))
            else:
                problems.append(ConfigProblem(source, key, value, _friendly(err["msg"])))
    problems.extend(cross_checks(data, source, urdf_joints))
    return parsed, problems


def build_arm(
    data: Any, source: str, urdf_joints: tuple[Joint, ...] | None = None
) -> ArmModel:
    """Validate a parsed config mapping and build the arm model (raises :class:`ConfigError`)."""
    parsed, problems = validate_config_dict(data, source, urdf_joints)
    if problems or parsed is None:
        raise ConfigError(problems)
    arm = parsed.arm
    js = arm.joints
    dh_table = None
    if arm.dh is not None:
        n = len(arm.dh.alpha_deg)
        names = js.names or [f"j{i + 1}" for i in range(n)]
        offset = np.array(arm.dh.offset_deg or [0.0] * n) * DEG
        alpha = np.array(arm.dh.alpha_deg) * DEG
        a_m = np.array(arm.dh.a_mm) / 1000.0
        d_m = np.array(arm.dh.d_mm) / 1000.0
        dh_table = DhTable(arm.dh.convention, alpha, a_m, d_m, offset)
        joints = joints_from_dh(dh_table, names, np.array(js.min_deg) * DEG, np.array(js.max_deg) * DEG,
                                np.array(js.counts_per_rev))
    else:
        assert urdf_joints is not None
        names = js.names or [j.name for j in urdf_joints]
        joints = tuple(
            Joint(
                name=names[i], R_pre=j.R_pre, p_pre_m=j.p_pre_m, axis=j.axis, R_post=j.R_post,
                p_post_m=j.p_post_m, offset_rad=0.0, min_rad=js.min_deg[i] * DEG,
                max_rad=js.max_deg[i] * DEG, counts_per_rev=js.counts_per_rev[i],
            )
            for i, j in enumerate(urdf_joints)
        )
    if js.encoder_on_joint is not None:
        joints = tuple(replace(j, encoder_on_joint=bool(on))
                       for j, on in zip(joints, js.encoder_on_joint, strict=True))
    sensors = tuple(
        SensorMount(
            name=s.name, type=s.type, link=s.link,
            R_LS=_ro(np.array(s.rotation, dtype=float)),
            p_L_m=_ro(np.array(s.position_mm, dtype=float) / 1000.0),
            bus=s.bus.model_dump() if s.bus else {}, settings=dict(s.settings), description=s.description(),
        )
        for s in parsed.sensors
    )
    return ArmModel(
        name=arm.name, joints=joints, sensors=sensors,
        ready_pose_rad=_ro(np.array(arm.ready_pose_deg) * DEG), dh=dh_table, source=source,
        effects=tuple(parsed.effects),
        calibration=_calibration(parsed.calibration, sensors),
        base_motion=(None if parsed.base_motion is None else
                     BaseMotion(parsed.base_motion.accel_sigma_mps2, parsed.base_motion.accel_tau_s,
                                parsed.base_motion.speed_sigma_mps, parsed.base_motion.pivot_sigma_m,
                                parsed.base_motion.turns_about)),
        magnetic_declination_deg=(None if parsed.site is None else parsed.site.magnetic_declination_deg),
        base_from_turning_centre_m=(
            None if parsed.chair is None
            else _ro(np.array(parsed.chair.base_from_turning_centre_mm, dtype=float) / 1000.0)),
        fixed_base=_fixed_base(parsed.base),
    )


def _fixed_base(section: FixedBaseSection | None) -> FixedBase | None:
    if section is None:
        return None
    given = section.roll_deg is not None
    sigma_deg = section.tilt_sigma_deg or (LEVELLED_TILT_SIGMA_DEG if given else LEVEL_AS_BUILT_SIGMA_DEG)
    return FixedBase(roll_rad=section.roll_deg * DEG if given else None,
                     pitch_rad=section.pitch_deg * DEG if given else None,
                     tilt_sigma_rad=sigma_deg * DEG)


LEVELLED_TILT_SIGMA_DEG = 0.1
"""A bolted base's tilt read with an installer's level (a machinist's level: 0.1°), 1 sigma."""
LEVEL_AS_BUILT_SIGMA_DEG = 1.0
"""A bolted base's tilt from level where no level was read: a floor or a table as built
(within about a degree), 1 sigma."""


def _default_floors(section: CalibrationSection, sensors: tuple[SensorMount, ...]) -> tuple[dict, dict]:
    """The unmodelled-error floors the block does not give, each sensor's datasheet-typical
    one (:data:`armfusion.models.sensor_description.UNMODELLED_FLOOR`): ``({key: value}, {key: where
    from})``, keys a link accelerometer's name, ``imu_acc``, ``imu_mag``. A floor the block
    gives, even 0 (sensors as exact as modelled), is never replaced."""
    values: dict[str, float] = {}
    said: dict[str, str] = {}
    given = section.accel_unmodelled_g_per_sensor or {}
    for s in sensors:
        if s.is_link_accelerometer and section.accel_unmodelled_g is None and s.name not in given:
            values[s.name] = unmodelled_floor(s.description.device, "accelerometer")
            said[s.name] = f"{s.description.device} accelerometer, {values[s.name]:g} g"
        if s.is_base_imu:
            if section.accel_unmodelled_g is None and section.imu_accel_unmodelled_g is None \
                    and s.name not in given:
                values["imu_acc"] = unmodelled_floor(s.description.device, "accelerometer")
                said["imu_acc"] = f"{s.description.device} accelerometer, {values['imu_acc']:g} g"
            if s.description.has("magnetometer") and section.mag_unmodelled_ut is None:
                values["imu_mag"] = unmodelled_floor(s.description.device, "magnetometer")
                said["imu_mag"] = f"{s.description.device} magnetometer, {values['imu_mag']:g} uT"
    return values, said


def _calibration(section: CalibrationSection, sensors: tuple[SensorMount, ...] = ()) -> ArmCalibration:
    """The validated ``calibration:`` block as the typed object the estimators read, each
    floor it does not give the sensor's datasheet-typical one (:func:`_default_floors`)."""
    identified = section.identified
    defaults, said = _default_floors(section, sensors)
    per_sensor = dict(section.accel_unmodelled_g_per_sensor or {})
    per_sensor.update({k: v for k, v in defaults.items() if k not in ("imu_acc", "imu_mag")})
    return ArmCalibration(
        accel_unmodelled_g=float(section.accel_unmodelled_g or 0.0),
        accel_unmodelled_g_per_sensor=per_sensor,
        accel_fast_error_g_per_sensor=dict(section.accel_fast_error_g_per_sensor or {}),
        imu_accel_unmodelled_g=defaults.get("imu_acc", section.imu_accel_unmodelled_g),
        mag_unmodelled_ut=float(defaults.get("imu_mag", section.mag_unmodelled_ut or 0.0)),
        floors_by_default=said,
        gyro_scale_unmodelled=(None if section.gyro_scale_unmodelled is None
                               else float(section.gyro_scale_unmodelled)),
        correction_covariance={
            stream: CorrectionCovariance(tuple(c.elements), _ro(np.array(c.matrix, dtype=float)))
            for stream, c in (section.correction_covariance or {}).items()},
        references=tuple(JointReference(r.joint, r.angle_deg, r.sigma_deg, r.where)
                         for r in (identified.references if identified else ())),
        joint_zero_conventions=tuple(identified.joint_zero_conventions if identified else ()),
    )


def _ro(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a
