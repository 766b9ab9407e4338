"""Config validation: every problem reported at once, naming file, key and value."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm
from armfusion.models.arm_config import ConfigError, build_arm
from armfusion.models.kinematics import chain_poses

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"


@pytest.fixture
def wmra_dict():
    return yaml.safe_load((CONFIG_DIR / "wmra.yaml").read_text())


def _problems(data, source="arm.yaml"):
    with pytest.raises(ConfigError) as e:
        build_arm(data, source)
    return e.value, [str(p) for p in e.value.problems]


def test_shipped_configs_load(wmra, crs):
    assert wmra.n_joints == 7 and wmra.convention == "modified"
    assert [s.name for s in wmra.link_accelerometers] == ["acc1", "acc2", "acc3", "acc4"]
    assert [s.link for s in wmra.link_accelerometers] == [2, 4, 6, 7]
    assert wmra.imu.name == "imu" and wmra.imu.link == 0
    np.testing.assert_allclose(np.degrees(wmra.ready_pose_rad), [90, 90, 0, 90, 90, 60, 0])
    np.testing.assert_allclose(wmra.counts_per_rad[0], 13258000 / (2 * np.pi))
    assert crs.n_joints == 6 and crs.convention == "standard"


def test_all_problems_reported_together(wmra_dict):
    bad = copy.deepcopy(wmra_dict)
    bad["sensors"][0]["rotation"] = [[1, 0, 0], [0, 1, 0], [0, 0.5, 1]]
    bad["sensors"][1]["link"] = 9
    bad["arm"]["joints"]["counts_per_rev"][2] = -4720000
    bad["sensors"][2]["type"] = "adxl999"
    err, lines = _problems(bad, "wmra.yaml")
    assert len(lines) == 4, lines
    text = str(err)
    assert "4 problems in arm config" in text
    assert "wmra.yaml: sensors[0].rotation: mounting rotation not orthonormal" in text
    assert "wmra.yaml: sensors[1].link: link index out of range: 0 (base) to 7 (got 9)" in text
    assert "wmra.yaml: arm.joints.counts_per_rev: counts per revolution must be from 1 to 2^32; " \
           "entry 2 is -4720000.0" in text
    assert "wmra.yaml: sensors[2].type: unknown sensor type; known types are adxl345, " \
           "mpu9150, mpu6050, analog_triax, custom (got 'adxl999')" in text


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["arm"]["dh"]["d_mm"].pop(), r"arm\.dh\.d_mm: has 6 entries; alpha_deg has 7"),
        (lambda d: d["arm"].__setitem__("ready_pose_deg", [90, 90, 0, 90, 90, 60, 250]),
         r"arm\.ready_pose_deg\[6\]: outside joint limits \[-200, 200\] deg \(got 250\)"),
        (lambda d: d["sensors"][0].__setitem__("rotaton", [[1, 0, 0]]),
         r"sensors\[0\]\.rotaton: unknown key"),
        (lambda d: d["arm"].pop("ready_pose_deg"), r"arm\.ready_pose_deg: required key is missing"),
        (lambda d: d["sensors"][1].__setitem__("name", "acc1"),
         r"sensors\[1\]\.name: duplicate sensor name \(also sensors\[0\]\)"),
        (lambda d: d["sensors"][0].__setitem__("rotation", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]),
         r"sensors\[0\]\.rotation: mounting rotation a reflection, not a rotation"),
        (lambda d: d["arm"]["joints"]["min_deg"].__setitem__(0, 300),
         r"arm\.joints\.min_deg\[0\]: lower limit is not below the upper limit 200"),
        (lambda d: d["sensors"][2]["bus"].pop("address"),
         r"sensors\[2\]\.bus\.address: an I2C device needs an address"),
        (lambda d: d["arm"]["dh"].__setitem__("convention", "craig"),
         r"arm\.dh\.convention: Input should be 'modified' or 'standard' \(got 'craig'\)"),
    ],
)
def test_each_problem_names_key_and_value(wmra_dict, mutate, message):
    mutate(wmra_dict)
    err, _ = _problems(wmra_dict)
    assert err.problems, "expected at least one problem"
    assert any(__import__("re").search(message, str(p)) for p in err.problems), str(err)


def test_not_a_mapping_and_bad_yaml(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("arm: [1, 2\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml: line \d+, column \d+: not valid YAML"):
        load_arm(p)
    p.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match=r"an arm config is a mapping"):
        load_arm(p)


def test_missing_config_names_the_shipped_ones():
    with pytest.raises(FileNotFoundError, match=r"no arm config 'nope'.*'crs_a465', 'imu_rig_pitch', "
                                                  r"'imu_rig_roll', 'imu_rig_yaw', 'ur5_two_imu', 'wmra'"):
        load_arm("nope")


def _urdf_from_modified_dh(arm) -> str:
    """The WMRA as a URDF: joint i's origin is Tz(d_{i-1}) Rx(alpha_i) Tx(a_i)."""
    dh = arm.dh
    parts = ['<robot name="wmra">', '<link name="base"/>']
    d_prev = 0.0
    for i in range(arm.n_joints):
        parent = "base" if i == 0 else f"l{i}"
        parts.append(
            f'<joint name="j{i + 1}" type="revolute"><parent link="{parent}"/>'
            f'<child link="l{i + 1}"/><origin xyz="{dh.a_m[i]} 0 {d_prev}" '
            f'rpy="{dh.alpha_rad[i]} 0 0"/><axis xyz="0 0 1"/>'
            f'<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>'
        )
        parts.append(f'<link name="l{i + 1}"/>')
        d_prev = dh.d_m[i]
    parts.append(f'<joint name="flange" type="fixed"><parent link="l{arm.n_joints}"/>'
                 f'<child link="tool"/><origin xyz="0 0 {d_prev}" rpy="0 0 0"/></joint>')
    parts.append('<link name="tool"/></robot>')
    return "\n".join(parts)


