"""What the heading holds of an iron fixed in the compass that nothing estimates (the config's
own word for it: its hard iron's σ, else ``calibration.mag_unmodelled_ut``).

Such an iron ``b`` (compass axes) errs a heading read from the compass by ``g · b``, with
``g = d ψ / d b`` its row at that attitude, which turns with the sensor. The filter's heading
is a gain-weighted mean of the headings it fused, so its iron error is ``s · b`` with
``s ← (1 − K) s + K g`` at each fused heading (``K = 1 − R / S``: how far the filter moved to
it), and its variance ``Σ (σ_k s_k)²``: at one attitude all of the iron, less as the sensor
turns and the iron's errors average.
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.fusion.tracking.calibrated import hard_iron_sigma_ut
from armfusion.models.arm import ArmModel
from armfusion.models.effects import Model


def iron_axes_ut(arm: ArmModel, model: Model | None) -> np.ndarray:
    """The σ per compass axis (µT) of the iron the config leaves in its readings: its hard
    iron's, else ``calibration.mag_unmodelled_ut`` on every axis."""
    s = hard_iron_sigma_ut(model)
    if s is not None:
        return np.asarray(s, float)[:3]
    return np.full(3, float(arm.calibration.mag_unmodelled_ut))


class FixedIron:
    """The heading's share of a fixed iron of σ ``sigma_ut`` per compass axis (µT), followed
    through the fused headings (the module's docstring)."""

    def __init__(self, sigma_ut: np.ndarray):
        self.sigma_ut = np.asarray(sigma_ut, float)
        self.gain: np.ndarray | None = None
        """``s``: the heading's iron error is ``s · b`` (rad per µT); None before a heading."""
        self._row: np.ndarray | None = None  # d psi / d b of the last prepared reading

    def read(self, h: np.ndarray, T: np.ndarray) -> None:
        """A reading prepared: its tilt-compensated horizontal field ``h`` (µT) and ``T`` the
        turn from compass axes to the frame ``h`` is in."""
        n2 = max(h[0] ** 2 + h[1] ** 2, 1e-12)
        self._row = np.array([h[1], -h[0], 0.0]) / n2 @ T  # d psi / d b (sign aside)

    def fused(self, R: float, S: float) -> None:
        """The last prepared reading's heading fused, its measurement variance ``R`` and the
        innovation's ``S`` (rad²). The first stands for the startup's heading too (it read the
        compass at the still start, the gain all its own)."""
        g = self._row
        if g is None:
            return
        if self.gain is None:
            self.gain = g.copy()
            return
        K = min(max(1.0 - R / S, 0.0), 1.0) if S > 0.0 else 0.0
        self.gain = (1.0 - K) * self.gain + K * g

    def var_rad2(self) -> float | None:
        """The heading's variance from the iron (rad²); None before a heading was fused."""
        if self.gain is None:
            return None
        return min(float(np.sum((self.sigma_ut * self.gain) ** 2)), math.pi**2)

    def snapshot(self) -> list | None:
        return None if self.gain is None else self.gain.tolist()

    def restore(self, gain) -> None:
        if isinstance(gain, list) and len(gain) == 3:
            g = np.asarray(gain, float)
            if np.all(np.isfinite(g)):
                self.gain = g
