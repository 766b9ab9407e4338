"""The heading of a hand-held IMU through fast turns (the ``broad_imu`` config, through
``import`` and the IMU-only track, as the BROAD benchmark runs it): a gyro whose scale and
axes are off by the fraction the config allows turns the heading wrong by that fraction of
every turn. The heading's sigma grows with the turn (``σ_s |ω|``, as the tilt's does), so
the heading stays within it, and the compass, heard more as the gyro's doubt grows, keeps
the heading near the truth through the turns and at the rest after them. A compass that
reads the field later than the gyro reads the turn (the config's ``delay_s`` for each) is
turned to its stamp by the turn over the difference; read as if it were the gyro's, it is
a heading off by the turn rate times the difference, many degrees at these rates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from armfusion.models.rotations import GRAVITY_MPS2, exp_so3

from tests.fusion.test_base_velocity import broad_delays_s, turned_back, turned_by, write_broad_trial
from tools.bench_heading_broad import (
    CONFIG,
    config_with_compass_delay,
    errors_rad,
    read_trial,
    run_armfusion,
    sensor_delays_s,
)

EARTH_ENU_UT = np.array([0.0, 16.0, -40.0])
GYRO_ERROR = np.array([[0.006, 0.002, -0.002], [-0.001, -0.005, 0.002], [0.002, -0.002, 0.006]])
"""The gyro's scale (diagonal) and axes (off-diagonal) error: about twice the config's 0.3 %
per axis, a part at the edge of what the config says of it."""


def _fast_trial(path: Path, seed: int = 7, rate_hz: float = 100.0, still_s: float = 3.0,
                turning_s: float = 16.0, rest_s: float = 14.0) -> Path:
    """A BROAD-format trial: an IMU still, then turned by hand at 300-700 deg/s about a
    wandering axis (mostly one way about its own z), then resting; its compass reads Earth's
    field plus noise (no iron); its gyro is off by :data:`GYRO_ERROR`, with a constant bias
    and white noise; every sensor late by the config's delay for it. Reference exact."""
    rng = np.random.default_rng(seed)
    n = int((still_s + turning_s + rest_s) * rate_hz)
    t = np.arange(n) / rate_hz
    f = rng.uniform(0.4, 0.9, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)

    def omega(tt: float) -> np.ndarray:  # body axes, rad/s
        s = tt - still_s
        on = min(max(s, 0.0), 1.0) * min(max(turning_s - s, 0.0), 1.0)
        return on * np.array([4.0 * np.sin(2 * np.pi * f[0] * s + ph[0]),
                              4.0 * np.sin(2 * np.pi * f[1] * s + ph[1]),
                              7.0 + 3.0 * np.sin(2 * np.pi * f[2] * s + ph[2])])

    Rs = turned_by(exp_so3(np.array([0.05, -0.04, 0.5])), omega, t, rate_hz)
    delays = broad_delays_s()
    w_now = np.array([omega(tt) for tt in t])
    w_gyro = np.array([omega(tt - delays["imu_gyro"]) for tt in t]) @ (np.eye(3) + GYRO_ERROR).T
    mag = np.einsum("nji,j->ni", turned_back(Rs, w_now, delays["imu_mag"]), EARTH_ENU_UT)
    acc = np.einsum("nji,j->ni", turned_back(Rs, w_now, delays["imu_acc"]), [0.0, 0.0, GRAVITY_MPS2])
    gyr = w_gyro + rng.normal(0, np.radians(0.01) * np.sqrt(rate_hz / 2), (n, 3)) + [0.002, -0.001, 0.0015]
    acc = acc + rng.normal(0, 0.0004 * GRAVITY_MPS2 * np.sqrt(rate_hz / 2), (n, 3))
    mag = mag + rng.normal(0, 0.3, (n, 3))
    return write_broad_trial(path, rate_hz, Rs, acc, gyr, mag, np.ones(n, bool))


def test_fast_turns_grow_the_heading_s_sigma_and_the_compass_keeps_it(tmp_path: Path) -> None:
    trial = read_trial(_fast_trial(tmp_path / "fast.hdf5"))
    af = run_armfusion(trial)
    err, _, _ = errors_rad(af.q_enu, trial.opt_quat)
    sig = af.heading_sigma_rad
    t = np.arange(len(err)) / trial.rate_hz
    ok = np.isfinite(err) & np.isfinite(sig)
    rest_end = ok & (t > 29.0)  # resting, the turns ten seconds past
    assert np.mean(err[ok] <= 3 * sig[ok]) >= 0.95
    # the gyro's error, about 0.6 % of the turns' thousands of degrees, would leave the heading
    # several degrees off; the compass, heard as the heading's doubt grows, keeps it near
    assert np.degrees(np.median(err[rest_end])) < 3.0


def test_a_compass_later_than_the_gyro_is_turned_to_its_stamp(tmp_path: Path) -> None:
    """The trial's compass is drawn as late as the config says (its ``delay_s``, beyond the
    gyro's); the same trial tracked with a config that takes it for as late as the gyro is
    off by the turn over the difference while the sensor turns."""
    gyro_s, compass_s = sensor_delays_s(CONFIG)
    assert compass_s > gyro_s  # the shipped config's compass is the later
    trial = read_trial(_fast_trial(tmp_path / "late.hdf5"))
    t = np.arange(len(trial.movement)) / trial.rate_hz
    turning = (t > 5.0) & (t < 18.0)

    def rms_deg(config: str) -> float:
        af = run_armfusion(trial, config)
        err, _, _ = errors_rad(af.q_enu, trial.opt_quat)
        ok = turning & np.isfinite(err)
        return float(np.degrees(np.sqrt(np.mean(err[ok] ** 2))))

    right = rms_deg(CONFIG)
    as_gyro = rms_deg(str(config_with_compass_delay(CONFIG, gyro_s, tmp_path)))
    assert right < 0.7 * as_gyro, (right, as_gyro)
