"""Where the fake devices' readings come from: the true physical quantities at time t.

A :class:`PhysicsSource` gives, at a time ``t_s`` on the fakes' clock, in the
sensor's own axes: the specific force in g (what an accelerometer measures, +1 g
on z when z points up at rest), the angular rate in rad/s, the magnetic field in
µT and the die temperature in °C. An ADXL345 fake uses only the specific force;
the MPU-9150 fake uses all four (its magnetic field is in the MPU accelerometer's
axes: the fake AK8975 maps it into its own). The simulator feeds the fakes by
implementing this protocol; :class:`StaticPhysics` and :class:`FunctionPhysics`
cover tests.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class PhysicsSource(Protocol):
    def specific_force_g(self, t_s: float) -> np.ndarray: ...  # (3,) g

    def angular_rate_rad_s(self, t_s: float) -> np.ndarray: ...  # (3,) rad/s

    def magnetic_field_uT(self, t_s: float) -> np.ndarray: ...  # (3,) µT

    def temperature_c(self, t_s: float) -> float: ...  # °C


def _vec3(v: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"{what} must have 3 components, got shape {np.shape(v)}")
    return a


@dataclass(frozen=True)
class StaticPhysics:
    """Constant quantities: a sensor at rest, z up, in a mid-latitude field."""

    specific_force: tuple[float, float, float] = (0.0, 0.0, 1.0)  # g
    angular_rate: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad/s
    magnetic_field: tuple[float, float, float] = (20.0, 0.0, -40.0)  # µT
    temperature: float = 25.0  # °C

    def specific_force_g(self, t_s: float) -> np.ndarray:
        return _vec3(self.specific_force, "specific_force")

    def angular_rate_rad_s(self, t_s: float) -> np.ndarray:
        return _vec3(self.angular_rate, "angular_rate")

    def magnetic_field_uT(self, t_s: float) -> np.ndarray:
        return _vec3(self.magnetic_field, "magnetic_field")

    def temperature_c(self, t_s: float) -> float:
        return float(self.temperature)


class FunctionPhysics:
    """Quantities from functions of time; any left out stays at ``StaticPhysics()``."""

    def __init__(
        self,
        specific_force_g: Callable[[float], Sequence[float]] | None = None,
        angular_rate_rad_s: Callable[[float], Sequence[float]] | None = None,
        magnetic_field_uT: Callable[[float], Sequence[float]] | None = None,
        temperature_c: Callable[[float], float] | None = None,
    ):
        base = StaticPhysics()
        self._f = specific_force_g or base.specific_force_g
        self._w = angular_rate_rad_s or base.angular_rate_rad_s
        self._m = magnetic_field_uT or base.magnetic_field_uT
        self._T = temperature_c or base.temperature_c

    def specific_force_g(self, t_s: float) -> np.ndarray:
        return _vec3(self._f(t_s), "specific_force_g(t)")

    def angular_rate_rad_s(self, t_s: float) -> np.ndarray:
        return _vec3(self._w(t_s), "angular_rate_rad_s(t)")

    def magnetic_field_uT(self, t_s: float) -> np.ndarray:
        return _vec3(self._m(t_s), "magnetic_field_uT(t)")

    def temperature_c(self, t_s: float) -> float:
        return float(self._T(t_s))
