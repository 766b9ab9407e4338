"""What a calibrated config's effects tell the tracker, read through the effects' own model
(:class:`armfusion.models.effects.Model`, built from the config's ``effects:`` list), and the
readings those effects correct: counts to SI units with the calibrated sensor errors
undone at the temperature the IMU reads (:class:`Readings`).

Where the tracker needs an effect's uncertainty (an encoder scale's, a time offset's, a
hard iron's), it is the model's prior sigma of that block: the sigma the config states,
else the effect's datasheet-typical one (the prior a refit would start from).
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
from armfusion.fusion.calibration import AffineMap, Calibration
from armfusion.fusion.tracking.settings import GYRO, IMU_ACC, MAG
from armfusion.models.arm import ArmModel
from armfusion.models.effects import JointEffect, Model, model_from_arm
from armfusion.models.effects.library import (
    EncoderScale,
    GyroScale,
    MagHardIron,
    MotionAcceleration,
    TimeOffset,
)
from armfusion.models.rotations import up_from_tilt
from armfusion.models.sensor_models import StreamModel, stream_models


def config_model(arm: ArmModel) -> Model | None:
    """The model of ``arm``'s config effects; None when it has none."""
    return model_from_arm(arm) if arm.effects else None


def effect_blocks(model: Model | None, effect: str):
    """``(effect object, value, sigma)`` of every entry of ``effect`` in ``model`` (flat arrays).
    ``effect`` is an effect class's own ``name`` (``GyroScale.name``), never a copy of it."""
    if model is None:
        return
    values = model.unpack()
    for e, b in zip(model.effects, model.blocks, strict=True):
        if e.name == effect:
            yield e, np.ravel(values[e.block_name]), np.ravel(b.prior_sigma)


def has_effect(model: Model | None, effect: str) -> bool:
    return any(True for _ in effect_blocks(model, effect))


def encoder_scales(arm: ArmModel, model: Model | None) -> tuple[np.ndarray, np.ndarray]:
    """Per joint, the config's encoder scale error (``encoder_scale``: the encoder gives
    ``1 + s`` times the counts the config's counts per revolution say) and its sigma (0
    where the config has none)."""
    s, sig = np.zeros(arm.n_joints), np.zeros(arm.n_joints)
    for e, value, sigma in effect_blocks(model, EncoderScale.name):
        if e.target in arm.joint_names:
            j = arm.joint_names.index(e.target)
            s[j], sig[j] = float(value[0]), float(sigma[0])
    return s, sig


def device_time_offsets(model: Model | None) -> dict[str, tuple[float, float]]:
    """Per device, the config's calibrated time offset (s: its samples stamped late by it,
    ``time_offset``: what is stamped t was true at t - offset) and its σ (s). Every stream
    of the device (a link sensor's accelerometer and gyroscope, the IMU's parts) shares it."""
    return {e.target: (float(value[0]), float(sigma[0]))
            for e, value, sigma in effect_blocks(model, TimeOffset.name)}


def part_delays_s(arm: ArmModel, streams) -> np.ndarray:
    """Per stream, its part's delay (s; its description's ``delay_s``, 0 where none): a
    reading stamped ``t`` is the quantity at ``t - delay``."""
    models = stream_models(arm)
    return np.array([models[s].delay_s if s in models else 0.0 for s in streams], dtype=float)


class StampOffsets(NamedTuple):
    """Per accelerometer, how late its reading is stamped and how well that is known."""

    offset_s: np.ndarray | None
    """How late each reading is stamped (s), ``(S,)``; None when no stamp is off."""
    var_s2: np.ndarray | None
    """The offset's variance (s²), ``(S,)``; None alike."""


def stamp_offsets(model: Model | None, accel_names,
                  delays_s: np.ndarray | None = None) -> StampOffsets:
    """Per accelerometer, how late its reading is stamped (s): the config's calibrated time
    offset (:func:`device_time_offsets`) plus its part's own delay ``delays_s`` (both read
    alike: the reading stands for the quantity that much before its stamp), and the
    offset's variance (s²). ``None`` when there is neither."""
    offsets = device_time_offsets(model)
    off = np.array([offsets.get(nm, (0.0, 0.0))[0] for nm in accel_names])
    if delays_s is not None:
        off = off + np.asarray(delays_s, float)
    var = np.array([offsets.get(nm, (0.0, 0.0))[1] ** 2 for nm in accel_names])
    if not off.any() and not var.any():
        return StampOffsets(None, None)
    return StampOffsets(off, var)


def with_lever_arms(arm: ArmModel, model: Model | None) -> ArmModel:
    """The arm with each sensor where its config's calibrated lever arm puts it (the
    ``motion_acceleration`` effects: an offset in the link's axes), so that the motion the
    tracker predicts at a sensor (centripetal, tangential) is at the right point."""
    shift = {e.target: value for e, value, _ in effect_blocks(model, MotionAcceleration.name)
             if e.target and value.shape == (3,) and np.any(value)}
    if not shift:
        return arm
    sensors = tuple(replace(s, p_L_m=np.asarray(s.p_L_m, float) + shift[s.name]) if s.name in shift else s
                    for s in arm.sensors)
    return replace(arm, sensors=sensors)


def hard_iron_sigma_ut(model: Model | None) -> np.ndarray | None:
    """The sigma (µT, per compass axis) of the config's ``mag_hard_iron``; None without one."""
    for _, _, sigma in effect_blocks(model, MagHardIron.name):
        return sigma
    return None


