"""A sensor part's declared delay (``delay_s`` in its description: a filter's group delay, or
half a period for a part that delivers its period's mean): refused when it is no delay, drawn
by the simulator, and made up for by the tracker, which turns the attitude over each
interval by the gyro rate at the interval's midpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from fusion.configfile import load_arm
from fusion.tracking.process import gyro_newer_weight
from fusion.tracking.start import delay_notes
from models.arm_config import ConfigError
from models.simulator import simulate
from tests.fusion.test_base_pivot import _swung_trial
from tests.fusion.test_base_velocity import _inclination_rmse_deg


def _config_with_gyro_delay(tmp_path: Path, base: str, delay_s, name: str = "c.yaml") -> Path:
    cfg = yaml.safe_load(Path(load_arm(base).source).read_text())
    imu = next(s for s in cfg["sensors"] if s["link"] == 0)
    imu.setdefault("outputs", {}).setdefault("gyroscope", {})["delay_s"] = delay_s
    out = tmp_path / name
    out.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return out


def test_the_newer_sample_s_weight_follows_the_delay():
    assert gyro_newer_weight(0.0, 100.0) == 0.5  # instantaneous samples: the midpoint rule
    assert gyro_newer_weight(0.0025, 200.0) == 1.0  # a period's mean: the newer sample alone
    assert gyro_newer_weight(0.0048, 100.0) == pytest.approx(0.98)  # an MPU-9150 at DLPF 3
    assert gyro_newer_weight(0.02, 100.0) == 1.0  # beyond half a period: capped


@pytest.mark.parametrize("delay", [-0.001, 1.5, True, "2 ms"])
def test_a_delay_that_is_no_filter_s_is_refused_naming_the_key(tmp_path, delay):
    with pytest.raises(ConfigError, match=r"outputs\.gyroscope\.delay_s: seconds, >= 0 and below 1"):
        load_arm(_config_with_gyro_delay(tmp_path, "wmra", delay))


def test_the_simulator_draws_the_declared_delay(tmp_path):
    delayed = load_arm(_config_with_gyro_delay(tmp_path, "wmra", 0.005))
    plain = load_arm("wmra")
    a, _ = simulate(delayed, "daily-use", 40.0, seed=2, noise=False)
    b, _ = simulate(plain, "daily-use", 40.0, seed=2, noise=False)
    ga, gb = a.get("imu_gyro"), b.get("imu_gyro")
    # half a sample late: the delayed stream is the plain one read 5 ms earlier (between
    # samples, within the counts' rounding); the other streams are unchanged
    mid = 0.5 * (gb.values[1:].astype(float) + gb.values[:-1].astype(float))
    moving = np.abs(np.diff(gb.values.astype(float), axis=0)).max(1) > 20  # turning, counts
    assert moving.sum() > 100
    err_delayed = np.abs(ga.values[1:][moving] - mid[moving]).max()
    err_plain = np.abs(gb.values[1:][moving] - mid[moving]).max()
    assert err_delayed <= 2.0 < err_plain
    assert np.array_equal(a.get("imu_acc").values, b.get("imu_acc").values)
    notes = delay_notes(delayed)
    assert notes == ["the gyroscope's delay (5 ms) made up for (up to half a sample period): the attitude "
                     "turns by the rate at each interval's midpoint"]


def test_a_gyro_that_delivers_period_means_keeps_the_tilt_only_when_its_delay_is_declared(tmp_path):
    # at 200 Hz, each gyro sample the rate half a period (2.5 ms) before its stamp: what a
    # part that delivers its period's mean reads (measured 0.34 deg declared, 0.75 not)
    trial = _swung_trial(tmp_path / "means.hdf5", gyro_delay_s=0.0025)
    declared = _config_with_gyro_delay(tmp_path, "broad_imu", 0.0025, "declared.yaml")
    instant = _config_with_gyro_delay(tmp_path, "broad_imu", 0.0, "instant.yaml")
    with_delay = _inclination_rmse_deg(declared, trial, 13.0)
    without = _inclination_rmse_deg(instant, trial, 13.0)
    assert with_delay < 0.7 * without, (with_delay, without)
