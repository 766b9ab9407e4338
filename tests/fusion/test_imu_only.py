"""An arm with no joints is a valid arm: an IMU alone (the shipped `broad_imu` config, the
BROAD benchmark's hand-held 9-axis IMU) loads, imports, starts on its still stretch and is
tracked by the chair's own tilt and heading code, through the command line; and the
tracker's attitude stays one attitude when the base turns over (pitch through the vertical,
roll past a whole turn), which a chair never does and a hand does.

The real slice: tests/data/broad/02_undisturbed_slow_rotation_B_6s_moving.hdf5 (README
there): about a second still, then the start of slow hand rotations, with the optical
reference."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.process import ProcessModel, attitude_sigma_rad
from armfusion.fusion.tracking.process_kernels import (
    points_from_tangent,
    process_points_tangent,
    tangent_from_points,
)
from armfusion.fusion.tracking.settings import StateLayout, TrackerSettings
from armfusion.models.arm_config import ConfigError
from armfusion.models.rotations import R_from_rpy, exp_so3
from typer.testing import CliRunner

DATA = Path(__file__).resolve().parents[1] / "data" / "broad"
SLICE = DATA / "02_undisturbed_slow_rotation_B_6s_moving.hdf5"
runner = CliRunner()


def test_the_imu_only_config_is_an_arm_with_no_joints_and_a_9_axis_base_imu() -> None:
    arm = load_arm("broad_imu")
    assert arm.n_joints == 0 and arm.link_accelerometers == ()
    assert arm.imu is not None and arm.imu.description.has("magnetometer")


def test_a_jointless_config_without_a_base_imu_is_refused_saying_what_it_needs(tmp_path: Path) -> None:
    cfg = yaml.safe_load((Path(load_arm("broad_imu").source)).read_text())
    cfg["sensors"][0]["link"] = 1  # no base IMU left (and no link 1 to put it on)
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ConfigError, match=r"an arm with no joints needs a base IMU \(an imu on link 0\)"):
        load_arm(tmp_path / "c.yaml")


def test_the_real_broad_slice_goes_through_import_and_the_imu_only_track(tmp_path: Path) -> None:
    rec = tmp_path / "b.csv"
    r = runner.invoke(app, ["import", str(SLICE), "--map", "broad", "--config", "broad_imu",
                            "--out", str(rec)])
    assert r.exit_code == 0, r.output
    assert "enc: absent (BROAD has no arm and no encoder" in r.output
    r = runner.invoke(app, ["track", "--config", "broad_imu", str(rec), "--json"])
    assert r.exit_code == 0, r.output
    doc = json.loads(r.output)
    # the startup read the still stretch's tilt from the IMU alone, the tracker ran after it
    assert doc["start"]["flags"] == {} and doc["start"]["t_end_s"] < 3.0
    assert "no joints: the base tilt from the IMU accelerometer alone" in doc["notes"]
    with h5py.File(SLICE) as f:
        n, rate = len(f["imu_gyr"]), float(f.attrs["sampling_rate"])
        q_end = f["opt_quat"][-1]
    assert doc["steps"] > 0.5 * n
    assert doc["rejections"]["imu_acc"] < 0.05 * doc["steps"]
    fin = doc["final"]
    assert fin["joint_names"] == [] and fin["t_s"] == pytest.approx((n - 1) / rate)
    for k in ("roll", "pitch"):
        assert np.isfinite(fin[f"{k}_rad"]) and 0.0 < fin[f"{k}_sigma_rad"] < np.radians(5.0), k
    # the heading's sigma keeps the config's own doubt about the compass (2 µT of iron against
    # about 15 µT of horizontal field: some 8 deg at any one heading, no averaging removes it)
    assert np.isfinite(fin["heading_rad"]) and np.radians(3.0) < fin["heading_sigma_rad"] < np.radians(15.0)
    # the last attitude against the optical reference (ENU: world x east; armfusion's x is
    # magnetic north, so its world is the reference's turned by -90 deg about up)
    w, x, y, z = q_end
    R_ref = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    R_nwu = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ R_ref
    R_est = R_from_rpy(fin["roll_rad"], fin["pitch_rad"], fin["heading_rad"])
    angle = np.degrees(np.arccos(np.clip((np.trace(R_est.T @ R_nwu) - 1) / 2, -1, 1)))
    assert angle < 2.0  # measured 0.6 deg; a wrong axis or sign is tens of degrees


def test_the_attitude_tangent_space_is_one_rotation_at_any_attitude_even_at_the_vertical() -> None:
    # points about a central attitude 0.5 deg from pitch -90 (where Euler angles are
    # singular): their Euler angles are exp([d]x) R_0 (d in world axes), and taking them
    # back gives d again
    L = StateLayout(0)
    rng = np.random.default_rng(5)
    X = np.zeros((7, L.size))
    X[:, [L.roll, L.pitch, L.yaw]] = [0.4, np.radians(-89.5), 2.9]
    d = rng.normal(0.0, 0.02, (6, 3))
    X[1:, [L.roll, L.pitch, L.yaw]] += d
    E = points_from_tangent(X, L.roll, L.yaw)
    R0 = R_from_rpy(0.4, np.radians(-89.5), 2.9)
    for i in range(1, 7):
        np.testing.assert_allclose(R_from_rpy(*E[i, [L.roll, L.pitch, L.yaw]]), exp_so3(d[i - 1]) @ R0,
                                   atol=1e-12)
    np.testing.assert_allclose(tangent_from_points(E, L.roll, L.yaw), X, atol=1e-10)
    # the reset folds a tangent vector into canonical Euler angles of the same rotation
    pm = ProcessModel(TrackerSettings(), L)
    x = X[3].copy()
    folded = pm.fold_attitude(x, X[0, [L.roll, L.pitch, L.yaw]])
    np.testing.assert_allclose(R_from_rpy(*folded[[L.roll, L.pitch, L.yaw]]), exp_so3(d[2]) @ R0, atol=1e-12)
    assert abs(folded[L.pitch]) <= np.pi / 2
    # one step of the gyro in the tangent space: each point's rotation turned by its rates
    # (1,000 deg/s for 10 ms, less its own bias), and the points taken back about the
    # propagated central point; the Euler points given alongside are the same rotations
    w = np.array([10.0, -17.0, 4.0])
    X[:, L.bias] = rng.normal(0.0, 0.01, (7, 3))
    T, Y = process_points_tangent(X, 0.01, w, True, L.roll, L.yaw, L.bias.start, L.accel.start, L.scale, 0.9)
    att = [L.roll, L.pitch, L.yaw]
    turned = [R_from_rpy(*E[i, att]) @ exp_so3(0.01 * (w - X[i, L.bias])) for i in range(7)]
    for i in range(7):
        np.testing.assert_allclose(R_from_rpy(*Y[i, att]), turned[i], atol=1e-12)
    back = points_from_tangent(T, L.roll, L.yaw)
    for i in range(7):
        np.testing.assert_allclose(R_from_rpy(*back[i, att]), turned[i], atol=1e-9)
    np.testing.assert_allclose(T[:, L.accel], 0.9 * X[:, L.accel])
    # the sigmas: a level base's are the tangent vector's own; the heading's (about the
    # world's vertical) stays that at any attitude, where roll's grows without bound near
    # pitch 90 deg (Euler roll is undefined there)
    C = np.diag([1e-4, 4e-4, 9e-4])
    np.testing.assert_allclose(attitude_sigma_rad(np.zeros(3), C), [0.01, 0.02, 0.03])
    on_side = attitude_sigma_rad(np.array([0.0, np.radians(89.9), 0.0]), C)
    assert on_side[2] == pytest.approx(0.03) and 1.0 < on_side[0] <= np.pi
