"""A tracked run's estimates as a rosbag2 MCAP file (``armfusion track REC --out EST.ros2.mcap``):
the messages a ROS 2 system takes as they are (:data:`TOPICS`).

Per fused instant, stamped with its time:

- ``/armfusion/joint_states`` (``sensor_msgs/JointState``): the config's joint names and their
  angles (rad), for robot_state_publisher with the URDF of ``armfusion info --urdf``;
- ``/armfusion/joint_states/sigma`` (``sensor_msgs/JointState``): the same names, each
  ``position`` the joint's one-sigma (rad);
- ``/armfusion/heading`` (``sensor_msgs/Imu``, frame :data:`BASE_FRAME`): the base's orientation
  in ENU (REP 103: roll, pitch and the heading as ENU yaw), its covariance as REP 145 has it,
  the angular velocity and linear acceleration marked not estimated
  (:mod:`~armfusion.fusion.ros2.conventions`);

and ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, the ROS convention for health) at
the first instant, whenever a status changes and at least once a second: one status for the
heading, one per joint (its flag), one per sensor (:func:`levels`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from armfusion.fusion.ros2.conventions import enu_quaternion_xyzw, not_estimated, orientation_covariance

BASE_FRAME = "arm_base"
"""The frame of the heading's orientation: the arm's base frame, the URDF's root link."""
JOINTS_TOPIC = "/armfusion/joint_states"
SIGMA_TOPIC = "/armfusion/joint_states/sigma"
HEADING_TOPIC = "/armfusion/heading"
DIAGNOSTICS_TOPIC = "/diagnostics"
JOINT_STATE, IMU, DIAGNOSTICS = ("sensor_msgs/msg/JointState", "sensor_msgs/msg/Imu",
                                 "diagnostic_msgs/msg/DiagnosticArray")
TOPICS: dict[str, str] = {JOINTS_TOPIC: JOINT_STATE, SIGMA_TOPIC: JOINT_STATE, HEADING_TOPIC: IMU,
                          DIAGNOSTICS_TOPIC: DIAGNOSTICS}
"""Every topic written and its type."""
DIAGNOSTICS_PERIOD_S = 1.0
"""Diagnostics are written at least this often (and at every change of a status)."""

OK, WARN, ERROR, STALE = 0, 1, 2, 3
"""``diagnostic_msgs/DiagnosticStatus`` levels."""
HEADING_LEVEL = {"compass_fused": OK, "gyro_only": WARN, "disturbed": WARN, "calibrating": ERROR}
"""The heading's status as a level: ``calibrating`` (no absolute heading yet) is ERROR, the
status a consumer of the heading should ignore it in."""
JOINT_LEVEL = {"ok": OK, "converging": WARN, "reacquiring": WARN, "ill_conditioned": WARN,
               "gimbal_lock": ERROR, "out_of_limits": ERROR, "unobserved": ERROR, "ambiguous": ERROR}
"""A joint whose angle no sensor reads (``gimbal_lock``, ``unobserved``: its sigma covers its
limits) or whose branch is not known is ERROR: its ``position`` is not to be used."""
SENSOR_LEVEL = {"ok": OK, "rejecting": WARN, "stale": STALE, "stuck": ERROR, "dead": ERROR, "absent": STALE}


def levels() -> dict[str, dict[str, int]]:
    """Each status word's level, per kind (for docs and tests)."""
    return {"heading": dict(HEADING_LEVEL), "joint": dict(JOINT_LEVEL), "sensor": dict(SENSOR_LEVEL)}


def _stamp(w, t_ns: int):
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return w.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def _header(w, t_ns: int, frame: str):
    return w.make("std_msgs/msg/Header", stamp=_stamp(w, t_ns), frame_id=frame)


def _status(w, level: int, name: str, message: str, hardware_id: str, values: dict):
    kv = [w.make("diagnostic_msgs/msg/KeyValue", key=k, value=str(v)) for k, v in values.items()]
    return w.make("diagnostic_msgs/msg/DiagnosticStatus", level=np.uint8(level), name=name, message=message,
                  hardware_id=hardware_id, values=kv)


