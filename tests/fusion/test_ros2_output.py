"""`armfusion track REC --out EST.ros2.mcap`: the estimates as ROS 2 messages in a rosbag2 MCAP
file that two independent readers (rosbags, mcap-ros2-support) decode message for message,
holding what the tracker estimated in REP 103's frame (ENU, yaw counter-clockwise from east)
with REP 145's covariance layout; and `armfusion info --urdf`, whose chain puts every sensor
where the arm model does."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from armfusion.fusion.cli.main import app
from armfusion.fusion.cli.track import write_estimates
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.ros2.conventions import enu_quaternion_xyzw
from armfusion.fusion.ros2.estimates_bag import BASE_FRAME, HEADING_LEVEL, JOINT_LEVEL, TOPICS
from armfusion.fusion.tracking.estimate import HEADING_STATUS
from armfusion.fusion.tracking.settings import JOINT_FLAGS
from armfusion.fusion.tracking.tracker import StartOptions, start_from_recording
from armfusion.models.rotations import R_from_rpy, rot_z
from armfusion.models.simulator import simulate
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

runner = CliRunner()


def read_ros2_messages(path: Path) -> list:
    """Every message, decoded by mcap-ros2-support from the schemas the file holds."""
    with open(path, "rb") as f:
        return [m for m in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]


def _R_from_xyzw(q) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


# ---------------------------------------------------------------------------- REP 103


@pytest.mark.parametrize(
    "heading_deg, forward_enu",
    [(0.0, [0, 1, 0]), (90.0, [-1, 0, 0]), (-90.0, [1, 0, 0]), (180.0, [0, -1, 0])],
)
def test_a_heading_from_north_becomes_the_enu_orientation_that_points_the_base_the_same_way(
    heading_deg: float, forward_enu: list
) -> None:
    # armfusion's heading: counter-clockwise from north (0 north, +90 west); in ENU (x east,
    # y north) the base's forward axis must point to the same compass direction
    q = enu_quaternion_xyzw(np.radians([0.0, 0.0, heading_deg]))
    assert np.linalg.norm(q) == pytest.approx(1.0) and q[3] >= 0.0
    np.testing.assert_allclose(_R_from_xyzw(q) @ [1, 0, 0], forward_enu, atol=1e-12)
    np.testing.assert_allclose(_R_from_xyzw(q) @ [0, 0, 1], [0, 0, 1], atol=1e-12)  # up stays up


def test_a_tilted_base_keeps_its_roll_and_pitch_and_turns_by_a_quarter_about_up() -> None:
    rng = np.random.default_rng(7)
    rpy = np.column_stack(
        [rng.uniform(-0.4, 0.4, 50), rng.uniform(-0.4, 0.4, 50), rng.uniform(-np.pi, np.pi, 50)]
    )
    for r, p, y in rpy:
        R_enu = _R_from_xyzw(enu_quaternion_xyzw(np.array([r, p, y])))
        np.testing.assert_allclose(R_enu, rot_z(np.pi / 2) @ R_from_rpy(r, p, y), atol=1e-12)
        # gravity seen in the base's axes is the same in either world (both have z up)
        np.testing.assert_allclose(R_enu.T @ [0, 0, 1], R_from_rpy(r, p, y).T @ [0, 0, 1], atol=1e-12)


# ---------------------------------------------------------------------------- the bag track writes


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A simulated WMRA turning once on the spot (the compass's status changes as its iron is
    learnt), tracked; its estimates written as CSV and as a ROS 2 bag."""
    arm = load_arm("wmra")
    rec, _ = simulate(arm, "compass-turn", seed=2)
    tr, _ = start_from_recording(arm, rec, options=StartOptions(propose_unlock=False))
    run = tr.run(rec)
    d = tmp_path_factory.mktemp("ros2")
    write_estimates(run, d / "est.ros2.mcap", arm.source)
    return arm, run, d / "est.ros2.mcap"