def test_urdf_description_gives_the_same_kinematics(tmp_path, wmra, wmra_dict, rng):
    (tmp_path / "wmra.urdf").write_text(_urdf_from_modified_dh(wmra))
    cfg = copy.deepcopy(wmra_dict)
    del cfg["arm"]["dh"]
    cfg["arm"]["urdf"] = "wmra.urdf"
    (tmp_path / "wmra_urdf.yaml").write_text(yaml.safe_dump(cfg))
    arm_u = load_arm(tmp_path / "wmra_urdf.yaml")
    assert arm_u.convention == "urdf"
    q = rng.uniform(wmra.min_rad, wmra.max_rad, size=(40, 7))
    a, b = chain_poses(wmra, q), chain_poses(arm_u, q)
    # link frames coincide except where URDF places frame i's origin before d_i;
    # the flange and every rotation must agree
    np.testing.assert_allclose(a.R_0L, b.R_0L, atol=1e-12)
    np.testing.assert_allclose(a.p_0L_m[:, -1], b.p_0L_m[:, -1], atol=1e-12)
    np.testing.assert_allclose(a.axis_0, b.axis_0, atol=1e-12)


def test_urdf_that_is_not_a_chain_is_refused(tmp_path, wmra_dict):
    (tmp_path / "tree.urdf").write_text(
        '<robot name="t"><link name="b"/><link name="x"/><link name="y"/>'
        '<joint name="a" type="revolute"><parent link="b"/><child link="x"/><axis xyz="0 0 1"/>'
        '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
        '<joint name="c" type="revolute"><parent link="b"/><child link="y"/><axis xyz="0 0 1"/>'
        '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    cfg = copy.deepcopy(wmra_dict)
    del cfg["arm"]["dh"]
    cfg["arm"]["urdf"] = "tree.urdf"
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ConfigError, match=r"arm\.urdf: URDF tree\.urdf: link 'b' has 2 child "
                                          r"joints; armfusion needs a serial chain"):
        load_arm(tmp_path / "c.yaml")


def test_the_calibration_block_becomes_one_typed_object(wmra, wmra_dict):
    """What a calibrated config says of its sensors is read as attributes with units, the
    per-sensor floor winning over the common one, and an uncalibrated config reads as zeros."""
    assert wmra.calibration.accel_floor_g("acc1") == wmra.calibration.accel_unmodelled_g
    assert wmra.calibration.references == () and not wmra.calibration.correction_covariance
    d = copy.deepcopy(wmra_dict)
    d["calibration"] = {
        "accel_unmodelled_g": 0.004, "accel_unmodelled_g_per_sensor": {"acc2": 0.001},
        "mag_unmodelled_ut": 2.5,
        "correction_covariance": {"acc2": {"elements": ["acc2.accel_bias[x]", "acc2.accel_bias[y]"],
                                           "matrix": [[1e-6, 0.0], [0.0, 4e-6]]}},
        "identified": {"references": [{"joint": "j1", "angle_deg": 10.0, "sigma_deg": 0.05,
                                       "t_start_s": 1.0, "t_end_s": 4.0, "where": "the parking stop"}]},
    }
    cal = build_arm(d, "calibrated.yaml").calibration
    assert (cal.accel_floor_g("acc2"), cal.accel_floor_g("acc1")) == (0.001, 0.004)
    assert cal.imu_accel_floor_g == 0.004 and cal.mag_unmodelled_ut == 2.5
    cov = cal.correction_covariance["acc2"]
    assert cov.elements == ("acc2.accel_bias[x]", "acc2.accel_bias[y]")
    np.testing.assert_array_equal(cov.matrix, [[1e-6, 0.0], [0.0, 4e-6]])
    (ref,) = cal.references
    assert (ref.joint, ref.angle_deg, ref.sigma_deg, ref.where) == ("j1", 10.0, 0.05, "the parking stop")
    exact = cal.as_exact()
    assert (exact.accel_floor_g("acc2"), exact.imu_accel_floor_g, exact.mag_unmodelled_ut) == (0.0, 0.0, 0.0)
    assert exact.references == cal.references


def test_joint_angles_are_reported_on_the_turn_inside_their_limits(wmra):
    """j6 (limits ±90°) estimated at 290° is the same pose as -70°: the controller reads -70°;
    an angle within half a turn of its limits' middle is not touched, to the bit."""
    q = np.radians([10.0, 20.0, 30.0, 40.0, 50.0, 290.0, -200.0])
    out = wmra.angles_in_range(q)
    mid = np.degrees(0.5 * (wmra.min_rad + wmra.max_rad))
    assert np.all(np.abs(np.degrees(out) - mid)[:6] <= 180.0)
    assert out[6] == q[6]  # j7's limits (±200°) span more than a turn: -200° is its own
    np.testing.assert_allclose(np.degrees(out[5]), -70.0, atol=1e-9)
    np.testing.assert_allclose(np.cos(out - q), 1.0)  # whole turns only
    inside = np.abs(np.degrees(q) - mid) <= 180.0
    assert np.array_equal(out[inside], q[inside])
