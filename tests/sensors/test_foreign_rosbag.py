"""The bag reader's layout of a message (where each number lies) agrees with rosbags' own
serialiser, whatever the frame id's length (CDR's alignment) and whichever of JointState's
arrays are empty or filled, in ROS 2's CDR and ROS 1's encoding."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from armfusion.sensors.foreign.rosbag import _layout
from rosbags.typesys import Stores, get_typestore

TYPE = "sensor_msgs/msg/JointState"


@pytest.mark.parametrize("store", [Stores.ROS2_HUMBLE, Stores.ROS1_NOETIC])
def test_every_number_of_a_joint_state_is_where_rosbags_put_it(store) -> None:
    ts = get_typestore(store)
    ros1 = store == Stores.ROS1_NOETIC
    rng = np.random.default_rng(0)
    H, T = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    checked = 0
    for frame, n_pos, n_vel, n_eff in itertools.product(
        ["", "a", "ab", "abc", "abcd"], [0, 1, 3], [0, 1, 2], [0, 2]
    ):
        header = (
            H(seq=0, stamp=T(sec=1, nanosec=2), frame_id=frame)
            if ros1
            else H(stamp=T(sec=1, nanosec=2), frame_id=frame)
        )
        m = ts.types[TYPE](
            header=header,
            name=[f"j{i}" for i in range(max(n_pos, n_vel, n_eff))],
            position=rng.normal(size=n_pos),
            velocity=rng.normal(size=n_vel),
            effort=rng.normal(size=n_eff),
        )
        raw = bytes(ts.serialize_ros1(m, TYPE) if ros1 else ts.serialize_cdr(m, TYPE))
        lay = _layout(ts.fielddefs, TYPE, raw, ros1)
        assert lay.strings["header.frame_id"] == frame
        for field in ("position", "velocity", "effort"):
            values = getattr(m, field)
            assert lay.locate(f"{field}[{len(values)}]") is None  # one past the end is no number
            for k, v in enumerate(values):
                off, dt = lay.locate(f"{field}[{k}]")
                assert np.frombuffer(raw[off : off + 8], dt)[0] == v
                checked += 1
    assert checked == 5 * (4 * 3 * 2 + 3 * 3 * 2 + 2 * 3 * 3)  # every number of every mix
