"""A joint's relative encoder made from the gyroscopes on either side of it: the degraded
mode an arm needs when an encoder fails, and how the real rig of ``docs/real-data.md`` is
tracked with its encoder withheld.

The joint's rate is the difference of the two links' angular rates about its axis
(:func:`armfusion.models.kinematics.joint_rate_from_link_rates`), each gyroscope read at the instant
its samples were true (a device's calibrated ``time_offset``: what is stamped t was true at
t - offset) and corrected as the tracker corrects it. Its integral is a relative encoder
that drifts: :func:`calibrate_gyro_encoder` measures its scale, bias and drift against the
encoder where the encoder is known (a factory calibration), :func:`with_gyro_encoder` puts
it in the encoder's place, and the tracker takes the drift as that joint's offset random
walk (``TrackerSettings.offset_random_walk_by_joint_deg_per_sqrt_s``), so gravity corrects
it where gravity sees the joint and its σ grows where it cannot.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from armfusion.fusion.identification.correction import startup_correction
from armfusion.fusion.tracking.calibrated import Readings, config_model, device_time_offsets, encoder_scales
from armfusion.fusion.tracking.settings import GYRO, TrackerSettings
from armfusion.models.arm import ArmModel
from armfusion.models.kinematics import joint_rate_from_link_rates
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.samples import Recording, Stream, link_gyro_stream

DRIFT_SPAN_S = 10.0
"""The longest span over which the integral's drift is measured (:func:`calibrate_gyro_encoder`)."""
RAD_PER_G = 1.0
"""What one g of error across a joint's accelerometer makes of the joint's angle where
gravity sees it best (the axis level, gravity across it): the most gravity can say."""
MIN_CALIBRATION_S = 10.0
"""The shortest stretch with the encoder known that a gyro encoder is calibrated on."""
RESPONSE_SPAN_S = 0.1
"""How far back what the encoder reads otherwise than the link reaches (s): a period of a
shaft's ringing down to 10 Hz, and any offset between the two clocks."""


@dataclass(frozen=True)
class GyroEncoderCalibration:
    """The gyros' joint angle against the encoder: ``angle(t) = scale · ∫rate(t) − Σₖ tapₖ ·
    tap_spacing_s · rate(t − k·tap_spacing_s) − bias · t``. The taps (``rate_taps``) are what
    the encoder reads otherwise than the link over the last :data:`RESPONSE_SPAN_S`: the
    encoder reads the shaft where it is driven and the gyros the link where they sit, and
    between the two are the shaft's own twist and ringing and the two clocks' offset (each
    part's filter delay, the logger's reading order). Causal: the stand-in at ``t`` needs no
    sample after ``t``. ``delay_s``: the taps' sum in seconds (per unit scale), how much
    later the encoder reads what the gyros' integral says.
    ``drift_deg_per_sqrt_s``: the spread of what that still leaves over ``drift_span_s``,
    per √s (the tracker's random walk for the joint): by default the time gravity takes to
    correct it (:func:`correction_span_s`);
    ``residual_deg``: its RMS over the whole stretch; ``span_s``: the stretch's length;
    ``bounded_deg``: the part of what is left that does not grow with the span (the spread of
    its changes over 40 spans from 1 s to ``DRIFT_SPAN_S`` fitted as ``2 b² + w² τ``: a bounded
    error ``b`` and a random walk ``w``), the error a gravity correction slower than a second
    cannot remove (a vibration of the joint that the gyros read otherwise than the encoder,
    or that their samples alias)."""

    joint: str
    scale: float
    bias_rad_s: float
    drift_deg_per_sqrt_s: float
    residual_deg: float
    span_s: float
    bounded_deg: float = 0.0
    delay_s: float = 0.0
    rate_taps: tuple[float, ...] = ()
    tap_spacing_s: float = 0.0
    drift_span_s: float = DRIFT_SPAN_S

    def as_dict(self) -> dict:
        return {"joint": self.joint, "scale": self.scale, "bias_deg_s": float(np.degrees(self.bias_rad_s)),
                "drift_deg_per_sqrt_s": self.drift_deg_per_sqrt_s, "residual_deg": self.residual_deg,
                "span_s": self.span_s, "bounded_deg": self.bounded_deg, "delay_s": self.delay_s,
                "rate_taps": [float(w) for w in self.rate_taps], "tap_spacing_s": self.tap_spacing_s,
                "drift_span_s": self.drift_span_s}


def _gyros(arm: ArmModel, joint: int) -> tuple[str, object, str, object]:
    """The gyroscope streams on either side of ``joint`` and their sensors: before it the
    base IMU's (joint 0) or a link gyroscope on the joint's own link, after it a link
    gyroscope on the next link."""
    name = arm.joint_names[joint]
    after = [s for s in arm.link_accelerometers if s.link == joint + 1 and s.has_link_gyro]
    if not after:
        raise ValueError(f"joint {name!r}: no link gyroscope on link {joint + 1} (after the joint) "
                         f"to make its encoder from")
    if joint == 0:
        if arm.imu is None:
            raise ValueError(f"joint {name!r}: no base IMU gyroscope (before the joint)")
        return GYRO, arm.imu, link_gyro_stream(after[0].name), after[0]
    before = [s for s in arm.link_accelerometers if s.link == joint and s.has_link_gyro]
    if not before:
        raise ValueError(f"joint {name!r}: no link gyroscope on link {joint} (before the joint) "
                         f"to make its encoder from")
    return link_gyro_stream(before[0].name), before[0], link_gyro_stream(after[0].name), after[0]