def test_every_message_of_the_bag_decodes_with_two_independent_readers(tracked) -> None:
    arm, run, path = tracked
    with open(path, "rb") as f:
        reader = make_reader(f)
        stats = reader.get_summary().statistics
        channels = {
            c.topic: reader.get_summary().schemas[c.schema_id].name
            for c in reader.get_summary().channels.values()
        }
        assert reader.get_header().profile == "ros2"
    assert channels == TOPICS
    decoded = [m for m in read_ros2_messages(path)]  # mcap-ros2-support, from the schemas in the file
    assert len(decoded) == stats.message_count
    ts = get_typestore(Stores.EMPTY)  # rosbags, from the definitions in the file alone
    n = 0
    with AnyReader([path], default_typestore=ts) as r:
        for c, _, raw in r.messages():
            r.deserialize(raw, c.msgtype)
            n += 1
    assert n == stats.message_count
    counts = {}
    for m in decoded:
        counts[m.channel.topic] = counts.get(m.channel.topic, 0) + 1
    assert counts["/armfusion/joint_states"] == counts["/armfusion/heading"] == run.steps
    assert counts["/armfusion/joint_states/sigma"] == run.steps
    assert run.t_s[-1] - run.t_s[0] <= counts["/diagnostics"] < run.steps / 10  # a second apart, or a change


def test_the_bag_holds_the_estimates_in_rep_103s_frame_with_rep_145s_covariances(tracked) -> None:
    arm, run, path = tracked
    by_topic: dict[str, list] = {t: [] for t in TOPICS}
    for m in read_ros2_messages(path):
        by_topic[m.channel.topic].append(m)
    stamps = np.array(
        [
            m.decoded_message.header.stamp.sec * 10**9 + m.decoded_message.header.stamp.nanosec
            for m in by_topic["/armfusion/heading"]
        ]
    )
    np.testing.assert_array_equal(stamps, np.rint(run.t_s * 1e9).astype(np.int64))
    js, sig = by_topic["/armfusion/joint_states"], by_topic["/armfusion/joint_states/sigma"]
    assert list(js[0].decoded_message.name) == list(arm.joint_names) == list(sig[-1].decoded_message.name)
    np.testing.assert_array_equal([m.decoded_message.position for m in js], run.q_rad)
    np.testing.assert_array_equal([m.decoded_message.position for m in sig], run.sigma_rad)
    for i in range(0, run.steps, 97):
        imu = by_topic["/armfusion/heading"][i].decoded_message
        assert imu.header.frame_id == BASE_FRAME
        o = imu.orientation
        R = _R_from_xyzw([o.x, o.y, o.z, o.w])
        np.testing.assert_allclose(R, rot_z(np.pi / 2) @ R_from_rpy(*run.rpy_rad[i]), atol=1e-9)
        # REP 145: 3 x 3 row-major about x, y, z; roll, pitch and yaw variances on the diagonal
        cov = np.array(imu.orientation_covariance).reshape(3, 3)
        np.testing.assert_array_equal(np.diag(cov), run.rpy_sigma_rad[i] ** 2)
        assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0
        # what armfusion does not estimate: -1 in the first element, as REP 145 says
        assert imu.angular_velocity_covariance[0] == -1.0 and imu.linear_acceleration_covariance[0] == -1.0


def test_the_diagnostics_say_the_heading_each_joint_and_each_sensor_with_ros_levels(tracked) -> None:
    arm, run, path = tracked
    diags = [m for m in read_ros2_messages(path) if m.channel.topic == "/diagnostics"]
    first = {s.name: s for s in diags[0].decoded_message.status}
    assert set(first) == (
        {"armfusion: heading"}
        | {f"armfusion: joint {j}" for j in arm.joint_names}
        | {f"armfusion: sensor {s}" for s in run.sensor_names}
    )
    seen = set()
    for d in diags:
        t = d.decoded_message.header.stamp.sec + d.decoded_message.header.stamp.nanosec * 1e-9
        i = int(np.argmin(np.abs(run.t_s - t)))
        st = {s.name: s for s in d.decoded_message.status}
        heading = HEADING_STATUS[run.heading_status[i]]
        assert st["armfusion: heading"].message == heading
        assert st["armfusion: heading"].level == HEADING_LEVEL[heading]
        seen.add(heading)
        for j, name in enumerate(arm.joint_names):
            flag = JOINT_FLAGS[run.flags[i, j]]
            assert (st[f"armfusion: joint {name}"].message, st[f"armfusion: joint {name}"].level) == (
                flag,
                JOINT_LEVEL[flag],
            )
    # every change of the heading's status in the run is in the diagnostics
    assert seen == {HEADING_STATUS[c] for c in np.unique(run.heading_status)}
    assert HEADING_LEVEL["calibrating"] == 2  # ERROR: no absolute heading yet, the status to ignore it in
    # a joint whose angle no sensor reads is ERROR, never a usable WARN: its position is not to be used
    assert all(JOINT_LEVEL[f] == 2 for f in ("gimbal_lock", "unobserved", "ambiguous", "out_of_limits"))


