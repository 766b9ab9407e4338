"""Sensors read at instants of their own: what every real driver gives (each device read in
turn on its bus), against the simulator's habit of one instant for all. The tracker must
track as well from either: the same motion read 1-5 ms apart once gave j5 0.93 deg RMS
instead of 0.05, and the joints' flags switched between ``ok`` and ``ill_conditioned``
hundreds of times a second (each update held what its one sensor cannot see)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.tracker import TrackerSettings, start_from_recording
from armfusion.models.simulator import SimulationOptions, simulate
from armfusion.sensors.samples import Recording

PHASE_MS = {"acc1": 1, "acc2": 2, "acc3": 3, "acc4": 4, "imu_acc": 5, "imu_gyro": 5, "imu_temp": 5,
            "imu_mag": 5}


@pytest.fixture(scope="module")
def drive_read_both_ways():
    """One 1 kHz simulation of the WMRA reaching while the chair drives, read at 100 Hz twice:
    every device at the same instants, and each at its own phase (1-5 ms after the encoders)."""
    arm = load_arm("wmra")
    rec, _ = simulate(arm, "daily-use", 45.0, rate_hz=1000.0, seed=2, options=SimulationOptions(noise=False))

    def read(phases):  # (the truth kept at 1 kHz: it is looked up at every instant)
        raw = rec.raw()
        every = {n: slice(phases.get(n, 0), None, 10) for n in raw}
        return Recording({n: replace(s, t_s=s.t_s[every[n]], values=s.values[every[n]]) if n in raw else s
                          for n, s in rec.streams.items()}, dict(rec.meta))

    return arm, read({}), read(PHASE_MS)


def _track(arm, rec):
    tr, start = start_from_recording(arm, rec, TrackerSettings())
    run = tr.run(rec)
    moving = run.t_s > start.t_end_s + 5.0
    rms = np.degrees(np.sqrt(np.mean(run.q_error_rad[moving] ** 2, axis=0)))
    flips = (np.diff(run.flags[moving].astype(int), axis=0) != 0).sum(axis=0)
    return run, rms, flips


def test_sensors_read_at_their_own_instants_track_as_well_as_at_one(drive_read_both_ways):
    arm, same, own = drive_read_both_ways
    run_same, rms_same, flips_same = _track(arm, same)
    run_own, rms_own, flips_own = _track(arm, own)
    assert run_own.steps > 4 * run_same.steps  # the instants really are apart
    # the arm as well tracked read either way (the joints' mean RMS to a third, or 0.02 deg),
    # no joint more than 0.15 deg worse, every joint within 3 sigma (the fault: mean 0.44
    # deg against 0.04, j5 0.93 against 0.05). Not equal: with the chair's swing about its
    # turning centre predicted from the gyro, j3 is 0.19 deg read apart against 0.08 at one
    # instant (docs/tracking.md, Limits)
    assert rms_own.mean() <= max(1.33 * rms_same.mean(), rms_same.mean() + 0.02), (rms_same, rms_own)
    assert np.all(rms_own <= rms_same + 0.15), (rms_same, rms_own)
    assert (np.abs(run_own.q_error_rad) <= 3 * run_own.sigma_rad).mean(axis=0).min() > 0.99
    # and its flag as steady: no joint switching flags at the sensors' rate
    assert np.all(flips_own <= 2 * flips_same + 10), (flips_same, flips_own)
