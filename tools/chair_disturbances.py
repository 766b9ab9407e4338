"""What a wheelchair meets that its compass and base IMU do not expect, added to a simulated
``daily-use`` recording (the raw counts, as the devices would give them): a magnet clipped
to the armrest, a magnet on the way that the chair drives past, and rough ground.

Each is a physical field or motion, not a number in the filter's own terms:

- :func:`magnet_clipped`: a field that rides with the IMU (a magnet or a tool clipped on the
  armrest, a motor's current): in the IMU's axes it is constant, a new hard iron, switched
  on over 2 s and kept to the end;
- :func:`magnet_passed`: a magnet fixed in the world (on the floor, in a door frame), the
  field of a point dipole ``B = mu0/(4 pi) (3 r (m.r) / |r|^5 - m / |r|^3)`` at the IMU's
  position as the chair drives past it, turned into the IMU's axes by the chair's attitude;
- :func:`rough_ground`: the chair's frame shaken by the ground: band-limited vibration of
  the IMU's specific force (along the world's vertical) and of its roll and pitch rates,
  zero-mean, from a seeded generator.

The chair's position and attitude come from the scenario itself
(:func:`armfusion.models.trajectories.make_scenario` with the recording's seed: the same
path as the simulator drove). Used by ``tools/bench_track_realistic.py``.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.sensor_description import (
    AK8975_COUNTS,
    AK8975_UT_PER_LSB,
    INT16,
    MPU9150_ACCEL_LSB_PER_G,
    MPU9150_GYRO_LSB_PER_DPS,
)
from armfusion.models.trajectories import make_scenario
from armfusion.sensors.samples import Recording

from tools.bench_track import with_stream

MU0_OVER_4PI_UT_M3_PER_AM2 = 0.1
"""mu0 / 4 pi = 1e-7 T m / A: a dipole of 1 A m^2 gives 0.1 µT at 1 m on its equator."""


def _add_counts(rec: Recording, name: str, add: np.ndarray, per_unit: float, limits) -> Recording:
    """``add`` (physical units, one row per sample of stream ``name``) added to its counts at
    ``per_unit`` counts per unit, rounded and clipped to the device's range as it would be."""
    s = rec.get(name)
    v = np.clip(s.values + np.round(add * per_unit).astype(np.int64), *limits)
    return with_stream(rec, name, v)


def magnet_clipped(rec: Recording, t_on_s: float, field_imu_ut: np.ndarray) -> Recording:
    """A magnet clipped on near the IMU at ``t_on_s`` (over 2 s) and left there: the field
    ``field_imu_ut`` (µT, the IMU's axes) added to the compass from then to the end."""
    m = rec.get("imu_mag")
    w = np.clip((m.t_s - t_on_s) / 2.0, 0.0, 1.0)
    return _add_counts(rec, "imu_mag", w[:, None] * np.asarray(field_imu_ut, float),
                       1.0 / AK8975_UT_PER_LSB, AK8975_COUNTS)


def chair_path(arm, duration_s: float, seed: int):
    """The scenario that drove a ``daily-use`` recording simulated for ``duration_s`` with
    ``seed`` (the simulator's own length: the path's drives are drawn up to it)."""
    return make_scenario(arm, "daily-use", duration_s, seed)


def dipole_ut(moment_am2: np.ndarray, r_m: np.ndarray) -> np.ndarray:
    """The field (µT) of a point dipole of moment ``moment_am2`` (A m^2) at offsets ``r_m``
    (N, 3) from it."""
    r = np.asarray(r_m, float)
    d = np.linalg.norm(r, axis=1, keepdims=True)
    mr = r @ np.asarray(moment_am2, float)
    return MU0_OVER_4PI_UT_M3_PER_AM2 * (3.0 * r * mr[:, None] / d**5 - np.asarray(moment_am2) / d**3)


def pass_moment(scenario, t_from_s: float, cruise_mps: float = 0.5, hold_s: float = 4.0) -> float:
    """The first moment after ``t_from_s`` at which the chair has driven at least
    ``cruise_mps`` for ``hold_s`` (the middle of that stretch): where a magnet is passed."""
    t = np.arange(t_from_s, scenario.duration_s - hold_s, 0.05)
    v, _, _ = scenario.base.speed(t)
    fast = v[:, 0] >= cruise_mps
    need = int(round(hold_s / 0.05))
    run = np.convolve(fast.astype(int), np.ones(need, int), "valid")
    k = np.flatnonzero(run == need)
    if not len(k):
        raise ValueError(f"the chair never cruises at {cruise_mps} m/s for {hold_s} s after {t_from_s} s")
    return float(t[k[0]] + hold_s / 2)


