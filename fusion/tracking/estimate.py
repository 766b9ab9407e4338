"""What the tracker gives for one instant: :class:`Estimate`, immutable and small."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Estimate:
    """One instant's estimate: immutable, small, everything a consumer needs."""

    t_s: float
    q_rad: np.ndarray
    sigma_rad: np.ndarray
    flags: tuple[str, ...]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    attitude_sigma_rad: np.ndarray
    gyro_bias_rad_s: np.ndarray
    axis_to_vertical_deg: np.ndarray
    sensors: tuple[tuple[str, str], ...]
    magnetic_disturbance: bool = False
    magnetic_recovery: bool = False
    joint_names: tuple[str, ...] = ()

    @property
    def heading_rad(self) -> float:
        return self.yaw_rad

    @property
    def heading_sigma_rad(self) -> float:
        return float(self.attitude_sigma_rad[2])

    def sensor_status(self, name: str) -> str:
        return dict(self.sensors)[name]

    def summary(self) -> str:
        """One line for a person."""
        bad = [f"{n} {f}" for n, f in zip(self.joint_names, self.flags, strict=True) if f != "ok"]
        sens = [f"{n} {s}" for n, s in self.sensors if s != "ok"]
        worst = float(np.degrees(np.max(self.sigma_rad)))
        text = (f"t={self.t_s:.2f}s heading {np.degrees(self.yaw_rad):.1f}±"
                f"{np.degrees(self.heading_sigma_rad):.2f}°, worst joint sigma {worst:.3f}°")
        if bad:
            text += "; " + ", ".join(bad)
        if sens:
            text += "; sensors: " + ", ".join(sens)
        if self.magnetic_disturbance:
            text += "; magnetic disturbance"
        return text

    def as_dict(self) -> dict:
        return {
            "t_s": self.t_s,
            "joints": [{"name": n, "angle_rad": float(q), "sigma_rad": float(s), "flag": f,
                        "axis_to_vertical_deg": float(a)}
                       for n, q, s, f, a in zip(self.joint_names, self.q_rad, self.sigma_rad, self.flags,
                                                self.axis_to_vertical_deg, strict=True)],
            "base": {"roll_rad": self.roll_rad, "pitch_rad": self.pitch_rad, "yaw_rad": self.yaw_rad,
                     "sigma_rad": self.attitude_sigma_rad.tolist(),
                     "gyro_bias_rad_s": self.gyro_bias_rad_s.tolist()},
            "heading": {"yaw_rad": self.yaw_rad, "sigma_rad": self.heading_sigma_rad,
                        "magnetic_disturbance": self.magnetic_disturbance,
                        "magnetic_recovery": self.magnetic_recovery},
            "sensors": dict(self.sensors),
        }