def gyro_joint_rate(arm: ArmModel, rec: Recording, joint: int, t_s: np.ndarray) -> np.ndarray:
    """The joint's rate (rad/s) at ``t_s`` from the gyroscopes on either side of it, each
    read at the instant its samples were true (its device's calibrated time offset) and,
    for the base IMU's, corrected as the tracker corrects it (the config's gyro effects)."""
    s_before, dev_before, s_after, dev_after = _gyros(arm, joint)
    models = stream_models(arm)
    model = config_model(arm)
    offsets = device_time_offsets(model)
    readings = Readings(arm, model, startup_correction(arm)) if arm.effects else None
    rates = []
    for stream, dev in ((s_before, dev_before), (s_after, dev_after)):
        st = rec.get(stream)
        if st is None or len(st) < 2:
            raise ValueError(f"joint {arm.joint_names[joint]!r}: the recording has no {stream!r} "
                             f"samples to make its encoder from")
        w = (readings.physical(stream, st.values) if readings is not None and stream == GYRO
             else models[stream].from_counts(st.values))
        w = w @ dev.R_LS.T  # the link's axes
        t_true = np.asarray(t_s, float) + offsets.get(dev.name, (0.0, 0.0))[0]
        rates.append(np.stack([np.interp(t_true, st.t_s, w[:, k]) for k in range(3)], axis=1))
    return joint_rate_from_link_rates(arm, joint, rates[0], rates[1])


def _integral(rate: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t_s))])


def encoder_angle_rad(arm: ArmModel, rec: Recording, joint: int) -> tuple[np.ndarray, np.ndarray]:
    """The encoder's times and the joint's relative angle from it (rad), the config's
    calibrated encoder scale applied as the tracker applies it."""
    enc = rec.get("enc")
    if enc is None or len(enc) < 2:
        raise ValueError("the recording has no encoder samples to calibrate the gyros' angle against")
    scale, _ = encoder_scales(arm, config_model(arm))
    return enc.t_s, enc.values[:, joint] / (arm.counts_per_rad[joint] * (1.0 + scale[joint]))


def calibrate_gyro_encoder(arm: ArmModel, rec: Recording, joint: int,
                           drift_span_s: float | None = None) -> GyroEncoderCalibration:
    """Where the encoder is known (``rec``, at least :data:`MIN_CALIBRATION_S`): the
    least-squares scale, taps and bias of the gyros' angle against the encoder's, and the drift
    that leaves over ``drift_span_s`` (default the time gravity takes to correct it,
    :func:`correction_span_s`, at most a third of the stretch and :data:`DRIFT_SPAN_S`)."""
    t, q = encoder_angle_rad(arm, rec, joint)
    span = float(t[-1] - t[0])
    if span < MIN_CALIBRATION_S:
        raise ValueError(f"a gyro encoder's calibration needs at least {MIN_CALIBRATION_S:.0f} s with "
                         f"the encoder known, got {span:.1f} s")
    rate = gyro_joint_rate(arm, rec, joint, t)
    spacing = float(np.median(np.diff(t)))
    taps = _rate_taps(rate, t, spacing, int(round(RESPONSE_SPAN_S / spacing)))
    A = np.concatenate([_integral(rate, t)[:, None], -taps, np.stack([-(t - t[0]), np.ones_like(t)], axis=1)],
                       axis=1)
    coef, *_ = np.linalg.lstsq(A, q - q[0], rcond=None)
    scale, weights, bias = float(coef[0]), coef[1:-2], float(coef[-2])
    rest = A @ coef - (q - q[0])
    longest_s = min(DRIFT_SPAN_S, span / 3.0)
    if drift_span_s is None:
        drift_span_s = correction_span_s(arm, rec, joint, rest, spacing, longest_s)
    k = max(int(round(drift_span_s / spacing)), 1)
    drift_span_s = k * spacing
    drift = float(np.degrees(np.sqrt(_walk_rad2_per_s(rest, k, spacing))))
    return GyroEncoderCalibration(arm.joint_names[joint], scale, bias, drift,
                                  float(np.degrees(np.sqrt(np.mean(rest**2)))), span,
                                  _bounded_deg(rest, t, max(drift_span_s, longest_s)),
                                  float(spacing * np.sum(weights) / scale), tuple(float(w) for w in weights),
                                  spacing, drift_span_s)