def heading_scale_sigma(arm: ArmModel, model: Model | None, default: float, any_axis: bool = False) -> float:
    """The sigma (fraction) of the gyro's scale about the base's vertical (``any_axis``: of
    any one of its axes, for a base that turns about every axis): the config's
    ``gyro_scale`` sigmas turned into the base's axes (``any_axis``: their rms), else the
    config's ``calibration.gyro_scale_unmodelled``, else ``default`` (the datasheet's) where
    the config says its IMU is not exact (its unmodelled error above zero), else 0."""
    if arm.imu is None:
        return default
    for _, _, sigma in effect_blocks(model, GyroScale.name):
        if any_axis:
            return float(np.sqrt(np.mean(np.asarray(sigma, float) ** 2)))
        return float(np.sqrt(np.sum((np.asarray(arm.imu.R_LS)[2] * sigma) ** 2)))
    own = arm.calibration.gyro_scale_unmodelled
    if own is not None:
        return float(own)
    return default if arm.calibration.imu_accel_floor_g > 0.0 else 0.0


def undo_map(correction: Calibration | None, stream: str) -> AffineMap | None:
    """The map that undoes ``correction``'s calibrated errors of ``stream``, ``(A, c)``
    (:meth:`armfusion.fusion.calibration.Calibration.undo_map`); None without a correction."""
    return None if correction is None else correction.undo_map(stream)


class Readings:
    """Counts to SI units per stream, the calibration's sensor errors (affine: mount, axes,
    scale, bias; the offset's temperature drift) undone at the temperature the IMU last read
    (:meth:`armfusion.fusion.calibration.Calibration.ideal`)."""

    def __init__(self, arm: ArmModel, model: Model | None, correction: Calibration | None):
        self.arm = arm
        self.calibration = correction
        """The config's calibration; None: readings are taken as they are."""
        self.temperature_ref_c = float(correction.temperature_c) if correction is not None else 25.0
        self.temperature_c = self.temperature_ref_c
        """The latest temperature the IMU read, °C."""
        self.models: dict[str, StreamModel] = stream_models(arm)

    @property
    def drifts_with_temperature(self) -> bool:
        """Whether any stream's correction depends on the temperature."""
        return self.calibration is not None and self.calibration.drifts_with_temperature

    def set_rates(self, rates_hz: dict[str, float]) -> None:
        """Each stream's model at its rate (which sets its datasheet noise)."""
        self.models = stream_models(self.arm, rates_hz)

    def physical(self, s: str, counts: np.ndarray, temperature_c=None) -> np.ndarray:
        """Counts ``(N, k)`` to SI units, the calibrated errors undone at ``temperature_c``
        (scalar or ``(N,)``, °C; default the latest the IMU read)."""
        y = self.models[s].from_counts(counts)
        if self.calibration is None:
            return y
        return self.calibration.ideal(s, y, self.temperature_c if temperature_c is None else temperature_c)


def joint_effects(correction) -> list:
    """The correction's joint effects with their values, ``(effect, parameters)`` in the
    model's order: they turn the controller's joint angles into the geometric ones."""
    if correction is None:
        return []
    th = correction.model.unpack()
    return [(e, th[e.block_name]) for e in correction.model.effects if isinstance(e, JointEffect)]


def spread_maps(correction) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Per accelerometer stream, the correction's spreads (every calibrated element moved by
    its sigma along a principal direction) as the maps ``(M, c)`` that undo them; the
    compass's doubt is :func:`armfusion.fusion.tracking.compass.compass_unmodelled_ut` instead."""
    if correction is None:
        return {}
    return {stream: [(np.linalg.inv(L1), np.asarray(c1, float)) for L1, c1 in maps]
            for stream, maps in correction.spread.items() if stream not in (MAG, GYRO)}


def accel_floors_g(arm: ArmModel, link_names, has_imu: bool) -> np.ndarray:
    """Per accelerometer stream (the link ones, then the IMU's), the config's unmodelled
    error in g, as the startup uses it; the IMU's is carried by its bias state instead (0)."""
    return np.array([arm.calibration.accel_floor_g(nm) for nm in link_names] + [0.0] * has_imu)


def accel_fast_errors_g(arm: ArmModel, link_names, has_imu: bool) -> np.ndarray:
    """Per accelerometer stream (the link ones, then the IMU's), the config's fast error
    beyond the datasheet noise in g (vibration: it joins each reading's noise, and only
    there; what stays is :func:`accel_floors_g`'s)."""
    cal = arm.calibration
    imu = [cal.accel_fast_error_g(arm.imu.name)] if has_imu and arm.imu is not None else [0.0] * has_imu
    return np.array([cal.accel_fast_error_g(nm) for nm in link_names] + imu)


def imu_bias_prior_var(arm: ArmModel, correction, R_0I: np.ndarray | None, roll_rad: float,
                       pitch_rad: float) -> np.ndarray:
    """Prior variance (g²) of what the IMU accelerometer's correction leaves, per IMU axis,
    at the still reading of the startup's tilt: a calibrated config's correction spread
    there, given the calibration's joint-zero conventions (the tracker keeps the convention
    its zeros were fitted in: the convention's own σ is the absolute zero's, reported with
    every joint through the consider sensitivity, never a freedom for the tilt to wander
    in), else the config's unmodelled-error floor (its statement of how far its sensors are
    from their model). ``R_0I``: the IMU's axes in the base's; None without an IMU."""
    if R_0I is None:
        return np.full(3, 1e-12)
    m = R_0I.T @ up_from_tilt(roll_rad, pitch_rad)
    if correction is not None and correction.spread.get(IMU_ACC):
        y0 = correction.readings_one(IMU_ACC, m)
        var = np.zeros(3)
        for L1, c1 in correction.spread_given_conventions.get(IMU_ACC, ()):
            var += (np.linalg.solve(L1, m - c1) - y0) ** 2
        return np.maximum(var, 1e-12)
    return np.full(3, max(arm.calibration.imu_accel_floor_g, 1e-6) ** 2)
