"""The units a sensor's values may arrive in, and the one conversion between them.

A sensor description (:mod:`armfusion.models.sensor_description`) declares what unit its values are
delivered in: register ``counts`` (with a scale), or a physical unit of its quantity. The
quantities and their units, each with its factor to the quantity's canonical unit (the one
armfusion computes in):

==================  =========  ===================================================
quantity            canonical  units accepted (aliases)
==================  =========  ===================================================
``acceleration``    ``g``      ``g``, ``mg``, ``m/s^2`` (``m/s2``, ``m/s²``)
``angular_rate``    ``rad/s``  ``rad/s``, ``deg/s`` (``dps``, ``°/s``)
``magnetic_field``  ``uT``     ``uT`` (``µT``), ``nT``, ``mT``, ``gauss`` (``G``)
``angle``           ``rad``    ``rad``, ``deg`` (``°``)
``temperature``     ``degC``   ``degC`` (``°C``)
``time``            ``s``      ``s``, ``ms``, ``us`` (``µs``), ``ns``
==================  =========  ===================================================

``counts`` belongs to no quantity: counts become a physical value only through a scale
(a device's LSB per unit), which the description holds.
"""

from __future__ import annotations

import math

import numpy as np

STANDARD_GRAVITY_MPS2 = 9.80665
"""1 g in m/s² (the conventional value, by definition)."""

COUNTS = "counts"

# unit -> (quantity, factor: value in this unit x factor = value in the canonical unit)
_UNITS: dict[str, tuple[str, float]] = {
    "g": ("acceleration", 1.0),
    "mg": ("acceleration", 1e-3),
    "m/s^2": ("acceleration", 1.0 / STANDARD_GRAVITY_MPS2),
    "rad/s": ("angular_rate", 1.0),
    "deg/s": ("angular_rate", math.pi / 180.0),
    "uT": ("magnetic_field", 1.0),
    "nT": ("magnetic_field", 1e-3),
    "mT": ("magnetic_field", 1e3),
    "T": ("magnetic_field", 1e6),  # tesla: ROS's sensor_msgs/MagneticField
    "gauss": ("magnetic_field", 100.0),
    "rad": ("angle", 1.0),
    "deg": ("angle", math.pi / 180.0),
    "degC": ("temperature", 1.0),
    "s": ("time", 1.0),
    "ms": ("time", 1e-3),
    "us": ("time", 1e-6),
    "ns": ("time", 1e-9),
}
_ALIASES = {"m/s2": "m/s^2", "m/s²": "m/s^2", "dps": "deg/s", "°/s": "deg/s", "µT": "uT", "μT": "uT",
            "G": "gauss", "°": "deg", "°C": "degC", "µs": "us", "μs": "us"}

CANONICAL: dict[str, str] = {"acceleration": "g", "angular_rate": "rad/s", "magnetic_field": "uT",
                             "angle": "rad", "temperature": "degC", "time": "s"}
"""Per quantity, the unit armfusion computes in."""


class UnitError(ValueError):
    """A unit that is not known, or not of the quantity asked for."""


def canonical_unit_name(unit: str) -> str:
    """``unit`` spelt the one way this module knows it (``m/s2`` -> ``m/s^2``); counts as is."""
    if not isinstance(unit, str):
        raise UnitError(f"a unit is a name such as 'g' or 'deg/s', not {type(unit).__name__}")
    u = unit.strip()
    u = _ALIASES.get(u, u)
    if u != COUNTS and u not in _UNITS:
        shown = u if len(u) <= 16 else u[:16] + "…"
        raise UnitError(f"unknown unit {shown!r}; known: {', '.join([COUNTS, *_UNITS])}")
    return u


def quantity_of(unit: str) -> str | None:
    """The quantity ``unit`` measures (None for counts)."""
    u = canonical_unit_name(unit)
    return None if u == COUNTS else _UNITS[u][0]


def units_of(quantity: str) -> tuple[str, ...]:
    """Every unit of ``quantity``, its canonical one first."""
    if quantity not in CANONICAL:
        raise UnitError(f"unknown quantity {quantity!r}; known: {', '.join(CANONICAL)}")
    rest = [u for u, (q, _) in _UNITS.items() if q == quantity and u != CANONICAL[quantity]]
    return (CANONICAL[quantity], *rest)


def factor(from_unit: str, to_unit: str) -> float:
    """The number a value in ``from_unit`` is multiplied by to be in ``to_unit`` (both of
    one quantity; counts only to counts, as 1)."""
    a, b = canonical_unit_name(from_unit), canonical_unit_name(to_unit)
    if a == COUNTS or b == COUNTS:
        if a != b:
            raise UnitError(f"cannot convert {a} to {b}: counts become a physical value only "
                            "through the device's scale (the sensor description's counts_per_unit)")
        return 1.0
    (qa, fa), (qb, fb) = _UNITS[a], _UNITS[b]
    if qa != qb:
        raise UnitError(f"cannot convert {a} ({qa}) to {b} ({qb})")
    return fa / fb


def convert(values, from_unit: str, to_unit: str) -> np.ndarray:
    """``values`` (any shape) from ``from_unit`` to ``to_unit``, as floats."""
    return np.asarray(values, dtype=float) * factor(from_unit, to_unit)
