"""The heading's sigma on a hand-held IMU (the ``broad_imu`` config, through ``import`` and
the IMU-only track, as the BROAD benchmark runs it): a compass iron fixed in the sensor
(the config says 2 µT per axis may be left) is a heading error that turns with the sensor.
Turned round and round, the heading averages it away and its sigma says so (it is of the
size of the error, not the iron's full 7° at one attitude); a magnet standing next to the
turning sensor for a while is caught and the heading's sigma still covers its error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from armfusion.models.rotations import GRAVITY_MPS2, exp_so3

from tests.fusion.test_base_velocity import broad_delays_s, turned_back, turned_by, write_broad_trial
from tools.bench_heading_broad import errors_rad, read_trial, run_armfusion

IRON_UT = np.array([1.5, -2.0, 1.0])
"""A hard iron left in the compass, fixed in its axes, of the size the config allows (2 µT per axis)."""
EARTH_ENU_UT = np.array([0.0, 16.0, -40.0])


def _spun_trial(path: Path, magnet_ut=None, seed: int = 4, rate_hz: float = 100.0, still_s: float = 3.0,
                moving_s: float = 30.0) -> Path:
    """A BROAD-format trial: an IMU still, then turned by hand about the vertical at about
    60 deg/s, one way, wobbling by some degrees in roll and pitch; its compass reads Earth's
    field plus :data:`IRON_UT` plus noise, and, with ``magnet_ut = (t1, t2, field)``, a magnet
    standing near it from t1 to t2 (a field fixed in the world, 1 s ramps). Gyro: a constant
    bias and white noise; every sensor late by the config's delay for it. Reference exact."""
    rng = np.random.default_rng(seed)
    n = int((still_s + moving_s) * rate_hz)
    t = np.arange(n) / rate_hz
    f_w = rng.uniform(0.3, 0.5, 2)

    def omega(tt: float) -> np.ndarray:  # body axes, rad/s
        on = min(max(tt - still_s, 0.0) / 2.0, 1.0)
        wob = 0.3 * np.sin(2 * np.pi * f_w * max(tt - still_s, 0.0))
        return on * np.array([wob[0], wob[1], 1.05])

    Rs = turned_by(exp_so3(np.array([0.05, -0.04, 0.5])), omega, t, rate_hz)
    delays = broad_delays_s()
    w_now = np.array([omega(tt) for tt in t])
    w_gyro = np.array([omega(tt - delays["imu_gyro"]) for tt in t])
    field = np.broadcast_to(EARTH_ENU_UT, (n, 3)).copy()
    if magnet_ut is not None:
        t1, t2, dB = magnet_ut
        on = np.clip(t - t1, 0.0, 1.0) * np.clip(t2 - t, 0.0, 1.0)
        field += on[:, None] * np.asarray(dB, float)
    mag = np.einsum("nji,nj->ni", turned_back(Rs, w_now, delays["imu_mag"]), field) + IRON_UT
    f = np.einsum("nji,j->ni", turned_back(Rs, w_now, delays["imu_acc"]), [0.0, 0.0, GRAVITY_MPS2])
    gyr = w_gyro + rng.normal(0, np.radians(0.01) * np.sqrt(rate_hz / 2), (n, 3)) + [0.002, -0.001, 0.0015]
    acc = f + rng.normal(0, 0.0004 * GRAVITY_MPS2 * np.sqrt(rate_hz / 2), (n, 3))
    mag = mag + rng.normal(0, 0.3, (n, 3))
    return write_broad_trial(path, rate_hz, Rs, acc, gyr, mag, t > still_s)


def _heading(path: Path):
    """The IMU-only track's heading error and sigma (rad) on the moving samples, and their times."""
    trial = read_trial(path)
    af = run_armfusion(trial)
    err, _, _ = errors_rad(af.q_enu, trial.opt_quat)
    ok = trial.movement & np.isfinite(err) & np.isfinite(af.heading_sigma_rad)
    return err[ok], af.heading_sigma_rad[ok], np.flatnonzero(ok) / trial.rate_hz


def test_a_sensor_turned_round_averages_its_iron_and_its_sigma_says_so(tmp_path: Path) -> None:
    err, sig, t = _heading(_spun_trial(tmp_path / "spun.hdf5"))
    late = t > 15.0  # after the first turns
    rms = float(np.sqrt(np.mean(err[late] ** 2)))
    med = float(np.median(sig[late]))
    assert np.mean(err <= 3 * sig) >= 0.95  # honest
    # and tight: a few times the error (the IMU's mount about the vertical, 1°, is in it
    # whatever the turns do, and the gyro's scale the config leaves unknown, 0.3 % of the
    # turns, though this gyro's is exact), far below the iron's full 7° at one attitude
    # (2 µT of 16)
    assert med < 4.5 * rms and med < np.radians(3.0), (np.degrees(med), np.degrees(rms))


def test_a_magnet_beside_the_turning_sensor_stays_within_the_heading_s_sigma(tmp_path: Path) -> None:
    err, sig, t = _heading(_spun_trial(tmp_path / "magnet.hdf5", magnet_ut=(12.0, 24.0, [8.0, -6.0, 5.0])))
    near = (t > 12.0) & (t < 26.0)
    assert np.mean(err <= 3 * sig) >= 0.95
    assert np.mean(err[near] <= 3 * sig[near]) >= 0.95
