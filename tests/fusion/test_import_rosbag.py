"""`armfusion import` of a ROS bag: rosbag2 (MCAP and SQLite3 storage) and ROS 1 bags, written
here by `rosbags`' own writers (an implementation independent of the reader's fast path),
come back as the samples they were made from: a simulated WMRA recording bit for bit where
the message types hold the same numbers, and the real BROAD and rig slices tracked to the
same figures as their native import. Frame ids, stamps, unknown types and malformed
messages are refused or said by topic and message index."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.importing.bag import import_bag
from armfusion.fusion.importing.column_map import ColumnMapError, load_column_map, parse_column_map
from armfusion.fusion.importing.run import import_recording
from armfusion.fusion.importing.to_stream import ImportMapError
from armfusion.models.sensor_models import stream_models
from armfusion.models.simulator import simulate
from armfusion.sensors.foreign import ForeignFileError
from armfusion.sensors.recording import read_recording
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

DATA = Path(__file__).resolve().parents[1] / "data"
runner = CliRunner()
TS2 = get_typestore(Stores.ROS2_HUMBLE)
TS1 = get_typestore(Stores.ROS1_NOETIC)


# ---------------------------------------------------------------------------- writing bags (rosbags' writers)


def _stamp(ts, t_ns: int):
    return ts.types["builtin_interfaces/msg/Time"](
        sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000)
    )


def _header(ts, t_ns: int, frame: str, seq: int = 0):
    H = ts.types["std_msgs/msg/Header"]
    if "seq" in [f[0] for f in ts.fielddefs["std_msgs/msg/Header"][1]]:
        return H(seq=seq, stamp=_stamp(ts, t_ns), frame_id=frame)
    return H(stamp=_stamp(ts, t_ns), frame_id=frame)


def _vec(ts, v):
    return ts.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def msg_vector3(ts, t_ns, frame, v):
    return ts.types["geometry_msgs/msg/Vector3Stamped"](header=_header(ts, t_ns, frame), vector=_vec(ts, v))


def msg_imu(ts, t_ns, frame, acc, gyro):
    cov = np.zeros(9)
    q = ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    return ts.types["sensor_msgs/msg/Imu"](
        header=_header(ts, t_ns, frame),
        orientation=q,
        orientation_covariance=np.r_[-1.0, np.zeros(8)],
        angular_velocity=_vec(ts, gyro),
        angular_velocity_covariance=cov,
        linear_acceleration=_vec(ts, acc),
        linear_acceleration_covariance=cov,
    )


def msg_mag(ts, t_ns, frame, b_t):
    return ts.types["sensor_msgs/msg/MagneticField"](
        header=_header(ts, t_ns, frame), magnetic_field=_vec(ts, b_t), magnetic_field_covariance=np.zeros(9)
    )


def msg_joints(ts, t_ns, names, q):
    return ts.types["sensor_msgs/msg/JointState"](
        header=_header(ts, t_ns, ""),
        name=list(names),
        position=np.asarray(q, float),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def msg_array(ts, values):
    L = ts.types["std_msgs/msg/MultiArrayLayout"]
    return ts.types["std_msgs/msg/Float64MultiArray"](
        layout=L(dim=[], data_offset=0), data=np.asarray(values, float)
    )


def write_bag(path: Path, topics: dict[str, tuple[str, list]], fmt: str) -> Path:
    """``topics[name] = (msgtype, [(receive_ns, message), ...])`` into a bag of ``fmt``
    (``mcap``, ``sqlite3``: rosbag2 directories; ``ros1``: a .bag), with rosbags' writers."""
    items = sorted(
        ((int(t), name, m) for name, (_, msgs) in topics.items() for t, m in msgs), key=lambda x: x[0]
    )
    if fmt == "ros1":
        path = path.with_suffix(".bag")
        with Writer1(path) as w:
            conns = {n: w.add_connection(n, typ, typestore=TS1) for n, (typ, _) in topics.items()}
            for t, name, m in items:
                w.write(conns[name], t, TS1.serialize_ros1(m, topics[name][0]))
        return path
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    with Writer2(path, version=9, storage_plugin=plugin) as w:
        conns = {n: w.add_connection(n, typ, typestore=TS2) for n, (typ, _) in topics.items()}
        for t, name, m in items:
            w.write(conns[name], t, TS2.serialize_cdr(m, topics[name][0]))
    return path


