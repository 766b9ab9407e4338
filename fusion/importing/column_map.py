"""The column map: which columns of a foreign file make which stream of an arm, in which unit.

A YAML file (read as boundedly and safely as a config: :func:`armfusion.fusion.configfile.read_yaml`)::

    time: {column: all_time, unit: s}          # or {rate_hz: 100}, or {rate_hz: {variable: sampling_rate}}
    start_row: {variable: data_line}           # optional: 1-based first row of the data (or a number)
    streams:
      shaft:      {columns: [all_accel_2_x, all_accel_2_y, all_accel_2_z], unit: g}
      imu_gyro:   {columns: ["imu_gyr[:, 0]", "imu_gyr[:, 1]", "imu_gyr[:, 2]"], unit: rad/s}
      enc:        {columns: [all_encoder], unit: deg, max_rounding_counts: 0.5}
      true_q:     {columns: [all_encoder], unit: deg}
    absent:                                    # optional: streams the config needs that the file lacks
      enc: the IMU was moved by hand; no arm

A column is ``NAME`` (a column vector, a CSV column) or ``NAME[:, K]`` (column K, from 0, of a
2-D variable or dataset).

A ROS bag's map names a topic and its fields instead of columns, and which time stamps a sample::

    time: {stamp: header}          # the messages' header stamp; or receive (the bag's log time)
    streams:
      imu_acc: {topic: /imu/data, fields: [linear_acceleration.x, linear_acceleration.y,
                                           linear_acceleration.z], unit: m/s^2, frame_id: imu_link}
      enc:     {topic: /joint_states, fields: ["position[j1]", "position[j2]"], unit: rad}
      acc1:    {topic: /acc1, fields: ["data[0]", "data[1]", "data[2]"], unit: counts, stamp: receive}

``frame_id`` (optional) is checked against every message; ``stamp`` on a stream overrides the
map's (a topic without a header, such as ``std_msgs/Float64MultiArray``, takes ``receive``).

Units are those of :mod:`armfusion.sensors.units` (``counts`` too). Every problem of the file is
reported together, naming the key (:class:`ColumnMapError`); what the map says about a
particular arm (a stream the config lacks, a unit of another quantity) is checked by
:mod:`armfusion.fusion.importing.to_stream` when the map meets the config.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from armfusion.fusion.configfile import read_yaml
from armfusion.fusion.shipped import shipped_config_dir
from armfusion.models.arm_config import ConfigError
from armfusion.sensors.foreign import parse_address
from armfusion.sensors.foreign.rosbag import check_field
from armfusion.sensors.samples import clipped_repr
from armfusion.sensors.units import UnitError, canonical_unit_name, quantity_of

IMPORTS_DIR = "imports"
"""The shipped column maps' folder inside the shipped configs (``config/imports/``)."""

DEFAULT_MAX_ROUNDING_COUNTS = 0.05
"""How far an angle may be from a whole encoder count, in counts, before the import refuses to
round it (unless the map's stream allows more): a twentieth of a count is what a float of the
angle the encoder gave is off its count by when the file stored it with a few decimals more
than the count needs."""

STAMPS = ("header", "receive")
"""What stamps a bag's sample: the message's header stamp, or the time the bag received it."""

MAX_STREAMS = 64
MAX_COLUMNS = 64


class ColumnMapError(ValueError):
    """Every problem of one column map, reported together (file, key, what is wrong)."""

    def __init__(self, source: str, problems: list[str]):
        self.problems = problems
        n = len(problems)
        super().__init__(f"{n} problem{'s' if n != 1 else ''} in column map {source}:\n"
                         + "\n".join(f"  - {p}" for p in problems))


