"""A hand is not a chair: it moves calmly, then vigorously (the tracker follows how vigorously,
:class:`armfusion.fusion.tracking.process.MotionIntensity`), and it turns what it holds about every
axis (``base_motion.turns_about: any``: every gyro axis's scale error is the tilt's noise,
not a state about the vertical). A chair's tracker is left as it was."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.filter import Tracker
from armfusion.fusion.tracking.process import MotionIntensity
from armfusion.fusion.tracking.settings import G, TrackerSettings
from armfusion.models.arm_config import ConfigError


def _hand_settings() -> TrackerSettings:
    return TrackerSettings().for_base(load_arm("broad_imu").base_motion)


def _readings_g(rng: np.random.Generator, accel_sigma_mps2: float, n: int) -> np.ndarray:
    """A sensor held level while a hand accelerates it by ``accel_sigma_mps2`` along a stroke
    whose direction changes (each axis in turn), in g."""
    a = np.zeros((n, 3))
    axis = (np.arange(n) // 50) % 3
    a[np.arange(n), axis] = rng.normal(0.0, accel_sigma_mps2, n)
    return (a + [0.0, 0.0, G]) / G


def test_the_motion_intensity_follows_a_calm_hand_then_a_vigorous_one() -> None:
    st = _hand_settings()
    intensity = MotionIntensity(st)
    assert intensity.k == 1.0  # the config's own hand until it reads otherwise
    rng = np.random.default_rng(3)
    dt = 1.0 / 285.714
    for f in _readings_g(rng, 0.5, 3000):  # 10 s of a calm hand: 0.5 m/s² along its stroke
        intensity.update(dt, f)
    calm = intensity.k
    for f in _readings_g(rng, 8.0, 3000):  # then 10 s of a vigorous one: 8 m/s²
        intensity.update(dt, f)
    vigorous = intensity.k
    # the whole magnitude's spread on each axis: k² = sqrt(3 m) / 3 m/s², where ‖f‖ - g shows
    # the stroke along gravity one time in three: sqrt(3 · 0.5² / 3) = 0.5 → k² 0.17 (k 0.41);
    # 8 → k² 2.7 (k 1.6)
    assert calm == pytest.approx(np.sqrt(0.5 / 3.0), rel=0.15)
    assert vigorous == pytest.approx(np.sqrt(8.0 / 3.0), rel=0.15)
    # a still sensor reads no motion: held at the range's calm end, not at zero
    for _ in range(3000):
        intensity.update(dt, np.array([0.0, 0.0, 1.0]))
    assert intensity.k == pytest.approx(np.sqrt(st.base_intensity_range[0]))
    # a reading that is not a number changes nothing
    k = intensity.k
    assert intensity.update(dt, np.array([np.nan, 0.0, 1.0])) == k


def test_a_faster_motion_has_a_wider_faster_acceleration_and_its_process_noise_says_so() -> None:
    tr = Tracker(load_arm("broad_imu"))
    process, L = tr.process, tr.layout
    dt = 0.0035
    nominal = process.Q(dt, True, False)[L.accel, L.accel].diagonal().copy()
    tr.intensity.k = 2.0
    faster = process.Q(dt, True, False)[L.accel, L.accel].diagonal()
    # spread k² σ_a over τ_a / k: the noise per step k⁴ (1 - e^(-2 dt k / τ)) / (1 - e^(-2 dt / τ))
    tau = tr.settings.base_accel_tau_s
    want = 16.0 * (-np.expm1(-4.0 * dt / tau)) / (-np.expm1(-2.0 * dt / tau))
    np.testing.assert_allclose(faster / nominal, want, rtol=1e-12)
    assert process.accel_sigma_mps2 == pytest.approx(4.0 * tr.settings.base_accel_sigma_mps2)


def test_a_hand_that_turns_about_every_axis_has_its_gyro_scale_error_as_attitude_noise() -> None:
    arm = load_arm("broad_imu")
    assert arm.base_motion.turns_about == "any" and arm.calibration.gyro_scale_unmodelled == 0.003
    tr = Tracker(arm)
    L = tr.layout
    assert L.scale < 0  # no scale state about the vertical: a hand has no vertical it turns about
    dt = 0.0035
    still = tr.process.Q(dt, True, False)
    turning = tr.process.Q(dt, True, False, rate_sq=np.radians(300.0) ** 2)
    extra = np.diag(turning - still)
    # roll, pitch and yaw: σ_s² |ω|² τ dt, 0.3 % at 300 °/s over the hand's 0.3 s
    want = 0.003**2 * np.radians(300.0) ** 2 * tr.settings.base_accel_tau_s * dt
    np.testing.assert_allclose(extra[[L.roll, L.pitch, L.yaw]], want, rtol=1e-12)
    assert np.count_nonzero(extra) == 3


def test_a_chair_keeps_its_scale_state_its_fixed_motion_and_no_tilt_noise_from_its_turns() -> None:
    tr = Tracker(load_arm("wmra"))
    assert tr.intensity is None and tr.layout.scale >= 0
    dt = 0.01
    np.testing.assert_array_equal(tr.process.Q(dt, True, False, rate_sq=1.0), tr.process.Q(dt, True, False))


@pytest.mark.parametrize(("section", "key", "value"), [
    ("base_motion", "turns_about", "sideways"),
    ("calibration", "gyro_scale_unmodelled", -0.01),
    ("calibration", "gyro_scale_unmodelled", 0.9),
])
def test_a_bad_hand_setting_is_refused_by_its_key(tmp_path: Path, section: str, key: str, value) -> None:
    cfg = yaml.safe_load(Path(load_arm("broad_imu").source).read_text())
    cfg[section][key] = value
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with pytest.raises(ConfigError) as e:
        load_arm(path)
    assert f"{section}.{key}" in str(e.value)