def _ns(t_s: np.ndarray) -> list[int]:
    return np.rint(np.asarray(t_s) * 1e9).astype(np.int64).tolist()


# ---------------------------------------------------------------------------- the simulated WMRA


@pytest.fixture(scope="module")
def wmra():
    arm = load_arm("wmra")
    rec, _ = simulate(arm, "static-poses", seed=1, duration_s=3.0)
    return arm, rec


WMRA_MAP = {
    "time": {"stamp": "header"},
    "streams": {
        **{
            f"acc{k}": {
                "topic": f"/arm/acc{k}",
                "fields": ["vector.x", "vector.y", "vector.z"],
                "unit": "counts",
                "frame_id": f"acc{k}",
            }
            for k in range(1, 5)
        },
        "imu_acc": {
            "topic": "/imu/data_raw",
            "fields": ["linear_acceleration.x", "linear_acceleration.y", "linear_acceleration.z"],
            "unit": "m/s^2",
            "frame_id": "imu",
        },
        "imu_gyro": {
            "topic": "/imu/data_raw",
            "fields": ["angular_velocity.x", "angular_velocity.y", "angular_velocity.z"],
            "unit": "rad/s",
        },
        "imu_mag": {
            "topic": "/imu/mag",
            "fields": ["magnetic_field.x", "magnetic_field.y", "magnetic_field.z"],
            "unit": "T",
            "frame_id": "imu",
        },
        # the encoder counts' angles, joints named and listed in another order than the config's
        "enc": {"topic": "/joint_states", "fields": [f"position[j{k}]" for k in range(1, 8)], "unit": "rad"},
        "true_q": {
            "topic": "/truth",
            "fields": [f"data[{k}]" for k in range(7)],
            "unit": "rad",
            "stamp": "receive",
        },
    },
}


def wmra_bag(path: Path, arm, rec, fmt: str) -> Path:
    ts = TS1 if fmt == "ros1" else TS2
    models = stream_models(arm)
    t_ns = _ns(rec.get("enc").t_s)
    topics: dict[str, tuple[str, list]] = {}
    for k in range(1, 5):
        s = rec.get(f"acc{k}")
        topics[f"/arm/acc{k}"] = (
            "geometry_msgs/msg/Vector3Stamped",
            [(t, msg_vector3(ts, t, f"acc{k}", v)) for t, v in zip(_ns(s.t_s), s.values, strict=True)],
        )
    acc_si = models["imu_acc"].from_counts(rec.get("imu_acc").values) * 9.80665  # g -> m/s^2
    gyro_si = models["imu_gyro"].from_counts(rec.get("imu_gyro").values)
    topics["/imu/data_raw"] = (
        "sensor_msgs/msg/Imu",
        [(t, msg_imu(ts, t, "imu", a, g)) for t, a, g in zip(t_ns, acc_si, gyro_si, strict=True)],
    )
    mag_t = models["imu_mag"].from_counts(rec.get("imu_mag").values) * 1e-6  # uT -> T
    topics["/imu/mag"] = (
        "sensor_msgs/msg/MagneticField",
        [(t, msg_mag(ts, t, "imu", b)) for t, b in zip(t_ns, mag_t, strict=True)],
    )
    gain = models["enc"].gain
    q_enc = rec.get("enc").values / gain  # counts -> rad, with the config's counts_per_rev
    order = [6, 0, 5, 1, 4, 2, 3]
    topics["/joint_states"] = (
        "sensor_msgs/msg/JointState",
        [
            (t, msg_joints(ts, t, [f"j{k + 1}" for k in order], q[order]))
            for t, q in zip(t_ns, q_enc, strict=True)
        ],
    )
    topics["/truth"] = (
        "std_msgs/msg/Float64MultiArray",
        [(t, msg_array(ts, q)) for t, q in zip(t_ns, rec.get("true_q").values, strict=True)],
    )
    return write_bag(path, topics, fmt)


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3", "ros1"])
def test_a_simulated_wmra_bag_imports_to_the_samples_it_was_made_from(tmp_path: Path, wmra, fmt: str) -> None:
    arm, rec = wmra
    bag = wmra_bag(tmp_path / "wmra", arm, rec, fmt)
    cmap = parse_column_map(WMRA_MAP, "wmra-bag.yaml")
    result = import_bag(bag, cmap, arm, "wmra")
    got = result.recording
    # counts carried as counts (Vector3Stamped) and angles to whole counts: bit for bit, times too
    for name in ("acc1", "acc2", "acc3", "acc4", "enc", "true_q"):
        assert got.get(name).values.dtype == rec.get(name).values.dtype, name
        np.testing.assert_array_equal(got.get(name).values, rec.get(name).values, err_msg=name)
        np.testing.assert_array_equal(got.get(name).t_s, rec.get(name).t_s, err_msg=name)
    # SI units through the config's nominal gain: the counts, to float rounding
    for name in ("imu_acc", "imu_gyro", "imu_mag"):
        np.testing.assert_allclose(
            got.get(name).values, rec.get(name).values, rtol=0, atol=1e-6, err_msg=name
        )
        np.testing.assert_array_equal(got.get(name).t_s, rec.get(name).t_s)
    assert result.summary["streams"]["enc"]["rounding_max_counts"] < 1e-6
    assert result.changes == ()
    topic = result.summary["topics"]["/imu/data_raw"]
    assert topic["messages"] == len(rec.get("imu_acc")) and topic["rate_hz"] == pytest.approx(100.0)
    assert topic["gaps"] == 0 and topic["frame_ids"] == {"imu": len(rec.get("imu_acc"))}
    assert result.summary["topics"]["/truth"]["stamp"] == "receive"