@dataclass(frozen=True)
class StreamSource:
    """One stream's source: its columns (addresses, in channel order; a bag's: the fields of
    ``topic``) and their unit; for a bag, the frame id its messages must carry (None: any)
    and the stamp it takes (``header`` or ``receive``; None: the map's)."""

    columns: tuple[str, ...]
    unit: str
    max_rounding_counts: float = DEFAULT_MAX_ROUNDING_COUNTS
    topic: str | None = None
    frame_id: str | None = None
    stamp: str | None = None


@dataclass(frozen=True)
class ColumnMap:
    """A validated column map (see the module's docstring)."""

    source: str
    streams: dict[str, StreamSource]
    time_column: str | None = None
    time_unit: str = "s"
    rate_hz: float | None = None
    rate_variable: str | None = None
    start_row: int | None = None
    start_row_variable: str | None = None
    absent: dict[str, str] = field(default_factory=dict)
    stamp: str | None = None
    """A bag's map: the time that stamps a sample (``header`` or ``receive``); None for a table's."""

    @property
    def is_bag(self) -> bool:
        return self.stamp is not None

    def topics(self) -> dict[str, list[str]]:
        """A bag's map: every topic read and its fields, once each, in map order."""
        out: dict[str, list[str]] = {}
        for s in self.streams.values():
            fields = out.setdefault(s.topic, [])
            for f in s.columns:
                if f not in fields:
                    fields.append(f)
        return out

    def columns(self) -> list[str]:
        """Every column the map reads, once each, in map order."""
        cols = [self.time_column] if self.time_column else []
        for s in self.streams.values():
            cols.extend(s.columns)
        return list(dict.fromkeys(cols))

    def scalars(self) -> list[str]:
        """The file's variables of one value that the map reads (start row, rate)."""
        return [v for v in (self.start_row_variable, self.rate_variable) if v]


def resolve_map_path(name_or_path: str | Path) -> Path:
    """A path as given if it exists, else a shipped map by name (``imu-rig`` or ``imu-rig.yaml``)."""
    p = Path(name_or_path)
    if p.exists():
        return p
    shipped = shipped_config_dir() / IMPORTS_DIR
    for cand in (shipped / f"{name_or_path}.yaml", shipped / str(name_or_path)):
        if cand.is_file():
            return cand
    names = sorted(x.stem for x in shipped.glob("*.yaml")) if shipped.is_dir() else []
    raise FileNotFoundError(f"no column map {str(name_or_path)!r}: not a file, and not one of the "
                            f"shipped maps {names}")


def load_column_map(name_or_path: str | Path) -> ColumnMap:
    """Read and validate a column map; :class:`ColumnMapError` lists every problem."""
    path = resolve_map_path(name_or_path)
    try:
        data = read_yaml(path)
    except ConfigError as e:
        raise ColumnMapError(str(path), [str(p).split(": ", 1)[1] for p in e.problems]) from None
    return parse_column_map(data, str(path))


def _unit(value: Any, key: str, problems: list[str]) -> str | None:
    try:
        return canonical_unit_name(value)
    except UnitError as e:
        problems.append(f"{key}: {e}")
        return None


def _positive_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and 0 < value < float("inf")


def _variable(value: Any) -> str | None:
    """``{variable: NAME}`` -> NAME."""
    if isinstance(value, dict) and set(value) == {"variable"} and isinstance(value["variable"], str):
        return value["variable"]
    return None


class _MapTime(NamedTuple):
    """A map's ``time``: a column and its unit, a rate (a number or a file's variable), or a
    bag's stamp (``header`` or ``receive``); the fields the map does not give are None."""

    column: str | None = None
    unit: str = "s"
    rate_hz: float | None = None
    rate_variable: str | None = None
    stamp: str | None = None


