"""Estimates recorded as armfusion's own records (the JSON messages on ``estimates/joints``
and ``estimates/heading`` that ``armfusion record`` and ``track --out EST.mcap`` write) turned
into what :func:`armfusion.fusion.ros2.estimates_bag.write_estimates_bag` writes: so the live service's
estimates reach ROS 2 as a bag too (``armfusion record OUT.mcap --ros2-out EST.ros2.mcap``).

The two records of one estimate share its time stamp; an instant is taken where its heading
record is, with the joints record of the same stamp (an arm with joints: an instant without
one is left out and counted). A record that is not one (bad JSON, a missing field, an
unknown flag or status word) is refused naming its topic and its index.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.estimate import HEADING_STATUS, HEADING_TOPIC, JOINTS_TOPIC, NORTH
from armfusion.fusion.tracking.run import TrackRun
from armfusion.fusion.tracking.settings import JOINT_FLAGS, SENSOR_STATUS


class RecordsError(ValueError):
    """A recorded estimate that cannot be read as one, with its topic and index."""


def read_records(path: str | Path) -> tuple[list[dict], list[dict]]:
    """The joints and heading records of an MCAP file, in file order."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    joints: list[dict] = []
    headings: list[dict] = []
    counts = {JOINTS_TOPIC: 0, HEADING_TOPIC: 0}
    try:
        with open(path, "rb") as fh:
            for _schema, channel, message in make_reader(fh).iter_messages(topics=list(counts)):
                index = counts[channel.topic]
                counts[channel.topic] += 1
                try:
                    doc = json.loads(message.data)
                except (UnicodeDecodeError, json.JSONDecodeError) as e:
                    raise RecordsError(f"{path}: {channel.topic} message {index}: not JSON ({e})") from None
                if not isinstance(doc, dict):
                    raise RecordsError(f"{path}: {channel.topic} message {index}: not a record")
                (joints if channel.topic == JOINTS_TOPIC else headings).append(doc)
    except McapError as e:
        raise RecordsError(f"{path}: not a complete MCAP file ({e})") from None
    return joints, headings


def _code(words: tuple[str, ...], word, what: str, where: str) -> int:
    if word not in words:
        raise RecordsError(f"{where}: {what} {str(word)[:40]!r} is not one of {', '.join(words)}")
    return words.index(word)


class _HeadingRecord(NamedTuple):
    """One heading record read: its stamp (s), roll/pitch/heading and their sigmas (rad), the
    gyro's bias (rad/s), the magnetic bits (1 disturbance, 2 recovery), and the status and
    north words as their codes."""

    t_s: float
    rpy_rad: list[float]
    rpy_sigma_rad: list[float]
    gyro_bias_rad_s: list[float]
    magnetic: int
    status: int
    north: int


class _JointsRecord(NamedTuple):
    """One joints record read: the angles and their sigmas (rad), each joint's flag code and
    each sensor's status code (empty for an arm without joints)."""

    q_rad: Sequence[float] = ()
    sigma_rad: Sequence[float] = ()
    flags: Sequence[int] = ()
    sensor_status: Sequence[int] = ()


def _joints_by_time(joints: list[dict], source: str) -> dict[float, tuple[int, dict]]:
    """Each joints record, with its index, by its time stamp."""
    by_t: dict[float, tuple[int, dict]] = {}
    for i, j in enumerate(joints):
        try:
            by_t[float(j["t_s"])] = (i, j)
        except (KeyError, TypeError, ValueError):
            raise RecordsError(f"{source}: {JOINTS_TOPIC} message {i}: no time stamp t_s") from None
    return by_t


def _heading_record(h: dict, where: str) -> _HeadingRecord:
    """A heading record read, or :class:`RecordsError` naming ``where`` it is."""
    try:
        t = float(h["t_s"])
        rpy = [float(h["roll_rad"]), float(h["pitch_rad"]), float(h["heading_rad"])]
        rpy_sigma = [float(h[k]) for k in ("roll_sigma_rad", "pitch_sigma_rad", "heading_sigma_rad")]
        bias = [float(v) for v in h["gyro_bias_rad_s"]]
        magnetic = (1 if h["magnetic_disturbance"] else 0) | (2 if h["magnetic_recovery"] else 0)
        status = _code(HEADING_STATUS, h["heading_status"], "heading_status", where)
        north = _code(NORTH, h.get("north", "magnetic"), "north", where)
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, RecordsError):
            raise
        raise RecordsError(f"{where}: not a heading record ({type(e).__name__}: {str(e)[:80]})") from None
    if len(bias) != 3:
        raise RecordsError(f"{where}: gyro_bias_rad_s has {len(bias)} values, not 3")
    return _HeadingRecord(t, rpy, rpy_sigma, bias, magnetic, status, north)


