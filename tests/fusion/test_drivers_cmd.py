"""`armfusion drivers`: the real drivers end to end against the simulator-fed fakes, and a
clear refusal when the real buses are not there."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.drivers_faults import parse_fault
from armfusion.fusion.cli.drivers_report import summary
from armfusion.fusion.cli.drivers_run import FakeRigOptions, run_fake
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import resolve_config_path
from armfusion.models.fake_rig import simulate_physics
from armfusion.models.sensor_models import ADXL345_NOISE_LSB_RMS_AT_100HZ, stream_models
from armfusion.models.simulator import SimulationOptions, simulate
from armfusion.sensors.bus import Status
from armfusion.sensors.recording import read_recording, write_recording
from typer.testing import CliRunner

runner = CliRunner()
ACCS = ("acc1", "acc2", "acc3", "acc4")
LSB_G = 1 / 256  # ADXL345, ±2 g 10-bit


@pytest.fixture(scope="module")
def moving():
    """5 s of the excitation scenario (everything moves) with every effect drawn, noise on."""
    return run_fake("wmra", FakeRigOptions("excitation", seed=5, realistic=True), 5.0, 100.0)


@pytest.fixture(scope="module")
def moving_ideal():
    """The same arm and motion without sensor noise: counts are the physics, rounded."""
    return run_fake("wmra", FakeRigOptions("excitation", seed=5, realistic=True, noise=False), 3.0, 100.0)


def _accel_vs_sim(run, name, tmp_path):
    """The recorded counts (through a CSV file) and the simulator's specific force (g) at
    the instants the fake sampled them."""
    path = tmp_path / f"{name}.csv"
    write_recording(run.recording, path)
    counts = read_recording(path).streams[name].values
    produced = list(run.rig[name].produced)
    assert len(counts) == len(produced), name  # every sample the device made, once
    t_sim = np.array([p.t_s for p in produced]) - run.epoch_s
    return counts, run.sim.at_many(name, t_sim)


def test_the_fakes_get_the_simulators_physics():
    """fake_rig keeps the simulator's chain: its values, rounded, are simulate()'s counts."""
    from armfusion.fusion.configfile import load_arm

    arm = load_arm("wmra")
    rec, _ = simulate(arm, "excitation", 4.0, seed=4, realistic=True, options=SimulationOptions(noise=False))
    run = simulate_physics(arm, "excitation", 4.0, seed=4, realistic=True)
    sm = stream_models(arm)
    for s in ("acc1", "acc4", "imu_acc", "imu_gyro", "imu_mag", "imu_temp", "enc"):
        st = rec.streams[s]
        v = run.at_many(s, st.t_s)
        c = v * 256 if s.startswith("acc") else v if s == "enc" else sm[s].to_counts(v)
        # the simulator's cubic time shift vs our linear 1 kHz grid: a count at most, rarely
        d = np.abs(np.rint(c) - st.values)
        assert d.max() <= 1 and np.mean(d > 0) < 0.01, s


def test_counts_round_trip_to_the_simulated_specific_force(moving_ideal, tmp_path):
    """No noise: counts / 256 is the simulator's specific force to the rounding (½ LSB),
    for a moving arm with mounts, biases, scale errors and time offsets."""
    for name in ACCS:
        counts, f_g = _accel_vs_sim(moving_ideal, name, tmp_path)
        err_lsb = np.abs(counts * LSB_G - f_g) / LSB_G
        assert err_lsb.max() <= 0.5 + 1e-6, name


def test_counts_round_trip_within_the_adxl345_noise_and_one_lsb(moving, tmp_path):
    sigma = ADXL345_NOISE_LSB_RMS_AT_100HZ  # x, y, z at 100 Hz
    for name in ACCS:
        counts, f_g = _accel_vs_sim(moving, name, tmp_path)
        err_lsb = (counts * LSB_G - f_g) / LSB_G
        # 5 sigma of noise plus one LSB of rounding bounds every one of ~500 × 3 samples
        assert np.all(np.abs(err_lsb) <= 5 * sigma + 1.0), name
        # and the scatter is the datasheet noise with rounding (√(σ² + 1/12)), within 15 %
        assert np.std(err_lsb, axis=0) == pytest.approx(np.sqrt(sigma**2 + 1 / 12), rel=0.15), name
        assert np.abs(np.mean(err_lsb, axis=0)).max() < 0.2, name  # no bias from the chain


def test_imu_readings_are_the_simulated_physics(moving_ideal):
    run = moving_ideal
    imu = [s for s in run.samples["imu"] if s.valid]
    produced = list(run.rig["imu"].produced)
    tp = np.array([p.t_s for p in produced])
    # the driver gets the newest sample the MPU made before its burst (1 kHz internal rate)
    k = np.searchsorted(tp, [s.t_s for s in imu], side="right") - 1
    assert np.all(np.array([s.t_s for s in imu]) - tp[k] < 1e-3 + 1e-9)
    t_sim = tp[k] - run.epoch_s
    acc = np.array([s.accel for s in imu]) / 16384.0
    assert np.abs(acc - run.sim.at_many("imu_acc", t_sim)).max() <= 0.5 / 16384 + 1e-9
    gyro = np.radians(np.array([s.gyro for s in imu]) / 131.0)
    assert np.abs(gyro - run.sim.at_many("imu_gyro", t_sim)).max() <= np.radians(0.5 / 131) + 1e-12
    temp = np.array([s.temp for s in imu]) / 340.0 + 35.0
    assert np.abs(temp - run.sim.at_many("imu_temp", t_sim)[:, 0]).max() <= 0.5 / 340 + 1e-9
    # the magnetometer, at the instants its measurements started: 0.3 µT/LSB, rounded
    # twice (the AK8975's raw counts, then after the driver's sensitivity adjustment)
    mags = [s for s in run.samples["imu"] if s.mag_valid]
    m = np.array([s.mag for s in mags]) * 0.3
    ref = run.sim.at_many("imu_mag", np.array([s.t_mag_s for s in mags]) - run.epoch_s)
    factor = run.rig["imu"].ak8975.factors.max()
    assert len(mags) > 250 and np.abs(m - ref).max() <= (0.5 * factor + 0.5) * 0.3 + 1e-9


def test_no_lost_or_duplicated_samples_at_100_hz(moving):
    rep = moving.loop
    assert rep.ticks == 500 and rep.missed_ticks == 0
    for name in ACCS:
        got = moving.samples[name]
        ok = [s for s in got if s.valid]
        produced = list(moving.rig[name].produced)
        assert [s.counts for s in ok] == [p.counts for p in produced], name
        assert np.array_equal([p.index for p in produced], np.arange(1, len(produced) + 1))
        assert abs(len(ok) - 500) <= 1 and not any(s.overrun for s in ok), name
        assert {s.status for s in got} == {Status.OK}, name
    imu = moving.samples["imu"]
    assert len(imu) == 500 and all(s.valid for s in imu)
    tp = np.array([p.t_s for p in moving.rig["imu"].produced])
    k = np.searchsorted(tp, [s.t_s for s in imu], side="right") - 1
    assert np.all(np.diff(k) > 0)  # a new IMU sample every tick, never the same one twice
    enc = moving.samples["enc"]
    assert np.array_equal([e.seq for e in enc], np.arange(enc[0].seq, enc[0].seq + len(enc)))
    st = moving.encoder_stats
    assert st.lost == st.duplicate == st.late == 0 and len(enc) >= 499
    doc = summary(moving)
    for name in (*ACCS, "imu"):
        d = doc["devices"][name]
        assert d["errors"] == d["retries"] == d["loop_errors"] == 0 and d["online"], name
    # the recording holds exactly these samples
    rec = moving.recording
    assert [len(rec.streams[n]) for n in ACCS] == [len([s for s in moving.samples[n] if s.valid])
                                                   for n in ACCS]
    assert len(rec.streams["imu_gyro"]) == 500 and len(rec.streams["enc"]) == len(enc)


def _startup_config(tmp_path: pathlib.Path) -> pathlib.Path:
    """The WMRA with ideal (calibrated) sensors, parked at a pose gravity sees fully."""
    d = yaml.safe_load(resolve_config_path("wmra").read_text())
    d["calibration"] = {"accel_unmodelled_g": 0.0}
    d["arm"]["ready_pose_deg"] = [30, 40, 20, -50, 60, 30, 100]
    cfg = tmp_path / "wmra_cal.yaml"
    cfg.write_text(yaml.safe_dump(d))
    return cfg


def test_calibrate_joints_on_a_fake_startup_recording_finds_the_true_angles(tmp_path):
    cfg = _startup_config(tmp_path)
    out = tmp_path / "startup.csv"
    r = runner.invoke(app, ["drivers", "--fake", "--config", str(cfg), "--scenario", "startup",
                            "--duration", "3", "--seed", "7", "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["out"] == str(out) and (tmp_path / "startup.truth.json").exists()
    true_q = read_recording(out).streams["true_q"].values[0]
    r = runner.invoke(app, ["calibrate", "joints", str(out), "--config", str(cfg), "--json"])
    assert r.exit_code == 0, r.output
    (seg,) = json.loads(r.stdout)["segments"]
    for j, q in zip(seg["joints"], true_q, strict=True):
        assert j["flag"] == "ok", j
        # within 3 sigma: the recording's noise is the only error left
        assert abs(j["angle_rad"] - q) <= 3 * j["sigma_rad"], (j["name"], np.degrees(j["angle_rad"] - q))


def test_injected_faults_are_counted_and_reported_not_a_crash():
    seen = {}

    def prepare(rig):  # the rig's own FaultInjectors: a flaky SPI link, a NACK burst on I2C
        rig["acc1"].faults.fail_randomly(0.05)
        rig.i2c[1].faults.fail_next(2)
        seen["acc1"] = rig["acc1"].faults
        seen["i2c1"] = rig.i2c[1].faults

    run = run_fake("wmra", FakeRigOptions("startup", seed=2, faults=("acc3:unplug@0.5-1.0",)), 2.0,
                   prepare=prepare)
    doc = summary(run)
    acc1 = doc["devices"]["acc1"]
    # every injected failure is a counted bus error; most are absorbed by the retries
    assert acc1["errors"] == seen["acc1"].injected > 0 and acc1["retries"] > 0
    assert acc1["samples"] + acc1["counters"].get("invalid", 0) >= 190
    acc3 = doc["devices"]["acc3"]
    assert acc3["counters"]["offline"] == 1 and acc3["counters"]["reinits"] == 1 and acc3["online"]
    assert 50 < acc3["samples"] < 190  # gone while unplugged, back after re-initialisation
    assert doc["faults"] == [{"spec": "acc3:unplug@0.5-1.0", "target": "acc3", "kind": "unplug"}]
    assert run.loop.ticks == 200  # the loop never stopped
    for name in ("acc1", "acc3"):  # the recording holds only valid samples, in time order
        assert np.all(np.diff(run.recording.streams[name].t_s) > 0)


def test_the_report_names_faults_and_errors():
    r = runner.invoke(app, ["drivers", "--fake", "--duration", "2", "--fault", "acc3:unplug@0.5-1",
                            "--fault", "i2c1:nack=2@0.2"], env={"COLUMNS": "160"})
    assert r.exit_code == 0, r.output
    assert "fault injected: acc3:unplug@0.5-1" in r.stdout
    row = next(ln for ln in r.stdout.splitlines() if ln.startswith("│ acc3"))
    cells = [c.strip() for c in row.strip("│").split("│")]
    assert cells[1] == "i2c1 0x53" and int(cells[5]) > 0 and "reinits 1" in cells[7]
    assert "200 ticks at 100 Hz" in r.stdout


def test_fault_specs_are_checked():
    assert parse_fault("acc3:unplug@2-3").t_end_s == 3.0
    with pytest.raises(ValueError, match=r"unknown kind 'melt'; kinds: nack, random"):
        parse_fault("acc3:melt")
    with pytest.raises(ValueError, match=r"random needs a probability in \(0, 1\]"):
        parse_fault("i2c1:random=2")
    r = runner.invoke(app, ["drivers", "--fake", "--duration", "1", "--fault", "acc9:stuck"])
    assert r.exit_code == 2 and "no device or bus 'acc9'" in r.stderr


@pytest.mark.skipif(any(pathlib.Path(p).exists() for p in ("/dev/i2c-1", "/dev/spidev0.0")),
                    reason="this machine has the Pi's buses")
def test_without_fake_the_real_buses_fail_one_line_per_device():
    r = runner.invoke(app, ["drivers"])
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert [ln.split(":")[1].strip() for ln in lines] == ["acc1", "acc2", "acc3", "acc4", "imu"]
    assert lines[0] == ("error: acc1: no ADXL345 on SPI bus 0 device 0: cannot open /dev/spidev0.0 "
                        "(No such file or directory); is SPI enabled (dtparam=spi=on in "
                        "/boot/config.txt)?")
    assert lines[4].startswith("error: imu: cannot open I2C bus 1 (/dev/i2c-1")
    assert "Traceback" not in r.output