def correction_span_s(arm: ArmModel, rec: Recording, joint: int, rest_rad: np.ndarray, spacing_s: float,
                      longest_s: float) -> float:
    """The time over which gravity corrects the stand-in's drift, so the drift the tracker
    takes is the one that acts over it: a random walk ``w²`` seen through the accelerometer
    after the joint, whose one sample errs by ``σ`` (its datasheet noise and the config's
    fast error, in rad at :data:`RAD_PER_G`) every ``dt``, is corrected over ``T = √(σ² dt /
    w²)``; ``w²`` measured over ``T`` (the spread of ``rest_rad``'s changes over it),
    solved by a few rounds from ``longest_s``, between two samples and ``longest_s``."""
    _, _, _, sensor = _gyros(arm, joint)
    st = rec.get(sensor.name)
    noise_g = float(np.max(stream_models(arm)[sensor.name].noise_physical_rms()))
    sigma_rad = RAD_PER_G * float(np.hypot(noise_g, arm.calibration.accel_fast_error_g(sensor.name)))
    density = sigma_rad**2 * float(np.median(np.diff(st.t_s)))  # rad² s
    span = longest_s
    for _ in range(8):
        w2 = _walk_rad2_per_s(rest_rad, max(int(round(span / spacing_s)), 1), spacing_s)
        span = float(np.clip(np.sqrt(density / max(w2, 1e-30)), 2 * spacing_s, longest_s))
    return span


def _walk_rad2_per_s(rest_rad: np.ndarray, k: int, spacing_s: float) -> float:
    """The spread of ``rest_rad``'s changes over ``k`` samples, per second of them: the
    random walk that would spread that much (rad²/s)."""
    return float(np.var(rest_rad[k:] - rest_rad[:-k])) / (k * spacing_s)


def _rate_taps(rate: np.ndarray, t_s: np.ndarray, spacing_s: float, n_lags: int) -> np.ndarray:
    """``spacing_s · rate`` as read 0, 1, … ``n_lags`` spacings earlier, one column each (the
    first sample's before the start; between samples, across a gap too, interpolated)."""
    lags = [spacing_s * np.interp(t_s - k * spacing_s, t_s, rate) for k in range(n_lags + 1)]
    return np.stack(lags, axis=1)


def _bounded_deg(rest_rad: np.ndarray, t_s: np.ndarray, longest_s: float) -> float:
    """The bounded part of ``rest_rad`` (deg): the variance of its changes over spans τ from
    1 s to ``longest_s`` fitted (least squares, both terms ≥ 0) as ``2 b² + w² τ``."""
    dt = float(np.median(np.diff(t_s)))
    spans = np.geomspace(1.0, max(longest_s, 1.0), 40)  # many spans: a tone's period averages out
    var, tau = [], []
    for span in spans:
        k = max(int(round(span / dt)), 1)
        if k < len(rest_rad):
            var.append(float(np.var(rest_rad[k:] - rest_rad[:-k])))
            tau.append(k * dt)
    if len(var) < 2:
        return 0.0
    A = np.stack([np.full(len(tau), 2.0), np.asarray(tau)], axis=1)
    coef, *_ = np.linalg.lstsq(A, np.asarray(var), rcond=None)
    if coef[1] < 0:  # no random walk: all of it bounded
        coef = np.array([np.mean(var) / 2.0, 0.0])
    return float(np.degrees(np.sqrt(max(coef[0], 0.0))))


def with_gyro_encoder(arm: ArmModel, rec: Recording, joint: int, cal: GyroEncoderCalibration) -> Recording:
    """``rec`` with the joint's encoder counts replaced by the gyros' calibrated angle (from
    0 at the first sample: a relative encoder), in counts as the tracker reads them (its
    calibrated encoder scale undone); the other joints' counts kept."""
    enc = rec.get("enc")
    t = enc.t_s
    rate = gyro_joint_rate(arm, rec, joint, t)
    angle = cal.scale * _integral(rate, t) - cal.bias_rad_s * (t - t[0])
    if cal.rate_taps:
        taps = np.asarray(cal.rate_taps)
        angle = angle - _rate_taps(rate, t, cal.tap_spacing_s, len(taps) - 1) @ taps
    scale, _ = encoder_scales(arm, config_model(arm))
    values = np.array(enc.values, dtype=float)
    values[:, joint] = angle * arm.counts_per_rad[joint] * (1.0 + scale[joint])
    virtual = Stream(enc.name, enc.kind, t, values, enc.channels)
    return Recording({**rec.streams, enc.name: virtual}, dict(rec.meta))


def settings_with_gyro_encoder(settings: TrackerSettings | None,
                               cal: GyroEncoderCalibration) -> TrackerSettings:
    """Tracker settings whose random walk for ``cal``'s joint is the gyros' drift."""
    st = settings or TrackerSettings()
    rw = dict(st.offset_random_walk_by_joint_deg_per_sqrt_s)
    rw[cal.joint] = max(cal.drift_deg_per_sqrt_s, st.offset_random_walk_deg_per_sqrt_s)
    return replace(st, offset_random_walk_by_joint_deg_per_sqrt_s=tuple(rw.items()))
