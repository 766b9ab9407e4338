"""The arm config's problems (:class:`ConfigProblem`, :class:`ConfigError`) and its cross-checks:
the checks that need several keys at once (:data:`CROSS_CHECKS`, run in turn on the parsed
mapping, each tolerant of a structurally broken file whose own keys the schema reports).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from armfusion.models.arm_config_schema import FEED_COUNTS
from armfusion.models.sensor_description import SensorDescription, describe
from armfusion.sensors.samples import clipped_repr


@dataclass(frozen=True)
class ConfigProblem:
    """One problem of a config: the file, the key, the value found there and what is wrong."""

    source: str
    key: str
    value: Any
    message: str

    def __str__(self) -> str:
        # a value is quoted short: a list of a million numbers, or what a YAML alias
        # expands to, must not become a message of megabytes
        got = "" if self.value is None else f" (got {clipped_repr(self.value, 60)})"
        return f"{self.source}: {self.key}: {self.message}{got}"


class ConfigError(ValueError):
    """Every problem found in one config, reported together."""

    def __init__(self, problems: list[ConfigProblem]):
        self.problems = problems
        n = len(problems)
        head = f"{n} problem{'s' if n != 1 else ''} in arm config"
        super().__init__(head + ":\n" + "\n".join(f"  - {p}" for p in problems))


@dataclass(frozen=True)
class _Parsed:
    """The parts of a parsed config mapping the cross-checks read: each an empty mapping (or
    None) where the file is broken there, which the schema's own checks report."""

    source: str
    data: dict
    arm: dict
    dh: dict | None
    joints: dict
    n_joints: int | None
    """From the DH table's ``alpha_deg``, else the URDF's joints; None when neither says."""
    sensors: list | None

    @classmethod
    def of(cls, data: dict, source: str, urdf_joints) -> _Parsed:
        arm = data.get("arm") if isinstance(data.get("arm"), dict) else {}
        dh = arm.get("dh") if isinstance(arm.get("dh"), dict) else None
        joints = arm.get("joints") if isinstance(arm.get("joints"), dict) else {}
        n = None
        if dh is not None and isinstance(dh.get("alpha_deg"), list):
            n = len(dh["alpha_deg"])
        elif urdf_joints is not None:
            n = len(urdf_joints)
        sensors = data.get("sensors") if isinstance(data.get("sensors"), list) else None
        return cls(source, data, arm, dh, joints, n, sensors)

    def problem(self, key: str, value: Any, message: str) -> ConfigProblem:
        """A problem of this file at ``key``."""
        return ConfigProblem(self.source, key, value, message)


def _dh_or_urdf(c: _Parsed) -> list[ConfigProblem]:
    """The arm's geometry from one of a DH table and a URDF."""
    out = []
    if c.dh is None and not c.arm.get("urdf"):
        out.append(c.problem("arm", None, "give either arm.dh (a DH table) or arm.urdf"))
    if c.dh is not None and c.arm.get("urdf"):
        out.append(c.problem("arm", "dh and urdf", "give arm.dh or arm.urdf, not both"))
    return out


def _dh_lengths(c: _Parsed) -> list[ConfigProblem]:
    """Every column of the DH table as long as ``alpha_deg``."""
    if c.dh is None or not isinstance(c.dh.get("alpha_deg"), list):
        return []
    out = []
    for key in ("a_mm", "d_mm", "offset_deg"):
        v = c.dh.get(key)
        if isinstance(v, list) and len(v) != c.n_joints:
            out.append(c.problem(f"arm.dh.{key}", v, f"has {len(v)} entries; alpha_deg has {c.n_joints}"))
    return out


def _joint_lengths(c: _Parsed) -> list[ConfigProblem]:
    """Every per-joint list (limits, encoders, names, the ready pose) one entry a joint."""
    n = c.n_joints
    if n is None:
        return []
    out = []
    for key in ("min_deg", "max_deg", "counts_per_rev", "names", "encoder_on_joint"):
        v = c.joints.get(key)
        if isinstance(v, list) and len(v) != n:
            out.append(c.problem(f"arm.joints.{key}", v, f"has {len(v)} entries; the arm has {n} joints"))
    ready = c.arm.get("ready_pose_deg")
    if isinstance(ready, list) and len(ready) != n:
        out.append(c.problem("arm.ready_pose_deg", ready,
                             f"has {len(ready)} entries; the arm has {n} joints"))
    return out


