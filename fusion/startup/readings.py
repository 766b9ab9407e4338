"""The still readings the solve works from: every sensor averaged over a still window.

:class:`StillReadings` holds each accelerometer's mean in g and the sigma of that mean (the
standard error, with the config's unmodelled-error floor). :func:`readings_from_recording`
makes them from a recording, leaving out (with an :class:`InputCheck`) a sensor whose window
is saturated or far from 1 g; :func:`readings_from_counts` from mean counts (batch tools);
:func:`check_readings` refuses readings that cannot give a number.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.fusion.startup.results import StartupInputError
from armfusion.models.arm import ArmModel
from armfusion.models.sensor_models import stream_models


@dataclass(frozen=True)
class StillReadings:
    """Averaged still readings in g, per sensor: ``mean_g (3,)`` and ``sigma_g (3,)``.

    ``sigma_g`` is the standard error of each axis's mean combined with the sensor's
    unmodelled-error floor. The IMU entry is the base accelerometer.
    """

    accel_mean_g: dict[str, np.ndarray]
    accel_sigma_g: dict[str, np.ndarray]
    imu_mean_g: np.ndarray | None
    imu_sigma_g: np.ndarray | None
    t_start_s: float = 0.0
    t_end_s: float = 0.0



@dataclass(frozen=True)
class InputCheck:
    """What was wrong with one sensor's still window, and that it was left out."""

    sensor: str
    message: str


def sensor_floor_g(arm: ArmModel, name: str) -> float:
    """The config's unmodelled error of one accelerometer, per axis in g (its own, else the
    arm's)."""
    return arm.calibration.accel_floor_g(name)


def _noise_g(model, n_samples: int, fast_error_g: float = 0.0) -> np.ndarray:
    """Standard error of a mean of ``n_samples`` counts, in g, the rounding to the values'
    resolution and the sensor's fast error beyond it (``fast_error_g``, per sample:
    ``calibration.accel_fast_error_g_per_sensor``) included."""
    return np.hypot(model.sigma_counts / np.abs(model.gain), fast_error_g) / np.sqrt(n_samples)


def readings_from_recording(
    arm: ArmModel, rec, t_start_s: float, t_end_s: float, window_s: float = 1.0,
    magnitude_range_g: tuple[float, float] = (0.8, 1.2),
) -> tuple[StillReadings, list[InputCheck]]:
    """Average every sensor over the last ``window_s`` of a still segment.

    Counts become g with each sensor's count model (``armfusion.models.sensor_models``). A sensor
    whose window holds saturated counts, or whose mean is far from 1 g in magnitude (dead,
    disconnected, or the arm was not still), is left out with a message; the others are kept.
    """
    t0 = max(t_start_s, t_end_s - window_s)
    means, sigmas, checks = {}, {}, []
    names = [m.name for m in arm.link_accelerometers] + (["imu_acc"] if arm.imu is not None else [])
    models = stream_models(arm, {nm: (rec.get(nm).rate_hz or 100.0) if rec.get(nm) is not None
                                 else 100.0 for nm in names})
    imu_m = imu_s = None
    for name in names:
        label = "imu" if name == "imu_acc" else name
        s = rec.get(name)
        if s is None:
            checks.append(InputCheck(label, (
                "imu: no accelerometer samples (imu_acc) in the recording; the base tilt rests "
                "on the link accelerometers alone") if name == "imu_acc"
                else f"{name}: no samples in the recording"))
            continue
        w = s.between(t0, t_end_s + 1e-9)
        sensor = arm.imu.name if name == "imu_acc" else name
        m, sg, msg = _average(label, w, models[name], magnitude_range_g, t0, t_end_s,
                              arm.calibration.accel_fast_error_g(sensor))
        if msg:
            checks.append(InputCheck(label, msg))
        elif name == "imu_acc":
            imu_m, imu_s = m, sg
        else:
            means[name] = m
            sigmas[name] = np.sqrt(sg**2 + sensor_floor_g(arm, name) ** 2)
    return StillReadings(means, sigmas, imu_m, imu_s, t0, t_end_s), checks


def _average(name, w, model, mag_range, t0, t1, fast_error_g: float = 0.0):
    """One sensor's window ``w`` averaged: ``(mean_g, sigma_g, None)``, or ``(None, None,
    message)`` when it is too short, saturated or far from 1 g."""
    where = f"{name} in t = {t0:.2f}..{t1:.2f} s"
    if len(w) < 3:
        return None, None, f"{where}: only {len(w)} samples; need at least 3"
    v = w.values
    lo, hi = model.counts_min, model.counts_max
    if lo is not None:
        sat = model.saturated(v)
        if sat.any():
            axis = "xyz"[int(np.argmax(sat.sum(0)))]
            return None, None, (f"{where}: axis {axis} saturated ({int(sat.sum(0).max())} of "
                                f"{len(w)} samples at the {lo:.0f}/{hi:.0f} count limit); left out")
    mean_g = model.from_counts(v.mean(0, keepdims=True))[0]
    mag = float(np.linalg.norm(mean_g))
    if not mag_range[0] <= mag <= mag_range[1]:
        return None, None, (f"{where}: reads {mag:.3f} g in magnitude while still, expected about "
                            f"1 g: a dead or disconnected sensor, or a wrong scale; left out")
    return mean_g, _noise_g(model, len(w), fast_error_g), None


def readings_from_counts(arm: ArmModel, mean_counts: dict[str, np.ndarray], n_samples: int,
                         rate_hz: float = 100.0) -> StillReadings:
    """Still readings from per-sensor mean counts over ``n_samples`` (no checks): the same
    conversion and sigmas as :func:`readings_from_recording`, for batch tools."""
    models = stream_models(arm, rate_hz)
    means, sigmas = {}, {}
    for mount in arm.link_accelerometers:
        if mount.name in mean_counts:
            mdl = models[mount.name]
            means[mount.name] = mdl.from_counts(np.asarray(mean_counts[mount.name], float)[None])[0]
            fast = arm.calibration.accel_fast_error_g(mount.name)
            sigmas[mount.name] = np.sqrt(_noise_g(mdl, n_samples, fast) ** 2
                                         + sensor_floor_g(arm, mount.name) ** 2)
    imu_m = imu_s = None
    if "imu_acc" in mean_counts and "imu_acc" in models:
        mdl = models["imu_acc"]
        imu_m = mdl.from_counts(np.asarray(mean_counts["imu_acc"], float)[None])[0]
        imu_s = _noise_g(mdl, n_samples, arm.calibration.accel_fast_error_g(arm.imu.name))
    return StillReadings(means, sigmas, imu_m, imu_s)


def check_readings(readings: StillReadings) -> None:
    """Refuse readings that cannot give a number (non-finite values), naming the sensor."""
    for name, m in readings.accel_mean_g.items():
        if not np.all(np.isfinite(m)) or not np.all(np.isfinite(readings.accel_sigma_g[name])):
            raise StartupInputError(f"{name}: reading {np.asarray(m).tolist()} is not finite")
        mag = float(np.linalg.norm(m))
        if not 0.5 <= mag <= 1.5:
            raise StartupInputError(
                f"{name}: reads {mag:.3f} g in magnitude while still, expected about 1 g")
    if readings.imu_mean_g is not None and not np.all(np.isfinite(readings.imu_mean_g)):
        raise StartupInputError(f"imu: reading {np.asarray(readings.imu_mean_g).tolist()} is not finite")