def _map_time(time: Any, problems: list[str]) -> _MapTime:
    """The map's ``time`` entry, checked (a problem appended, defaults returned, when it is wrong)."""
    if not isinstance(time, dict) or not ({"column", "unit"} == set(time) or set(time) == {"rate_hz"}
                                          or set(time) == {"stamp"}):
        problems.append("time: give {column: NAME, unit: s|ms|us|ns} or {rate_hz: NUMBER} "
                        "(or {rate_hz: {variable: NAME}}); for a ROS bag {stamp: header|receive}")
        return _MapTime()
    if "stamp" in time:
        if time["stamp"] in STAMPS:
            return _MapTime(stamp=time["stamp"])
        problems.append(f"time.stamp: header or receive (got {clipped_repr(time['stamp'])})")
        return _MapTime(stamp="header")
    if "column" in time:
        column = _address(time["column"], "time.column", problems)
        unit = _unit(time["unit"], "time.unit", problems) or "s"
        if quantity_of(unit) != "time":
            problems.append(f"time.unit: {unit!r} is not a unit of time (s, ms, us, ns)")
        return _MapTime(column=column, unit=unit)
    rate_variable = _variable(time["rate_hz"])
    if rate_variable is not None:
        return _MapTime(rate_variable=rate_variable)
    if _positive_number(time["rate_hz"]):
        return _MapTime(rate_hz=float(time["rate_hz"]))
    problems.append(f"time.rate_hz: a rate > 0 in Hz, or {{variable: NAME}} "
                    f"(got {clipped_repr(time['rate_hz'])})")
    return _MapTime()


def _map_start_row(start: Any, problems: list[str]) -> tuple[int | None, str | None]:
    """The map's ``start_row``: a row number from 1, or the file's variable that holds one."""
    if start is None:
        return None, None
    variable = _variable(start)
    if variable is not None:
        return None, variable
    if isinstance(start, int) and not isinstance(start, bool) and start >= 1:
        return start, None
    problems.append(f"start_row: a row number from 1, or {{variable: NAME}} (got {clipped_repr(start)})")
    return None, None


def _stream_source(entry: dict, key: str, bag: bool, problems: list[str]) -> StreamSource | None:
    """One stream's entry (a table's columns or a bag's topic and fields, its unit and
    rounding), checked; None when a problem leaves it unusable."""
    keys = ({"topic", "fields", "unit", "max_rounding_counts", "frame_id", "stamp"} if bag
            else {"columns", "unit", "max_rounding_counts"})
    extra = set(entry) - keys
    if extra:
        problems.append(f"{key}: unknown key(s) {', '.join(sorted(map(str, extra)))} "
                        f"(expected {', '.join(sorted(keys))}"
                        + (")" if bag else "; topic and fields take time: {stamp: header|receive})"))
    cols = entry.get("fields" if bag else "columns")
    if (not isinstance(cols, list) or not cols or len(cols) > MAX_COLUMNS):
        problems.append(f"{key}.{'fields' if bag else 'columns'}: a list of 1 to {MAX_COLUMNS} "
                        f"{'fields' if bag else 'columns'}")
        return None
    if bag:
        bag_source = _bag_source(entry, key, problems)
        addresses = [_field(c, f"{key}.fields", problems) for c in cols]
    else:
        bag_source = {}
        addresses = [_address(c, f"{key}.columns", problems) for c in cols]
    unit = _unit(entry.get("unit"), f"{key}.unit", problems) if "unit" in entry else None
    if "unit" not in entry:
        problems.append(f"{key}.unit: missing: say what unit the columns hold (g, deg/s, counts...)")
    rounding = entry.get("max_rounding_counts", DEFAULT_MAX_ROUNDING_COUNTS)
    if not (isinstance(rounding, int | float) and not isinstance(rounding, bool)
            and 0 <= rounding <= 0.5):
        problems.append(f"{key}.max_rounding_counts: a number of counts from 0 to 0.5 "
                        f"(got {clipped_repr(rounding)})")
        rounding = DEFAULT_MAX_ROUNDING_COUNTS
    if unit is None or None in addresses:
        return None
    return StreamSource(tuple(addresses), unit, float(rounding), **bag_source)