def write_estimates_bag(run, path: str | Path, arm_name: str) -> dict[str, int]:
    """Write ``run`` (:class:`armfusion.fusion.tracking.run.TrackRun`) to ``path`` (see the module's
    docstring); returns the messages written per topic. Times before 0 s are refused: a ROS
    stamp is unsigned seconds."""
    from armfusion.fusion.tracking.estimate import HEADING_STATUS, NORTH
    from armfusion.sensors.ros2_mcap import Ros2McapWriter

    t_ns = np.rint(np.asarray(run.t_s, float) * 1e9).astype(np.int64)
    if t_ns.size and t_ns[0] < 0:
        raise ValueError(f"the run starts at t = {run.t_s[0]:.3f} s; a ROS time stamp cannot be before 0 s")
    names = [str(n) for n in run.joint_names]
    quat = enu_quaternion_xyzw(run.rpy_rad)
    cov = orientation_covariance(run.rpy_sigma_rad)
    none = not_estimated()
    heading_codes = (run.heading_status if run.heading_status is not None
                     else np.full(run.steps, HEADING_STATUS.index("gyro_only")))
    north = NORTH[bool(run.true_north)]
    last_diag_ns, last_codes = 0, None
    with Ros2McapWriter(path) as w:
        empty = np.zeros(0)
        for i in range(run.steps):
            t = int(t_ns[i])
            if names:
                w.write(JOINTS_TOPIC, JOINT_STATE, t, w.make(
                    JOINT_STATE, header=_header(w, t, ""), name=names,
                    position=np.asarray(run.q_rad[i], float), velocity=empty, effort=empty))
                w.write(SIGMA_TOPIC, JOINT_STATE, t, w.make(
                    JOINT_STATE, header=_header(w, t, ""), name=names,
                    position=np.asarray(run.sigma_rad[i], float), velocity=empty, effort=empty))
            x, y, z, qw = (float(v) for v in quat[i])
            w.write(HEADING_TOPIC, IMU, t, w.make(
                IMU, header=_header(w, t, BASE_FRAME),
                orientation=w.make("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=qw),
                orientation_covariance=cov[i],
                angular_velocity=w.make("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0),
                angular_velocity_covariance=none,
                linear_acceleration=w.make("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0),
                linear_acceleration_covariance=none))
            codes = (int(heading_codes[i]), tuple(int(c) for c in run.flags[i]),
                     tuple(int(c) for c in run.sensor_status[i]), int(run.magnetic[i]))
            if last_codes is None or codes != last_codes or t - last_diag_ns >= DIAGNOSTICS_PERIOD_S * 1e9:
                last_diag_ns, last_codes = t, codes
                w.write(DIAGNOSTICS_TOPIC, DIAGNOSTICS, t, _diagnostics(w, run, i, t, codes, arm_name, north))
        return dict(w.counts)


def _diagnostics(w, run, i: int, t: int, codes: tuple, arm_name: str, north: str):
    """Instant ``i``'s ``DiagnosticArray``: the heading, each joint, each sensor."""
    from armfusion.fusion.tracking.estimate import HEADING_STATUS, yaw_enu_rad
    from armfusion.fusion.tracking.settings import JOINT_FLAGS, SENSOR_STATUS

    heading = HEADING_STATUS[codes[0]]
    r, p, h = (float(v) for v in run.rpy_rad[i])
    sr, sp, sh = (float(v) for v in run.rpy_sigma_rad[i])
    statuses = [_status(w, HEADING_LEVEL[heading], "armfusion: heading", heading, arm_name, {
        "heading_status": heading, "north": north, "yaw_enu_deg": f"{np.degrees(yaw_enu_rad(h)):.3f}",
        "heading_sigma_deg": f"{np.degrees(sh):.4f}", "roll_deg": f"{np.degrees(r):.4f}",
        "roll_sigma_deg": f"{np.degrees(sr):.4f}", "pitch_deg": f"{np.degrees(p):.4f}",
        "pitch_sigma_deg": f"{np.degrees(sp):.4f}", "magnetic_disturbance": str(bool(codes[3] & 1)).lower(),
        "magnetic_recovery": str(bool(codes[3] & 2)).lower(),
        "gyro_bias_rad_s": " ".join(f"{v:.6g}" for v in run.gyro_bias_rad_s[i])})]
    for j, name in enumerate(run.joint_names):
        flag = JOINT_FLAGS[codes[1][j]]
        statuses.append(_status(w, JOINT_LEVEL[flag], f"armfusion: joint {name}", flag, arm_name, {
            "flag": flag, "angle_deg": f"{np.degrees(run.q_rad[i, j]):.4f}",
            "sigma_deg": f"{np.degrees(run.sigma_rad[i, j]):.4f}"}))
    for k, sensor in enumerate(run.sensor_names):
        status = SENSOR_STATUS[codes[2][k]]
        statuses.append(_status(w, SENSOR_LEVEL[status], f"armfusion: sensor {sensor}", status, arm_name,
                                {"status": status}))
    return w.make(DIAGNOSTICS, header=_header(w, t, ""), status=statuses)