def _joint_limits(c: _Parsed) -> list[ConfigProblem]:
    """Each joint's lower limit below its upper; its range within the encoder feed's counts;
    the ready pose within the limits."""
    lo, hi = c.joints.get("min_deg"), c.joints.get("max_deg")
    if not (_numlist(lo) and _numlist(hi) and len(lo) == len(hi)):
        return []
    out = [c.problem(f"arm.joints.min_deg[{i}]", a, f"lower limit is not below the upper limit {b}")
           for i, (a, b) in enumerate(zip(lo, hi, strict=True)) if a >= b]
    cpr = c.joints.get("counts_per_rev")
    if _numlist(cpr) and len(cpr) == len(lo):
        for i, (a, b, counts) in enumerate(zip(lo, hi, cpr, strict=True)):
            if counts * (b - a) / 360.0 > FEED_COUNTS:  # relative counts: either way from power-up
                out.append(c.problem(f"arm.joints.counts_per_rev[{i}]", counts,
                                     f"the joint's {b - a:g}° are {counts * (b - a) / 360.0:.3g} counts, "
                                     f"more than the encoder feed's int32 holds either side of "
                                     f"where it powered up ({FEED_COUNTS})"))
    ready = c.arm.get("ready_pose_deg")
    if _numlist(ready) and len(ready) == len(lo):
        out += [c.problem(f"arm.ready_pose_deg[{i}]", r, f"outside joint limits [{lo[i]}, {hi[i]}] deg")
                for i, r in enumerate(ready) if not lo[i] <= r <= hi[i]]
    return out


def _bus_spot(s: dict) -> tuple | None:
    """``(kind, bus, chip select or address)``: where a sensor is wired, None where not said."""
    bus = s.get("bus")
    if not isinstance(bus, dict):
        return None
    spot = (bus.get("kind"), bus.get("bus"),
            bus.get("chip_select") if bus.get("kind") == "spi" else bus.get("address"))
    return spot if None not in spot and all(isinstance(x, str | int) for x in spot) else None


@dataclass(frozen=True)
class _Sensors:
    """The sensor list's cross-references: the first sensor on each bus spot, and for each
    sensor the one before it of the same name."""

    first_on_spot: dict[tuple, int]
    named_before: dict[int, int]

    @classmethod
    def of(cls, sensors: list) -> _Sensors:
        first_on_spot: dict[tuple, int] = {}
        named_before: dict[int, int] = {}
        last_named: dict[str, int] = {}
        for k, s in enumerate(sensors):
            if not isinstance(s, dict):
                continue
            spot = _bus_spot(s)
            if spot is not None:
                first_on_spot.setdefault(spot, k)
            name = s.get("name")
            if isinstance(name, str):
                if name in last_named:
                    named_before[k] = last_named[name]
                last_named[name] = k
        return cls(first_on_spot, named_before)


def _bus_shared(c: _Parsed, k: int, s: dict, all_: _Sensors) -> list[ConfigProblem]:
    """One device on each bus spot."""
    spot = _bus_spot(s)
    if spot is None or all_.first_on_spot[spot] == k:
        return []
    what = "chip select" if spot[0] == "spi" else "address"
    return [c.problem(f"sensors[{k}].bus", s.get("bus"),
                      f"the {spot[0].upper()} bus {spot[1]} {what} {spot[2]} is "
                      f"sensors[{all_.first_on_spot[spot]}]'s already: one device each")]


def _imu_name_on_link(c: _Parsed, k: int, s: dict, all_: _Sensors) -> list[ConfigProblem]:
    """A name starting with ``imu`` for the base IMU alone."""
    name = s.get("name")
    if isinstance(name, str) and name.startswith("imu") and _role(s) in ("link", "other"):
        return [c.problem(f"sensors[{k}].name", s["name"],
                          "a name starting with 'imu' is the base IMU's streams' (imu_acc…) "
                          "in a recording; name a sensor on a link otherwise")]
    return []


def _duplicate_name(c: _Parsed, k: int, s: dict, all_: _Sensors) -> list[ConfigProblem]:
    """Every sensor's name its own."""
    if k not in all_.named_before:
        return []
    return [c.problem(f"sensors[{k}].name", s.get("name"),
                      f"duplicate sensor name (also sensors[{all_.named_before[k]}])")]


def _link_in_range(c: _Parsed, k: int, s: dict, all_: _Sensors) -> list[ConfigProblem]:
    """A sensor's link is the base (0) or one of the arm's."""
    link = s.get("link")
    if isinstance(link, int) and c.n_joints is not None and not 0 <= link <= c.n_joints:
        return [c.problem(f"sensors[{k}].link", link, f"link index out of range: 0 (base) to {c.n_joints}")]
    return []


def _part_on_its_link(c: _Parsed, k: int, s: dict, all_: _Sensors) -> list[ConfigProblem]:
    """A magnetometer on the base only; on the base, a gyroscope or magnetometer only in an IMU."""
    desc, link = _description_or_none(s), s.get("link")
    if desc is None or not isinstance(link, int):
        return []
    out = []
    if desc.has("magnetometer") and link != 0:
        out.append(c.problem(f"sensors[{k}].link", link,
                             f"a magnetometer ({s.get('type')}) is read only as part of the "
                             "base IMU, on link 0 (the base)"))
    if link == 0 and desc.kind in ("gyroscope", "magnetometer"):
        out.append(c.problem(f"sensors[{k}].kind", desc.kind,
                             "on the base, a gyroscope or magnetometer is read as part of "
                             "an IMU (kind imu, with its accelerometer)"))
    return out