def test_a_bag_with_a_gap_and_a_stamp_out_of_order_says_both_by_topic_and_message(
    tmp_path: Path, wmra
) -> None:
    arm, rec = wmra
    stamps = [int(t) for k, t in enumerate(_ns(np.arange(50) * 0.01)) if k not in (20, 21, 22)]  # 3 not sent
    stamps[31] = stamps[30]  # message 31 (from 0) carries message 30's stamp once more
    msgs = [(k * 10_000_000, msg_vector3(TS2, t, "acc1_link", [1.0, 2.0, 3.0])) for k, t in enumerate(stamps)]
    bag = write_bag(tmp_path / "b", {"/arm/acc1": ("geometry_msgs/msg/Vector3Stamped", msgs)}, "mcap")
    m = {
        "time": {"stamp": "header"},
        "streams": {
            "acc1": {"topic": "/arm/acc1", "fields": ["vector.x", "vector.y", "vector.z"], "unit": "counts"}
        },
        "absent": {k: "not in this test bag" for k in ("enc", "acc2", "acc3", "acc4")},
    }
    result = import_bag(bag, parse_column_map(m, "m.yaml"), arm, "wmra")
    assert (
        "acc1: dropped 1 message(s) of /arm/acc1 whose header stamp is not after every earlier one (each a "
        "repeat of the one before): messages 31 (t = 0.330000 s) (from 0)"
    ) in result.changes
    topic = result.summary["topics"]["/arm/acc1"]
    assert (topic["gaps"], topic["missing_samples"]) == (2, 4)  # 3 not sent, 1 dropped
    assert len(result.recording.get("acc1")) == 46


def _one_topic_map(**stream) -> dict:
    return {
        "time": {"stamp": "header"},
        "streams": {
            "acc1": {
                "topic": "/arm/acc1",
                "fields": ["vector.x", "vector.y", "vector.z"],
                "unit": "counts",
                **stream,
            }
        },
        "absent": {k: "not in this test bag" for k in ("enc", "acc2", "acc3", "acc4")},
    }


