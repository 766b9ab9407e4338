"""How fast a ROS bag imports: a 10-minute WMRA bag, five 100 Hz sensor topics and the encoders'
joint states, on one core.

Simulates `daily-use` on the WMRA for ``--duration`` s at 100 Hz and writes it with rosbags'
own writer as a rosbag2 bag (MCAP storage, and SQLite3 storage): the four link
accelerometers as ``geometry_msgs/Vector3Stamped`` (counts), the base IMU as
``sensor_msgs/Imu`` (m/s^2, rad/s), the encoders as ``sensor_msgs/JointState`` (rad). Then
times ``armfusion.fusion.importing.bag.import_bag`` (best of ``--repeats``), and, in the same process on
the same bag, the straightforward way as the baseline: rosbags' reader and its deserialiser
for every message, the fields gathered into arrays. Checks that both give the same values.
BLAS is held to one thread. Writes its section of docs/benchmarks.md.

    python tools/bench_import_bag.py [--duration 600] [--repeats 2] [--no-write] [--out FILE]
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.importing.bag import import_bag  # noqa: E402
from armfusion.fusion.importing.column_map import parse_column_map  # noqa: E402
from armfusion.models.sensor_models import stream_models  # noqa: E402
from armfusion.models.simulator import simulate  # noqa: E402

from tools.benchdoc import machine_line, publish  # noqa: E402

TARGET_S = 10.0
ACCELS = ("acc1", "acc2", "acc3", "acc4")
XYZ = ("x", "y", "z")
BAG_MAP = {
    "time": {"stamp": "header"},
    "streams": {
        **{a: {"topic": f"/arm/{a}", "fields": [f"vector.{c}" for c in XYZ], "unit": "counts"}
           for a in ACCELS},
        "imu_acc": {"topic": "/imu/data", "fields": [f"linear_acceleration.{c}" for c in XYZ],
                    "unit": "m/s^2"},
        "imu_gyro": {"topic": "/imu/data", "fields": [f"angular_velocity.{c}" for c in XYZ],
                     "unit": "rad/s"},
        "enc": {"topic": "/joint_states", "fields": [f"position[j{k}]" for k in range(1, 8)], "unit": "rad"},
    },
}


def write_bag(path: Path, arm, rec, storage) -> int:
    """The recording as a rosbag2 bag by rosbags' writer; returns the messages written."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T, H, V = (ts.types[k] for k in ("builtin_interfaces/msg/Time", "std_msgs/msg/Header",
                                     "geometry_msgs/msg/Vector3"))
    Q, imu_t, v3s, js = (ts.types[k] for k in (
        "geometry_msgs/msg/Quaternion", "sensor_msgs/msg/Imu", "geometry_msgs/msg/Vector3Stamped",
        "sensor_msgs/msg/JointState"))
    models = stream_models(arm)
    t_ns = np.rint(rec.get("enc").t_s * 1e9).astype(np.int64).tolist()
    acc_si = models["imu_acc"].from_counts(rec.get("imu_acc").values) * 9.80665
    gyro_si = models["imu_gyro"].from_counts(rec.get("imu_gyro").values)
    q_enc = rec.get("enc").values / models["enc"].gain
    names = list(arm.joint_names)
    cov, empty = np.zeros(9), np.zeros(0)
    n = 0
    with Writer(path, version=9, storage_plugin=storage) as w:
        conns = {a: w.add_connection(f"/arm/{a}", v3s.__msgtype__, typestore=ts) for a in ACCELS}
        c_imu = w.add_connection("/imu/data", imu_t.__msgtype__, typestore=ts)
        c_js = w.add_connection("/joint_states", js.__msgtype__, typestore=ts)
        accs = {a: rec.get(a).values.astype(float) for a in ACCELS}
        for i, t in enumerate(t_ns):
            stamp = T(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
            for a in ACCELS:
                m = v3s(header=H(stamp=stamp, frame_id=a), vector=V(*accs[a][i]))
                w.write(conns[a], t, ts.serialize_cdr(m, v3s.__msgtype__))
            m = imu_t(header=H(stamp=stamp, frame_id="imu"), orientation=Q(0.0, 0.0, 0.0, 1.0),
                      orientation_covariance=np.r_[-1.0, np.zeros(8)], angular_velocity=V(*gyro_si[i]),
                      angular_velocity_covariance=cov, linear_acceleration=V(*acc_si[i]),
                      linear_acceleration_covariance=cov)
            w.write(c_imu, t, ts.serialize_cdr(m, imu_t.__msgtype__))
            m = js(header=H(stamp=stamp, frame_id=""), name=names, position=q_enc[i], velocity=empty,
                   effort=empty)
            w.write(c_js, t, ts.serialize_cdr(m, js.__msgtype__))
            n += 6
    return n


def baseline(path: Path) -> dict[str, np.ndarray]:
    """rosbags' reader and deserialiser, message by message, the mapped fields into arrays."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    rows: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        for c, _, raw in r.messages():
            m = r.deserialize(raw, c.msgtype)
            if c.msgtype == "geometry_msgs/msg/Vector3Stamped":
                rows.setdefault(c.topic.rsplit("/", 1)[1], []).append((m.vector.x, m.vector.y, m.vector.z))
            elif c.msgtype == "sensor_msgs/msg/Imu":
                a, g = m.linear_acceleration, m.angular_velocity
                rows.setdefault("imu", []).append((a.x, a.y, a.z, g.x, g.y, g.z))
            else:
                rows.setdefault("enc", []).append(tuple(m.position))
    return {k: np.array(v) for k, v in rows.items()}


def timed(fn, repeats: int):
    """The best wall time and the best CPU time (this process) of ``repeats`` runs, and the result."""
    wall, cpu, out = float("inf"), float("inf"), None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    return (wall, cpu), out


def main() -> None:
    from rosbags.rosbag2 import StoragePlugin

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="simulated seconds")
    ap.add_argument("--repeats", type=int, default=2, help="best of this many imports")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md")
    ap.add_argument("--out", type=Path, help="write the section to this file instead")
    a = ap.parse_args()
    arm = load_arm("wmra")
    rec, _ = simulate(arm, "daily-use", a.duration, 100.0, seed=1)
    cmap = parse_column_map(BAG_MAP, "bench")
    rows = []
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as d:
        for label, storage in (("MCAP", StoragePlugin.MCAP), ("SQLite3", StoragePlugin.SQLITE3)):
            bag = Path(d) / label
            t0 = time.perf_counter()
            n = write_bag(bag, arm, rec, storage)
            t_write = time.perf_counter() - t0
            size_mb = sum(f.stat().st_size for f in bag.iterdir()) / 1e6
            t_ours, result = timed(lambda bag=bag: import_bag(bag, cmap, arm, "wmra"), a.repeats)
            t_base, base = timed(lambda bag=bag: baseline(bag), 1)
            got = result.recording
            for acc in ACCELS:
                assert np.array_equal(got.get(acc).values, base[acc]), acc
            gain = stream_models(arm)["enc"].gain
            assert np.array_equal(got.get("enc").values, np.rint(base["enc"] * gain))
            assert np.array_equal(got.get("enc").values, rec.get("enc").values)
            print(f"{label}: {n} messages, {size_mb:.0f} MB (written by rosbags in {t_write:.1f} s); import "
                  f"{t_ours[1]:.2f} s CPU ({t_ours[0]:.2f} s wall), rosbags message by message "
                  f"{t_base[1]:.2f} s CPU ({t_base[0]:.2f} s wall)", flush=True)
            rows.append((label, n, size_mb, t_ours, t_base))
    body = ["## Importing a ROS bag (`tools/bench_import_bag.py`)\n",
            f"WMRA, {a.duration:g} s of `daily-use` at 100 Hz written by rosbags' own writer as a rosbag2 "
            "bag: five sensor topics (acc1…acc4 as `geometry_msgs/Vector3Stamped`, the base IMU as "
            "`sensor_msgs/Imu`) and the encoders' `sensor_msgs/JointState`, all at 100 Hz; `armfusion "
            f"import`'s `import_bag` (best of {a.repeats}) against rosbags' reader and deserialiser message "
            "by message (the fields gathered into arrays) on the same bag, in the same process, one BLAS "
            f"thread; both give the same values (checked); {machine_line()}. CPU time (this process's) is "
            "the figure compared, as the machine is shared (load average "
            f"{load_before:.1f} before, {os.getloadavg()[0]:.1f} after); wall time beside it.\n",
            "| storage | messages | size | import, CPU (wall) | rosbags, message by message | ratio |",
            "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for label, n, size_mb, t_ours, t_base in rows:
        body.append(f"| {label} | {n:,} | {size_mb:.0f} MB | {t_ours[1]:.2f} s ({t_ours[0]:.2f} s) | "
                    f"{t_base[1]:.2f} s ({t_base[0]:.2f} s) | {t_base[1] / t_ours[1]:.1f}x |")
    worst = max(r[3][1] for r in rows)
    body.append(f"\nTarget: a 10-minute bag with five 100 Hz sensor topics in under {TARGET_S:g} s on one "
                f"core: **{worst:.2f} s** of CPU at worst ({'met' if worst < TARGET_S else 'not met'}).")
    publish("bench_import_bag", "\n".join(body), a.out, quick=a.no_write)
    if a.no_write:
        print("\n".join(body))


if __name__ == "__main__":
    main()