def _bus_address_given(c: _Parsed, k: int, s: dict, all_: _Sensors) -> list[ConfigProblem]:
    """An I2C device's address, an SPI device's chip select."""
    bus = s.get("bus")
    if not isinstance(bus, dict):
        return []
    out = []
    if bus.get("kind") == "i2c" and bus.get("address") is None:
        out.append(c.problem(f"sensors[{k}].bus.address", None, "an I2C device needs an address"))
    if bus.get("kind") == "spi" and bus.get("chip_select") is None:
        out.append(c.problem(f"sensors[{k}].bus.chip_select", None, "an SPI device needs a chip_select"))
    return out


SENSOR_CHECKS = (_bus_shared, _imu_name_on_link, _duplicate_name, _link_in_range, _part_on_its_link,
                 _bus_address_given)
"""The checks of one sensor against the arm and the other sensors, in the order they are said."""


def _each_sensor(c: _Parsed) -> list[ConfigProblem]:
    """:data:`SENSOR_CHECKS` on every sensor, sensor by sensor."""
    if c.sensors is None:
        return []
    all_ = _Sensors.of(c.sensors)
    return [p for k, s in enumerate(c.sensors) if isinstance(s, dict)
            for check in SENSOR_CHECKS for p in check(c, k, s, all_)]


def _sensor_roles(c: _Parsed) -> list[ConfigProblem]:
    """A link accelerometer on an arm with joints, a base IMU on one without, at most one
    base IMU; the calibration's per-sensor entries name sensors there are."""
    if c.sensors is None:
        return []
    out = []
    sensors = c.sensors
    roles = [(s.get("name"), _role(s)) for s in sensors if isinstance(s, dict)]
    accels = [nm for nm, role in roles if role == "link"]
    imus = [nm for nm, role in roles if role == "base_imu"]
    if not accels and all(role is not None for _, role in roles) and c.n_joints != 0:
        # an arm with joints needs a link accelerometer to read them; a zero-joint arm
        # (an IMU alone, docs/tracking-hand.md) needs only its base IMU
        out.append(c.problem("sensors", len(sensors), "the arm has no link accelerometer"))
    if c.n_joints == 0 and not imus and all(role is not None for _, role in roles):
        out.append(c.problem("sensors", len(sensors),
                             "an arm with no joints needs a base IMU (an imu on link 0)"))
    if len(imus) > 1:
        out.append(c.problem("sensors", ", ".join(map(str, imus)),
                             "more than one IMU on the base (link 0); the base has one"))
    cal = c.data.get("calibration")
    if isinstance(cal, dict):
        # per sensor: by the sensor's name (the IMU's too); covariances: by stream
        for key, allowed in (("accel_unmodelled_g_per_sensor", accels + imus),
                             ("accel_fast_error_g_per_sensor", accels + imus),
                             ("correction_covariance", accels + ["imu_acc"] * bool(imus))):
            given = cal.get(key)
            if isinstance(given, dict):
                out += [c.problem(f"calibration.{key}.{name}", name,
                                  "no such accelerometer in sensors (it has "
                                  f"{', '.join(map(str, allowed)) or 'none'})")
                        for name in given if name not in allowed]
    return out


CROSS_CHECKS = (_dh_or_urdf, _dh_lengths, _joint_lengths, _joint_limits, _each_sensor, _sensor_roles)
"""The checks that need several keys at once, in the order their problems are said."""


def cross_checks(data: dict, source: str, urdf_joints) -> list[ConfigProblem]:
    """Every problem :data:`CROSS_CHECKS` find in the parsed mapping ``data``; tolerant of a
    structurally broken file."""
    parsed = _Parsed.of(data, source, urdf_joints)
    return [p for check in CROSS_CHECKS for p in check(parsed)]


def _description_or_none(s: dict) -> SensorDescription | None:
    """A config sensor's description, or None where its own check will say what is wrong."""
    try:
        return describe(s.get("type"), s.get("kind"), s.get("outputs") if isinstance(s.get("outputs"), dict)
                        else None, s.get("settings") if isinstance(s.get("settings"), dict) else {})
    except (ValueError, TypeError, AttributeError):
        return None


def _role(s: dict) -> str | None:
    """``base_imu``, ``link`` (carries an accelerometer), ``other``; None when undescribable."""
    desc = _description_or_none(s)
    if desc is None:
        return None
    if desc.kind == "imu" and s.get("link") == 0:
        return "base_imu"
    return "link" if desc.has("accelerometer") else "other"


def _numlist(v) -> bool:
    """A list of finite numbers (a NaN or an infinity is said once, by the field's own check)."""
    return isinstance(v, list) and all(isinstance(x, int | float) and np.isfinite(x) for x in v)