def _map_streams(raw: Any, bag: bool, problems: list[str]) -> dict[str, StreamSource]:
    """The map's ``streams``: every stream name -> its source, the ones with a problem left out."""
    if not isinstance(raw, dict) or not raw:
        problems.append("streams: a mapping of stream name -> {columns: [...], unit: ...}")
        return {}
    if len(raw) > MAX_STREAMS:
        problems.append(f"streams: {len(raw)} streams; a map takes at most {MAX_STREAMS}")
        return {}
    streams: dict[str, StreamSource] = {}
    for name, entry in raw.items():
        key = f"streams.{clipped_repr(name)[1:-1] if isinstance(name, str) else clipped_repr(name)}"
        if not isinstance(name, str) or not isinstance(entry, dict):
            problems.append(f"{key}: each stream is NAME: {{columns: [...], unit: ...}}")
            continue
        source = _stream_source(entry, key, bag, problems)
        if source is not None:
            streams[name] = source
    return streams


def _map_absent(absent: Any, streams: dict[str, StreamSource], problems: list[str]) -> dict[str, str]:
    """The map's ``absent``: stream name -> why the file lacks it (none of them under ``streams``)."""
    absent = absent or {}
    if not isinstance(absent, dict) or not all(isinstance(k, str) and isinstance(v, str) and v.strip()
                                               for k, v in absent.items()):
        problems.append("absent: a mapping of stream name -> why the file lacks it")
        return {}
    for name in absent:
        if name in streams:
            problems.append(f"absent.{name}: the map gives this stream under streams too")
    return dict(absent)


def parse_column_map(data: Any, source: str) -> ColumnMap:
    """A :class:`ColumnMap` from the YAML's data, or :class:`ColumnMapError` listing every
    problem (in the map's order: its keys, time, start row, streams, absent)."""
    problems: list[str] = []
    if not isinstance(data, dict):
        raise ColumnMapError(source, ["the file should be a mapping with 'time' and 'streams'"])
    for key in data:
        if key not in ("time", "start_row", "streams", "absent"):
            problems.append(f"{clipped_repr(key)}: unknown key (expected time, start_row, streams, absent)")
    time = _map_time(data.get("time"), problems)
    start_row, start_variable = _map_start_row(data.get("start_row"), problems)
    streams = _map_streams(data.get("streams"), time.stamp is not None, problems)
    absent = _map_absent(data.get("absent"), streams, problems)
    if time.stamp is not None and (start_row is not None or start_variable is not None):
        problems.append("start_row: a ROS bag's map has none (a sample is a message)")
    if problems:
        raise ColumnMapError(source, problems)
    return ColumnMap(source, streams, time.column, time.unit, time.rate_hz, time.rate_variable, start_row,
                     start_variable, absent, time.stamp)


def _bag_source(entry: dict, key: str, problems: list[str]) -> dict:
    """A bag stream's topic, frame id and stamp (checked)."""
    topic = entry.get("topic")
    if not (isinstance(topic, str) and 0 < len(topic) <= 256 and topic.strip() == topic):
        problems.append(f"{key}.topic: a topic name (got {clipped_repr(topic)})")
    frame = entry.get("frame_id")
    if frame is not None and not (isinstance(frame, str) and len(frame) <= 256):
        problems.append(f"{key}.frame_id: the frame id every message must carry (got {clipped_repr(frame)})")
    stamp = entry.get("stamp")
    if stamp is not None and stamp not in STAMPS:
        problems.append(f"{key}.stamp: header or receive (got {clipped_repr(stamp)})")
    return {"topic": topic, "frame_id": frame, "stamp": stamp}


def _field(value: Any, key: str, problems: list[str]) -> str | None:
    why = check_field(value)
    if why:
        problems.append(f"{key}: {why}")
        return None
    return value


def _address(value: Any, key: str, problems: list[str]) -> str | None:
    try:
        return str(parse_address(value))
    except ValueError as e:
        problems.append(f"{key}: {e}")
        return None