def _joints_record(j: dict, names: tuple[str, ...], sensors: tuple[str, ...], where: str) -> _JointsRecord:
    """A joints record read for the joints ``names`` and the ``sensors`` of the first record,
    or :class:`RecordsError` naming ``where`` it is."""
    if tuple(j.get("joint_names", ())) != names:
        raise RecordsError(f"{where}: joint_names differ from the first record's")
    try:
        q = [float(v) for v in j["q_rad"]]
        sigma = [float(v) for v in j["sigma_rad"]]
        flags = [_code(JOINT_FLAGS, f, "flag", where) for f in j["flags"]]
        sensor_words = j.get("sensors", {})
        status_codes = [_code(SENSOR_STATUS, sensor_words.get(s, "absent"), f"sensor {s}'s status",
                              where) for s in sensors]
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        if isinstance(e, RecordsError):
            raise
        raise RecordsError(f"{where}: not a joints record ({type(e).__name__}: "
                           f"{str(e)[:80]})") from None
    if not len(q) == len(sigma) == len(flags) == len(names):
        raise RecordsError(f"{where}: q_rad, sigma_rad and flags must each have {len(names)} values")
    return _JointsRecord(q, sigma, flags, status_codes)


def _track_run(names: tuple[str, ...], sensors: tuple[str, ...], headings: list[_HeadingRecord],
               joints: list[_JointsRecord]) -> TrackRun:
    """The instants read (a heading record and the joints record of its stamp each) as a
    run's arrays (no counters: none were recorded)."""
    n, m, s = len(headings), len(names), len(sensors)

    def array(values: list, shape: tuple, dtype=float) -> np.ndarray:
        return np.array(values, dtype=dtype).reshape(shape)

    return TrackRun(
        joint_names=names, sensor_names=sensors, t_s=array([h.t_s for h in headings], (n,)),
        q_rad=array([j.q_rad for j in joints], (n, m)),
        sigma_rad=array([j.sigma_rad for j in joints], (n, m)),
        flags=array([j.flags for j in joints], (n, m), np.int8),
        rpy_rad=array([h.rpy_rad for h in headings], (n, 3)),
        rpy_sigma_rad=array([h.rpy_sigma_rad for h in headings], (n, 3)),
        gyro_bias_rad_s=array([h.gyro_bias_rad_s for h in headings], (n, 3)),
        magnetic=array([h.magnetic for h in headings], (n,), np.int8),
        sensor_status=array([j.sensor_status for j in joints], (n, s), np.int8),
        elapsed_s=0.0, counters={}, nis={},
        heading_status=array([h.status for h in headings], (n,), np.int8),
        true_north=bool(headings and headings[-1].north == NORTH.index("true")))


def run_from_records(joints: list[dict], headings: list[dict],
                     source: str = "records") -> tuple[TrackRun, int]:
    """The recorded estimates as a run (a :class:`~armfusion.fusion.tracking.run.TrackRun` with no
    counters: none were recorded), and how many heading records had no joints record at
    their stamp (left out; see the module's docstring)."""
    by_t = _joints_by_time(joints, source)
    names = tuple(str(n) for n in joints[0].get("joint_names", ())) if joints else ()
    sensors = tuple(str(s) for s in joints[0].get("sensors", {})) if joints else ()
    heading_rows: list[_HeadingRecord] = []
    joints_rows: list[_JointsRecord] = []
    left_out = 0
    for k, h in enumerate(headings):
        heading = _heading_record(h, f"{source}: {HEADING_TOPIC} message {k}")
        if names and heading.t_s not in by_t:
            left_out += 1
            continue
        if names:
            i, j = by_t[heading.t_s]
            joints_rows.append(_joints_record(j, names, sensors, f"{source}: {JOINTS_TOPIC} message {i}"))
        else:
            joints_rows.append(_JointsRecord())
        heading_rows.append(heading)
    return _track_run(names, sensors, heading_rows, joints_rows), left_out


def write_ros2_from_records(src: str | Path, out: str | Path,
                            arm_name: str) -> tuple[TrackRun, int, dict]:
    """Read the estimates recorded in ``src`` and write them to the rosbag2 MCAP ``out``;
    returns the run read, the heading records left out and the messages written per topic."""
    from armfusion.fusion.ros2.estimates_bag import write_estimates_bag

    joints, headings = read_records(src)
    if not headings:
        raise RecordsError(f"{src}: no estimate recorded (no {HEADING_TOPIC} message): was a fusion "
                           "node publishing?")
    run, left_out = run_from_records(joints, headings, str(src))
    return run, left_out, write_estimates_bag(run, out, arm_name)