def test_the_track_command_writes_a_ros2_bag_by_its_name(tmp_path: Path) -> None:
    rec = tmp_path / "r.mcap"
    assert (
        runner.invoke(
            app, ["simulate", "--scenario", "startup", "--duration", "6", "--out", str(rec)]
        ).exit_code
        == 0
    )
    r = runner.invoke(app, ["track", str(rec), "--out", str(tmp_path / "est.ros2.mcap"), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["out"].endswith("est.ros2.mcap")
    with open(tmp_path / "est.ros2.mcap", "rb") as f:
        assert make_reader(f).get_header().profile == "ros2"


# ---------------------------------------------------------------------------- the URDF


@pytest.mark.parametrize("config", ["wmra", "crs_a465", "imu_rig_yaw", "wmra with DH offsets"])
def test_the_urdf_puts_every_sensor_and_the_flange_where_the_arm_model_does(
    tmp_path: Path, config: str
) -> None:
    import yaml
    import yourdfpy
    from armfusion.models.kinematics import chain_poses, sensor_poses

    if config == "wmra with DH offsets":  # each joint's zero turned: the URDF's origins carry it
        cfg = yaml.safe_load(Path(load_arm("wmra").source).read_text())
        cfg["arm"]["dh"]["offset_deg"] = [10, -20, 30, 0, 5, 0, -45]
        config = str(tmp_path / "offsets.yaml")
        Path(config).write_text(yaml.safe_dump(cfg))
    path = tmp_path / "arm.urdf"
    r = runner.invoke(app, ["info", "--config", config, "--urdf", str(path), "--json"])
    assert r.exit_code == 0, r.output and json.loads(r.stdout)["urdf"] == str(path)
    arm = load_arm(config)
    robot = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    assert [j for j in robot.actuated_joint_names] == list(arm.joint_names)
    rng = np.random.default_rng(3)
    names = [s.name for s in arm.sensors]
    for _ in range(5):
        q = rng.uniform(arm.min_rad, arm.max_rad)
        robot.update_cfg(dict(zip(arm.joint_names, q, strict=True)))
        R_0S, p_0S = sensor_poses(arm, q, names)
        for k, name in enumerate(names):
            T = robot.get_transform(frame_to=name, frame_from=BASE_FRAME)
            np.testing.assert_allclose(T[:3, :3], R_0S[0, k], atol=1e-9, err_msg=name)
            np.testing.assert_allclose(T[:3, 3], p_0S[0, k], atol=1e-9, err_msg=name)
        if arm.n_joints:
            poses = chain_poses(arm, q)
            T = robot.get_transform(frame_to="flange", frame_from=BASE_FRAME)
            np.testing.assert_allclose(T[:3, :3], poses.R_0L[0, -1], atol=1e-9)
            np.testing.assert_allclose(T[:3, 3], poses.p_0L_m[0, -1], atol=1e-9)
    lim = {j.name: (j.limit.lower, j.limit.upper) for j in robot.robot.joints if j.type == "revolute"}
    assert lim == {j.name: (j.min_rad, j.max_rad) for j in arm.joints}




def test_the_urdf_is_xml_a_strict_parser_reads(tmp_path: Path) -> None:
    # before: its comment held "--urdf", which no XML comment may: ElementTree (and armfusion's
    # own URDF reader) refused the file, "not well-formed (invalid token): line 3, column 64"
    import xml.etree.ElementTree as ET

    src = tmp_path / "my--arm-.yaml"  # a source path with "--" in it lands in the comment too
    src.write_text(Path(load_arm("wmra").source).read_text())
    path = tmp_path / "arm.urdf"
    r = runner.invoke(app, ["info", "--config", str(src), "--urdf", str(path)])
    assert r.exit_code == 0, r.output
    robot = ET.parse(path).getroot()
    assert [j.get("name") for j in robot.iter("joint") if j.get("type") == "revolute"] == \
        list(load_arm("wmra").joint_names)