def magnet_passed(rec: Recording, arm, scenario, t_pass_s: float, moment_am2: np.ndarray,
                  beside_m: float) -> tuple[Recording, float]:
    """A magnet of ``moment_am2`` (A m^2, world axes) fixed ``beside_m`` to the left of where
    the IMU is at ``t_pass_s``, at its height: its field added to the compass all along (it
    matters only near it). Returns the recording and the largest field it adds (µT)."""
    m = rec.get("imu_mag")
    p_imu = np.asarray(arm.imu.p_L_m, float)
    base = scenario.base(m.t_s)
    R_WB = base.R_WB
    pos = scenario.base_position_m(m.t_s) + np.einsum("nij,j->ni", R_WB, p_imu)
    k = int(np.argmin(np.abs(m.t_s - t_pass_s)))
    where = pos[k] + beside_m * R_WB[k][:, 1] * np.array([1.0, 1.0, 0.0])
    B_W = dipole_ut(moment_am2, pos - where)
    R_WI = R_WB @ np.asarray(arm.imu.R_LS, float)
    B_I = np.einsum("nji,nj->ni", R_WI, B_W)
    return (_add_counts(rec, "imu_mag", B_I, 1.0 / AK8975_UT_PER_LSB, AK8975_COUNTS),
            float(np.linalg.norm(B_I, axis=1).max()))


def _band_noise(rng: np.random.Generator, n: int, rate_hz: float, band_hz: tuple[float, float],
                rms: float, channels: int) -> np.ndarray:
    """Zero-mean noise of ``rms`` per channel, its power flat within ``band_hz`` and none
    outside (white noise filtered in the frequency domain)."""
    spec = np.fft.rfft(rng.standard_normal((n, channels)), axis=0)
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    spec[(f < band_hz[0]) | (f > band_hz[1])] = 0.0
    x = np.fft.irfft(spec, n, axis=0)
    return x * rms / np.sqrt(np.mean(x**2, axis=0))


def rough_ground(rec: Recording, arm, scenario, t1_s: float, t2_s: float, seed: int,
                 accel_g_rms: float = 0.2, rate_dps_rms: float = 3.0,
                 band_hz: tuple[float, float] = (5.0, 30.0)) -> Recording:
    """The chair shaken by rough ground from ``t1_s`` to ``t2_s`` (1 s ramps): the IMU's
    specific force shaken along the world's vertical by ``accel_g_rms``, its roll and pitch
    rates (the chair's axes) by ``rate_dps_rms`` each, both within ``band_hz``."""
    R_I = np.asarray(arm.imu.R_LS, float)
    rng = np.random.default_rng(seed)
    acc = rec.get("imu_acc")
    w = np.clip((acc.t_s - t1_s), 0.0, 1.0) * np.clip((t2_s - acc.t_s), 0.0, 1.0)
    rate = 1.0 / float(np.median(np.diff(acc.t_s)))
    up = _band_noise(rng, len(acc.t_s), rate, band_hz, accel_g_rms, 1)[:, 0] * w
    R_WB = scenario.base(acc.t_s).R_WB
    up_I = np.einsum("nji,j->ni", R_WB @ R_I, np.array([0.0, 0.0, 1.0])) * up[:, None]
    out = _add_counts(rec, "imu_acc", up_I, MPU9150_ACCEL_LSB_PER_G, INT16)
    gyro = rec.get("imu_gyro")
    wg = np.clip((gyro.t_s - t1_s), 0.0, 1.0) * np.clip((t2_s - gyro.t_s), 0.0, 1.0)
    rates_B = np.zeros((len(gyro.t_s), 3))
    rates_B[:, :2] = _band_noise(rng, len(gyro.t_s), rate, band_hz, rate_dps_rms, 2) * wg[:, None]
    rates_I = rates_B @ R_I  # (the IMU's axes: R_I^T times each row)
    return _add_counts(out, "imu_gyro", rates_I, MPU9150_GYRO_LSB_PER_DPS, INT16)