def test_a_frame_id_other_than_the_maps_is_refused_naming_topic_and_message(tmp_path: Path, wmra) -> None:
    arm, _ = wmra
    msgs = [
        (k * 10_000_000, msg_vector3(TS2, k * 10_000_000, "acc1_link" if k != 7 else "base", [0, 0, 1]))
        for k in range(10)
    ]
    bag = write_bag(tmp_path / "b", {"/arm/acc1": ("geometry_msgs/msg/Vector3Stamped", msgs)}, "mcap")
    with pytest.raises(
        ImportMapError,
        match=r"stream acc1: topic /arm/acc1 message 7 \(from 0\) has frame_id "
        r"'base'; the map says 'acc1_link'",
    ):
        import_bag(bag, parse_column_map(_one_topic_map(frame_id="acc1_link"), "m.yaml"), arm, "wmra")


def test_an_unknown_type_a_missing_topic_and_a_headerless_stamp_are_refused_clearly(
    tmp_path: Path, wmra
) -> None:
    arm, _ = wmra
    twist = TS2.types["geometry_msgs/msg/Twist"](linear=_vec(TS2, [0, 0, 0]), angular=_vec(TS2, [0, 0, 0]))
    bag = write_bag(
        tmp_path / "b",
        {
            "/arm/acc1": ("geometry_msgs/msg/Twist", [(0, twist)]),
            "/arr": ("std_msgs/msg/Float64MultiArray", [(0, msg_array(TS2, [1, 2, 3]))]),
        },
        "mcap",
    )
    with pytest.raises(
        ForeignFileError,
        match=r"topic /arm/acc1 is geometry_msgs/msg/Twist; the import reads "
        r"sensor_msgs/msg/Imu, sensor_msgs/msg/MagneticField",
    ):
        import_bag(bag, parse_column_map(_one_topic_map(), "m.yaml"), arm, "wmra")
    with pytest.raises(ForeignFileError, match=r"no topic '/nope'; the bag has '/arm/acc1', '/arr'"):
        import_bag(bag, parse_column_map(_one_topic_map(topic="/nope"), "m.yaml"), arm, "wmra")
    arr = _one_topic_map(topic="/arr", fields=["data[0]", "data[1]", "data[2]"])
    with pytest.raises(
        ImportMapError,
        match=r"topic /arr \(std_msgs/msg/Float64MultiArray\) has no header "
        r"stamp: give the stream stamp: receive",
    ):
        import_bag(bag, parse_column_map(arr, "m.yaml"), arm, "wmra")
    arr["streams"]["acc1"]["stamp"] = "receive"
    assert import_bag(bag, parse_column_map(arr, "m.yaml"), arm, "wmra").recording.get(
        "acc1"
    ).values.tolist() == [[1, 2, 3]]
    arr["streams"]["acc1"]["fields"][2] = "data[3]"
    with pytest.raises(
        ForeignFileError,
        match=r"topic /arr \(std_msgs/msg/Float64MultiArray\): message 0 "
        r"\(from 0\) has no field 'data\[3\]'; its numbers: "
        r"layout.data_offset, data\[K\]",
    ):
        import_bag(bag, parse_column_map(arr, "m.yaml"), arm, "wmra")


def test_a_malformed_message_is_refused_by_topic_and_index(tmp_path: Path, wmra) -> None:
    arm, _ = wmra
    bag = tmp_path / "b"
    good = TS2.serialize_cdr(msg_vector3(TS2, 0, "acc1_link", [1, 2, 3]), "geometry_msgs/msg/Vector3Stamped")
    with Writer2(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/arm/acc1", "geometry_msgs/msg/Vector3Stamped", typestore=TS2)
        for k in range(5):
            w.write(c, k * 10_000_000, bytes(good) if k != 3 else bytes(good)[:-10])  # message 3 cut short
    with pytest.raises(
        ForeignFileError,
        match=r"topic /arm/acc1 \(geometry_msgs/msg/Vector3Stamped\): message 3 "
        r"\(from 0\) does not decode",
    ):
        import_bag(bag, parse_column_map(_one_topic_map(), "m.yaml"), arm, "wmra")


def test_a_file_that_is_not_a_bag_is_refused_naming_it(tmp_path: Path, wmra) -> None:
    arm, _ = wmra
    (tmp_path / "x.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(ForeignFileError, match=r"x\.mcap: not a readable rosbag2, MCAP storage \("):
        import_bag(tmp_path / "x.mcap", parse_column_map(_one_topic_map(), "m.yaml"), arm, "wmra")


def test_a_bag_map_and_a_table_map_each_refuse_the_others_file(tmp_path: Path, wmra) -> None:
    arm, _ = wmra
    (tmp_path / "t.csv").write_text("t,a\n0,1\n")
    with pytest.raises(
        ImportMapError, match=r"names topics and fields \(a ROS bag's map\), but .*t\.csv is not a ROS bag"
    ):
        import_recording(tmp_path / "t.csv", parse_column_map(_one_topic_map(), "m.yaml"), arm, "wmra")
    table = parse_column_map(
        {
            "time": {"column": "t", "unit": "s"},
            "streams": {"acc1": {"columns": ["a", "a", "a"], "unit": "counts"}},
        },
        "t.yaml",
    )
    with pytest.raises(ImportMapError, match=r"is a ROS bag, but column map t\.yaml names columns"):
        import_bag(tmp_path / "b.mcap", table, arm, "wmra")


def test_a_bag_map_is_checked_like_any_map() -> None:
    with pytest.raises(ColumnMapError) as e:
        parse_column_map(
            {
                "time": {"stamp": "sent"},
                "start_row": 3,
                "streams": {
                    "acc1": {
                        "topic": "/a",
                        "fields": ["vector.x", "x y"],
                        "unit": "counts",
                        "columns": ["a"],
                        "stamp": "later",
                    }
                },
            },
            "m.yaml",
        )
    text = str(e.value)
    for said in (
        "time.stamp: header or receive (got 'sent')",
        "streams.acc1: unknown key(s) columns",
        "streams.acc1.fields: 'x y' is not a field",
        "streams.acc1.stamp: header or receive (got 'later')",
        "start_row: a ROS bag's map has none",
    ):
        assert said in text, said


# ---------------------------------------------------------------------------- the real slices, as bags


def _broad_bag(tmp_path: Path, fmt: str) -> Path:
    import h5py

    with h5py.File(DATA / "broad" / "02_undisturbed_slow_rotation_B_6s_moving.hdf5") as f:
        acc, gyr, mag, rate = (
            f["imu_acc"][()],
            f["imu_gyr"][()],
            f["imu_mag"][()],
            float(f.attrs["sampling_rate"]),
        )
    t_ns = _ns(np.arange(len(acc)) / rate)
    ts = TS2
    return write_bag(
        tmp_path / "broad",
        {
            "/imu/data_raw": (
                "sensor_msgs/msg/Imu",
                [
                    (int(t), msg_imu(ts, int(t), "imu_link", a, g))
                    for t, a, g in zip(t_ns, acc, gyr, strict=True)
                ],
            ),
            "/imu/mag": (
                "sensor_msgs/msg/MagneticField",
                [(int(t), msg_mag(ts, int(t), "imu_link", m * 1e-6)) for t, m in zip(t_ns, mag, strict=True)],
            ),
        },
        fmt,
    )


BROAD_BAG_MAP = {
    "time": {"stamp": "header"},
    "streams": {
        "imu_acc": {
            "topic": "/imu/data_raw",
            "fields": [f"linear_acceleration.{a}" for a in "xyz"],
            "unit": "m/s^2",
            "frame_id": "imu_link",
        },
        "imu_gyro": {
            "topic": "/imu/data_raw",
            "fields": [f"angular_velocity.{a}" for a in "xyz"],
            "unit": "rad/s",
        },
        "imu_mag": {"topic": "/imu/mag", "fields": [f"magnetic_field.{a}" for a in "xyz"], "unit": "T"},
    },
    "absent": {"enc": "BROAD has no arm and no encoder (an IMU moved by hand)"},
}


def _track(rec: Path, config: str, *extra: str) -> dict:
    r = runner.invoke(app, ["track", str(rec), "--config", config, "--json", *extra])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


def _same_figures(a: dict, b: dict) -> None:
    """The figures ``track`` reports, alike to what a person reads (four significant digits;
    the bag's stamps are whole nanoseconds, the source's times floats a few 1e-15 s off them,
    and a value through m/s^2 and back differs in its last bit)."""
    assert (a["steps"], a["rejections"], a["start"]["flags"]) == (
        b["steps"],
        b["rejections"],
        b["start"]["flags"],
    )
    assert a["start"]["t_start_s"] == pytest.approx(b["start"]["t_start_s"], abs=1e-6)
    for k in (
        "roll_rad",
        "pitch_rad",
        "heading_rad",
        "roll_sigma_rad",
        "pitch_sigma_rad",
        "heading_sigma_rad",
    ):
        assert a["final"][k] == pytest.approx(b["final"][k], rel=1e-4, abs=1e-9), k
    np.testing.assert_allclose(a["final"]["q_rad"], b["final"]["q_rad"], rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(a["final"]["sigma_rad"], b["final"]["sigma_rad"], rtol=1e-4)
    for k in ("rms_error_deg", "heading_rms_deg"):
        if k in a:
            assert a[k] == pytest.approx(b[k], rel=1e-4), k


def test_the_broad_slice_as_a_bag_imports_and_tracks_to_the_native_imports_figures(tmp_path: Path) -> None:
    native = tmp_path / "native.mcap"
    r = runner.invoke(
        app,
        [
            "import",
            str(DATA / "broad" / "02_undisturbed_slow_rotation_B_6s_moving.hdf5"),
            "--map",
            "broad",
            "--config",
            "broad_imu",
            "--out",
            str(native),
        ],
    )
    assert r.exit_code == 0, r.output
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(BROAD_BAG_MAP))
    bag = _broad_bag(tmp_path, "mcap")
    out = tmp_path / "from_bag.mcap"
    r = runner.invoke(
        app,
        ["import", str(bag), "--map", str(tmp_path / "m.yaml"), "--config", "broad_imu", "--out", str(out)],
    )
    assert r.exit_code == 0, r.output
    assert (
        "/imu/data_raw (sensor_msgs/msg/Imu, frame imu_link): 1714 messages, 285.7 Hz by its header stamp, "
        "no gap" in r.output
    )
    a, b = read_recording(native), read_recording(out)
    for name in ("imu_acc", "imu_gyro", "imu_mag"):
        np.testing.assert_allclose(b.get(name).t_s, a.get(name).t_s, rtol=0, atol=0.5e-9)  # ns stamps
        np.testing.assert_allclose(b.get(name).values, a.get(name).values, rtol=1e-12)
    _same_figures(_track(native, "broad_imu"), _track(out, "broad_imu"))


def test_the_rig_slice_as_a_ros1_bag_imports_and_tracks_to_the_native_imports_figures(tmp_path: Path) -> None:
    import scipy.io

    src = DATA / "imu-rig" / "raw_roll_slow_20s.mat"
    native = import_recording(
        src, load_column_map("imu-rig"), load_arm("imu_rig_roll"), "imu_rig_roll"
    ).recording
    raw = scipy.io.loadmat(src)
    start = int(raw["data_line"].ravel()[0]) - 1
    t_ns = _ns(raw["all_time"].ravel()[start:])
    g, dps = 9.80665, np.pi / 180

    def col(name: str) -> np.ndarray:
        return raw[name].ravel()[start:]

    ts = TS1
    imu = {
        k: [
            (
                int(t),
                msg_imu(
                    ts,
                    int(t),
                    f"imu{k}",
                    [col(f"all_accel_{k}_{a}")[i] * g for a in "xyz"],
                    [col(f"all_gyro_{k}_{a}")[i] * dps for a in "xyz"],
                ),
            )
            for i, t in enumerate(t_ns)
        ]
        for k in (1, 2)
    }
    enc = [
        (int(t), msg_joints(ts, int(t), ["shaft"], [np.radians(col("all_encoder")[i])]))
        for i, t in enumerate(t_ns)
    ]
    bag = write_bag(
        tmp_path / "rig",
        {
            "/frame/imu": ("sensor_msgs/msg/Imu", imu[1]),
            "/shaft/imu": ("sensor_msgs/msg/Imu", imu[2]),
            "/joint_states": ("sensor_msgs/msg/JointState", enc),
        },
        "ros1",
    )

    def imu_streams(topic: str) -> dict:
        return {
            "acc": {"topic": topic, "fields": [f"linear_acceleration.{a}" for a in "xyz"], "unit": "m/s^2"},
            "gyro": {"topic": topic, "fields": [f"angular_velocity.{a}" for a in "xyz"], "unit": "rad/s"},
        }

    f, s = imu_streams("/frame/imu"), imu_streams("/shaft/imu")
    m = {
        "time": {"stamp": "header"},
        "streams": {
            "shaft": s["acc"],
            "shaft_gyro": s["gyro"],
            "imu_acc": f["acc"],
            "imu_gyro": f["gyro"],
            "enc": {
                "topic": "/joint_states",
                "fields": ["position[shaft]"],
                "unit": "rad",
                "max_rounding_counts": 0.5,
            },
            "true_q": {"topic": "/joint_states", "fields": ["position[shaft]"], "unit": "rad"},
        },
    }
    result = import_bag(bag, parse_column_map(m, "rig-bag.yaml"), load_arm("imu_rig_roll"), "imu_rig_roll")
    got = result.recording
    # the logger's repeated stamps are dropped as the .mat import drops them
    assert len(got.get("enc")) == len(native.get("enc")) and any(
        "dropped 5 message(s)" in c for c in result.changes
    )
    np.testing.assert_array_equal(got.get("enc").values, native.get("enc").values)
    for name in ("shaft", "shaft_gyro", "imu_acc", "imu_gyro"):
        np.testing.assert_allclose(got.get(name).values, native.get(name).values, rtol=1e-12, atol=1e-15)
    from armfusion.sensors.recording import write_recording

    write_recording(native, tmp_path / "native.mcap")
    write_recording(got, tmp_path / "bag.mcap")
    _same_figures(
        _track(tmp_path / "native.mcap", "imu_rig_roll", "--moving-start"),
        _track(tmp_path / "bag.mcap", "imu_rig_roll", "--moving-start"),
    )


def test_the_command_reads_a_bag_directory_and_its_storage_file_alike(tmp_path: Path, wmra) -> None:
    arm, rec = wmra
    bag = wmra_bag(tmp_path / "wmra", arm, rec, "sqlite3")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(WMRA_MAP))
    outs = []
    for k, src in enumerate((bag, next(bag.glob("*.db3")))):
        shutil.rmtree(tmp_path / f"o{k}", ignore_errors=True)
        outs.append(tmp_path / f"o{k}.csv")
        r = runner.invoke(
            app,
            [
                "import",
                str(src),
                "--map",
                str(tmp_path / "m.yaml"),
                "--config",
                "wmra",
                "--out",
                str(outs[-1]),
                "--json",
            ],
        )
        assert r.exit_code == 0, r.output
        assert json.loads(r.stdout)["format"] == (
            "rosbag2 directory" if k == 0 else "rosbag2, SQLite3 storage"
        )
    assert outs[0].read_text() == outs[1].read_text()


def test_the_shipped_ros2_map_imports_a_wmra_bag_through_the_command(tmp_path: Path, wmra) -> None:
    arm, rec = wmra
    bag = wmra_bag(tmp_path / "wmra", arm, rec, "mcap")
    out = tmp_path / "rec.mcap"
    r = runner.invoke(
        app, ["import", str(bag), "--map", "ros2-wmra", "--config", "wmra", "--out", str(out), "--json"]
    )
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["not_mapped"] == ["imu_temp", "true_q", "true_base"] and s["changes"] == []
    assert s["topics"]["/arm/acc3"]["frame_ids"] == {"acc3": len(rec.get("acc3"))}
    back = read_recording(out)
    for name in ("acc1", "acc2", "acc3", "acc4", "enc"):
        np.testing.assert_array_equal(back.get(name).values, rec.get(name).values, err_msg=name)
    np.testing.assert_allclose(back.get("imu_gyro").values, rec.get("imu_gyro").values, rtol=0, atol=1e-6)
