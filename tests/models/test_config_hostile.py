"""Configs against hostile and broken files: read safely and within bounds (a regular file,
no NUL, no key twice), every field (the ``calibration:`` block and the effects included)
checked at load against physical bounds, a URDF's geometry too, each problem one line
naming the file and key, values quoted short; fuzzing checks the loader's answers."""

from __future__ import annotations

import copy
import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import MAX_YAML_VALUES, load_arm, read_yaml
from armfusion.models.arm_config import ConfigError
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
runner = CliRunner()


@pytest.fixture
def wmra_dict() -> dict:
    return yaml.safe_load((CONFIG_DIR / "wmra.yaml").read_text())


def _write(path: Path, data) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def _load_problems(path: Path) -> tuple[str, list[str]]:
    with pytest.raises(ConfigError) as e:
        load_arm(path)
    return str(e.value), [str(p) for p in e.value.problems]


# ---------------------------------------------------------------------------- the YAML


def _alias_bomb() -> str:
    """Eight anchors, each a list of ten of the one before: 10^8 values in 300 bytes."""
    names = "abcdefgh"
    lines = ["a: &a [x,x,x,x,x,x,x,x,x,x]"]
    lines += [f"{n}: &{n} [{','.join([f'*{p}'] * 10)}]" for p, n in zip(names[:-1], names[1:], strict=True)]
    return "\n".join(lines) + "\narm: *h\n"


def test_an_alias_bomb_is_refused_within_a_second(tmp_path: Path) -> None:
    # before: 12 s, 1.7 GB and 254 MB of stderr (here: still running after 120 s at 2 GB)
    text = _alias_bomb()
    assert len(text) < 320
    p = tmp_path / "bomb.yaml"
    p.write_text(text)
    t0 = time.perf_counter()
    message, problems = _load_problems(p)
    assert time.perf_counter() - t0 < 1.0
    assert problems == [f"{p}: line 6: its aliases expand to more than {MAX_YAML_VALUES} values "
                        "(a YAML alias bomb?); a config is far smaller"]
    assert len(message) < 300


def test_aliases_that_expand_to_little_are_fine(tmp_path: Path, wmra_dict: dict) -> None:
    text = (CONFIG_DIR / "wmra.yaml").read_text().replace(
        "ready_pose_deg:", "ready_pose_deg: &ready")  # an anchor, unused: still the same config
    p = tmp_path / "a.yaml"
    p.write_text(text)
    assert load_arm(p).n_joints == 7
    q = tmp_path / "b.yaml"
    q.write_text("base: &v [1, 2, 3]\nuse: [*v, *v]\n")
    assert read_yaml(q) == {"base": [1, 2, 3], "use": [[1, 2, 3], [1, 2, 3]]}


def test_random_bytes_give_one_line_not_a_traceback(tmp_path: Path) -> None:
    p = tmp_path / "noise.yaml"
    p.write_bytes(b"\xff" + np.random.default_rng(5).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    _, problems = _load_problems(p)
    assert problems == [f"{p}: byte 0: not UTF-8 text; a config is a YAML text file"]
    r = runner.invoke(app, ["info", "--config", str(p)])
    assert r.exit_code == 2
    assert "not UTF-8 text" in r.output and "Traceback" not in r.output


def test_a_recursive_alias_and_deep_nesting_are_refused(tmp_path: Path) -> None:
    p = tmp_path / "r.yaml"
    p.write_text("arm: &a\n  self: *a\n")
    _, problems = _load_problems(p)
    assert problems == [f"{p}: line 1: a YAML alias refers to a node that contains it "
                        "(a recursive alias)"]
    p.write_text("[" * 2000 + "]" * 2000)
    _, problems = _load_problems(p)
    assert problems == [f"{p}: (file): nested too deeply to be a config"]


def test_not_yaml_names_the_line_and_a_huge_file_is_refused_unread(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("arm:\n  name: x\n   - oops: [\n")
    _, problems = _load_problems(p)
    assert problems == [f"{p}: line 3, column 10: not valid YAML: mapping values are not allowed here"]
    big = tmp_path / "big.yaml"
    big.write_text("arm: {}\n")
    os.truncate(big, 50_000_000)  # sparse
    _, problems = _load_problems(big)
    assert problems == [f"{big}: (file): 50000000 bytes is more than a config may be (4000000); "
                        "is it a config?"]


# ---------------------------------------------------------------------------- the fields


def test_an_unmodelled_error_of_lots_fails_at_load_naming_the_key(
    tmp_path: Path, wmra_dict: dict
) -> None:
    # before: `info` passed, and `track` failed later blaming the recording
    wmra_dict["calibration"]["accel_unmodelled_g"] = "lots"
    p = _write(tmp_path / "lots.yaml", wmra_dict)
    _, problems = _load_problems(p)
    assert problems == [f"{p}: calibration.accel_unmodelled_g: Input should be a valid number, "
                        "unable to parse string as a number (got 'lots')"]
    r = runner.invoke(app, ["info", "--config", str(p)])
    assert r.exit_code == 2 and "calibration.accel_unmodelled_g" in r.output


@pytest.mark.parametrize(
    "mutate, expected",
    [
        (lambda d: d["arm"]["dh"]["d_mm"].__setitem__(2, float("inf")),
         "arm.dh.d_mm[2]: Input should be a finite number (got inf)"),
        (lambda d: d["arm"]["joints"]["max_deg"].__setitem__(0, float("nan")),
         "arm.joints.max_deg[0]: Input should be a finite number (got nan)"),
        (lambda d: d["calibration"].__setitem__("accel_unmodelled_g", -0.01),
         "calibration.accel_unmodelled_g: Input should be greater than or equal to 0 (got -0.01)"),
        (lambda d: d["calibration"].__setitem__("mag_unmodelled_ut", -3),
         "calibration.mag_unmodelled_ut: Input should be greater than or equal to 0 (got -3)"),
        (lambda d: d["calibration"].__setitem__("accel_unmodelled_g_per_sensor", {"acc9": 0.01}),
         "calibration.accel_unmodelled_g_per_sensor.acc9: no such accelerometer in sensors "
         "(it has acc1, acc2, acc3, acc4, imu) (got 'acc9')"),
        (lambda d: d["calibration"].__setitem__("unmodeled_g", 0.01),
         "calibration.unmodeled_g: unknown key (got 0.01)"),
        (lambda d: d["calibration"].__setitem__(
            "correction_covariance", {"acc1": {"elements": ["a", "b"], "matrix": [[1.0, 0.0]]}}),
         "calibration.correction_covariance.acc1: matrix must be 2 x 2, one row and column per "
         "element"),
        (lambda d: d.__setitem__("effects", [{"effect": "accel_bias", "target": "acc1",
                                              "params": {"bias_g": [0.01, 0.0]}}]),
         "effects[0].params.bias_g: expected 3 values"),
    ],
)
def test_every_field_is_checked_at_load(tmp_path: Path, wmra_dict: dict, mutate, expected) -> None:
    d = copy.deepcopy(wmra_dict)
    mutate(d)
    p = _write(tmp_path / "c.yaml", d)
    _, problems = _load_problems(p)
    assert len(problems) == 1 and problems[0].startswith(f"{p}: {expected}"), problems


def test_a_huge_value_is_quoted_short(tmp_path: Path, wmra_dict: dict) -> None:
    wmra_dict["arm"]["ready_pose_deg"] = list(range(5000))
    p = _write(tmp_path / "long.yaml", wmra_dict)
    message, problems = _load_problems(p)
    assert problems[0].startswith(f"{p}: arm.ready_pose_deg: has 5000 entries; the arm has 7 "
                                  "joints (got [0, 1, 2, 3, 4, 5")
    assert "… (" in problems[0] and len(message) < 600


# ---------------------------------------------------------------------------- physical bounds
# every number of a config within what an arm on a chair can be; every name its own


def _spi(d: dict) -> None:
    d["sensors"][1]["bus"]["chip_select"] = 0  # acc1's


def _covariance(d: dict, matrix) -> None:
    d["calibration"]["correction_covariance"] = {"acc1": {"elements": ["a", "b"], "matrix": matrix}}


@pytest.mark.parametrize(
    "mutate, expected",
    [
        (lambda d: d["arm"]["dh"]["d_mm"].__setitem__(0, 1e308),
         "arm.dh.d_mm: entry 0 is 1e+308 mm; at most ±100000 mm"),
        (lambda d: d["arm"]["dh"]["a_mm"].__setitem__(0, 1e200),
         "arm.dh.a_mm: entry 0 is 1e+200 mm; at most ±100000 mm"),
        (lambda d: d["arm"]["dh"]["alpha_deg"].__setitem__(1, 1e9),
         "arm.dh.alpha_deg: entry 1 is 1000000000.0 deg; at most ±3600 deg"),
        (lambda d: d["arm"]["joints"]["counts_per_rev"].__setitem__(0, 1e-300),
         "arm.joints.counts_per_rev: counts per revolution must be from 1 to 2^32; entry 0 is 1e-300"),
        (lambda d: d["arm"]["joints"]["counts_per_rev"].__setitem__(3, 1e300),
         "arm.joints.counts_per_rev: counts per revolution must be from 1 to 2^32; entry 3 is 1e+300"),
        (lambda d: d["arm"]["joints"]["counts_per_rev"].__setitem__(0, 2**32),
         "arm.joints.counts_per_rev[0]: the joint's 210° are 2.51e+09 counts, more than the encoder feed's "
         "int32 holds either side of where it powered up (2147483647)"),
        (lambda d: d["sensors"][2].__setitem__("position_mm", [1e9, 0, 0]),
         "sensors[2].position_mm: entry 0 is 1000000000.0 mm; at most ±100000 mm"),
        (lambda d: d["sensors"][0].__setitem__("link", True),
         "sensors[0].link: Input should be a valid integer (got True)"),
        (lambda d: d["sensors"][0]["bus"].__setitem__("chip_select", "0"),
         "sensors[0].bus.chip_select: Input should be a valid integer (got '0')"),
        (_spi, "sensors[1].bus: the SPI bus 0 chip select 0 is sensors[0]'s already: one device each"),
        (lambda d: d["sensors"][3]["bus"].__setitem__("address", 0x53),
         "sensors[3].bus: the I2C bus 1 address 83 is sensors[2]'s already: one device each"),
        (lambda d: d["sensors"][0].__setitem__("name", "t"),
         "sensors[0].name: a recording's own stream is called 't'"),
        (lambda d: d["sensors"][0].__setitem__("name", "enc"),
         "sensors[0].name: a recording's own stream is called 'enc'"),
        (lambda d: d["sensors"][0].__setitem__("name", "true_q"),
         "sensors[0].name: a recording's own stream is called 'true_q'"),
        (lambda d: d["sensors"][0].__setitem__("name", "acc2_gyro"),
         "sensors[0].name: a recording's own stream is called 'acc2_gyro'"),
        (lambda d: d["sensors"][0].__setitem__("name", "imu2"),
         "sensors[0].name: a name starting with 'imu' is the base IMU's streams' (imu_acc…) in a recording"),
        (lambda d: _covariance(d, [[1.0, 2.0], [2.0, 1.0]]),
         "calibration.correction_covariance.acc1: matrix must be positive semi-definite"),
        # (two joints of one name: a --reference, --encoder-withheld or effect target meant either)
        (lambda d: d["arm"]["joints"].__setitem__("names", ["j1", "j1", "j3", "j4", "j5", "j6", "j7"]),
         "arm.joints.names: joint names must be unique; 'j1' is given twice"),
        (lambda d: d["sensors"][0].__setitem__("name", "a" * 5000),
         "sensors[0].name: String should have at most 64 characters"),
    ],
)
def test_every_number_within_physical_bounds_and_every_name_its_own(
    tmp_path: Path, wmra_dict: dict, mutate, expected: str
) -> None:
    # before: accepted by `info`; `simulate` then wrote every count as -2^63, or failed on shapes
    mutate(wmra_dict)
    p = _write(tmp_path / "c.yaml", wmra_dict)
    _, problems = _load_problems(p)
    assert any(q.startswith(f"{p}: {expected}") for q in problems), problems
    r = runner.invoke(app, ["info", "--config", str(p)])
    assert r.exit_code == 2 and "Traceback" not in r.output


def test_a_fits_semi_definite_covariance_is_taken(tmp_path: Path, wmra_dict: dict) -> None:
    # two elements known only together (one held to the other): semi-definite, and the file's
    # 6 digits leave its least eigenvalue at -5e-8
    _covariance(wmra_dict, [[1.0, 1.0], [1.0, 0.9999999]])
    assert load_arm(_write(tmp_path / "c.yaml", wmra_dict)).n_joints == 7


def test_an_integer_of_thousands_of_digits_is_refused_naming_its_line(tmp_path: Path) -> None:
    # before: Python's int() limit (4300 digits) was a ValueError traceback in every command
    text = (CONFIG_DIR / "wmra.yaml").read_text().replace("d_mm: [120.4,", "d_mm: [" + "9" * 5000 + ",")
    p = tmp_path / "c.yaml"
    p.write_text(text)
    line = text[: text.index("9" * 5000)].count("\n") + 1
    _, problems = _load_problems(p)
    assert problems == [f"{p}: line {line}: a number of 5000 characters (it starts '9999999999999999'); "
                        "no number needs so many"]
    r = runner.invoke(app, ["info", "--config", str(p)])
    assert r.exit_code == 2 and "Traceback" not in r.output


def test_more_sensors_than_a_recording_holds_are_refused_at_once(tmp_path: Path, wmra_dict: dict) -> None:
    # before: 2000 sensors took `info` 31 s to accept; `simulate` ran past a minute towards a
    # recording of 6000 columns that the reader refuses
    extra = {"type": "adxl345", "link": 2, "rotation": np.eye(3).tolist(), "position_mm": [0, 0, 0]}
    wmra_dict["sensors"] += [{"name": f"s{i}", **extra} for i in range(2000)]
    p = _write(tmp_path / "c.yaml", wmra_dict)
    t0 = time.perf_counter()
    _, problems = _load_problems(p)
    assert time.perf_counter() - t0 < 10
    assert problems == [f"{p}: sensors: 2005 sensors, more than a recording holds: each has at least 3 "
                        "columns, and a recording CSV at most 1000 (so at most 333 sensors)"]


def test_a_key_given_twice_is_refused_naming_both_lines(tmp_path: Path) -> None:
    text = (CONFIG_DIR / "wmra.yaml").read_text()
    text = text.replace("  name: WMRA-II\n", "  name: WMRA-II\n  name: other\n")
    p = tmp_path / "twice.yaml"
    p.write_text(text)
    _, problems = _load_problems(p)
    assert problems == [f"{p}: line 12: the key 'name' is given twice (first on line 11); a config gives "
                        "each key once"]


def test_a_nul_byte_a_device_and_a_fifo_are_refused_in_one_line(tmp_path: Path) -> None:
    p = tmp_path / "nul.yaml"
    p.write_bytes((CONFIG_DIR / "wmra.yaml").read_bytes().replace(b"name: WMRA-II", b"name: WMRA\0II"))
    _, problems = _load_problems(p)
    assert problems == [f"{p}: line 11: holds a NUL byte; a config is a YAML text file"]
    t0 = time.perf_counter()
    _, problems = _load_problems(Path("/dev/zero"))  # before: read without end
    not_a_file = "(file): not a regular file (a device, a FIFO, a directory); is it a config?"
    assert problems == [f"/dev/zero: {not_a_file}"]
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    _, problems = _load_problems(fifo)  # before: blocked until a writer came
    assert problems == [f"{fifo}: {not_a_file}"]
    assert time.perf_counter() - t0 < 1.0


_URDF_JOINT = ('<joint name="j{i}" type="revolute"><parent link="{parent}"/><child link="l{i}"/>'
               '<origin xyz="{xyz}" rpy="0 0 0"/><axis xyz="{axis}"/>'
               '<limit lower="-3" upper="3" effort="1" velocity="1"/></joint><link name="l{i}"/>')


def _urdf_config(tmp_path: Path, xyz: str = "0 0 0.1", axis: str = "0 0 1", head: str = "",
                 text: str | None = None) -> Path:
    if text is None:
        text = (head + '<robot name="r"><link name="base"/>'
                + _URDF_JOINT.format(i=1, parent="base", xyz=xyz, axis=axis)
                + _URDF_JOINT.format(i=2, parent="l1", xyz="0 0 0.3", axis="0 1 0") + "</robot>")
    (tmp_path / "r.urdf").write_text(text)
    cfg = {"arm": {"name": "r", "urdf": "r.urdf", "ready_pose_deg": [0, 0],
                   "joints": {"min_deg": [-90, -90], "max_deg": [90, 90], "counts_per_rev": [4096, 4096]}},
           "sensors": [{"name": "acc1", "type": "adxl345", "link": 2, "position_mm": [0, 0, 100]}]}
    return _write(tmp_path / "r.yaml", cfg)


@pytest.mark.parametrize("kw, expected", [
    (dict(xyz="nan 0 0"), "joint 'j1': its origin is not finite (xyz, rpy)"),
    (dict(xyz="1e308 0 0"), "joint 'j1': its origin is 1e+308 m away along an axis; a length is below 100 m"),
    (dict(xyz="0 200 0"), "joint 'j1': its origin is 200 m away along an axis; a length is below 100 m"),
    (dict(axis="0 0 0"), "joint 'j1': axis [0.0, 0.0, 0.0] is not a direction (finite, not zero)"),
    (dict(axis="nan 0 1"), "joint 'j1': axis [nan, 0.0, 1.0] is not a direction (finite, not zero)"),
    # its length overflows to inf, so the axis divided by it was [0, 0, 0], and accepted
    (dict(axis="1e308 1e308 0"),
     "joint 'j1': axis [1e+308, 1e+308, 0.0] is not a direction (finite, not zero)"),
    (dict(text="this is not xml <<<"), "not XML (syntax error: line 1, column 0)"),
    (dict(head='<?xml version="1.0"?>\n<!DOCTYPE r [<!ENTITY x "y">]>\n'),
     "line 2: a DOCTYPE declaration; a URDF needs none"),
    (dict(text='<robot name="r">\0</robot>'), "line 1 holds a NUL byte; a URDF is XML text"),
    # before: "not a URDF (ValueError: could not broadcast input array from shape (2,) into shape (3,))"
    (dict(xyz="0 0"), "joint 'j1': origin xyz='0 0' is not three numbers"),
    (dict(axis="a b c"), "joint 'j1': axis xyz='a b c' is not three numbers"),
])
def test_a_urdf_that_is_not_geometry_is_refused_in_one_line(tmp_path: Path, kw: dict, expected: str) -> None:
    # before: NaN or 1e308 geometry and a zero axis were accepted (then -2^63 counts, a LinAlgError);
    # not XML, a DOCTYPE or a NUL were tracebacks
    p = _urdf_config(tmp_path, **kw)
    _, problems = _load_problems(p)
    assert problems == [f"{p}: arm.urdf: URDF r.urdf: {expected} (got 'r.urdf')"] or \
        problems[0].startswith(f"{p}: arm.urdf: URDF r.urdf: {expected}"), problems
    r = runner.invoke(app, ["info", "--config", str(p)])
    assert r.exit_code == 2 and "Traceback" not in r.output


def test_a_sound_urdf_is_taken(tmp_path: Path) -> None:
    assert load_arm(_urdf_config(tmp_path)).n_joints == 2


def test_info_never_writes_over_the_urdf_its_config_reads(tmp_path: Path) -> None:
    # before: `info --urdf` replaced the config's own URDF with its generated one, exit 0
    p = _urdf_config(tmp_path)
    before = (tmp_path / "r.urdf").read_bytes()
    r = runner.invoke(app, ["info", "--config", str(p), "--urdf", str(tmp_path / "r.urdf")])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert (f"--urdf {tmp_path / 'r.urdf'}: is the input {tmp_path / 'r.urdf'}; an output never replaces "
            "a file the command reads") in " ".join(r.stderr.split())
    assert (tmp_path / "r.urdf").read_bytes() == before


# ---------------------------------------------------------------------------- fuzzing the loader

_HOSTILE_NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**70), 2**70),
    st.sampled_from([True, False, None, "", "x", 1e308, -1e308, 1e-300, 0, 2**32 + 1, [], {}]))


def _leaves(d, path=()):
    """The paths of every number in ``d`` (a config as loaded)."""
    if isinstance(d, dict):
        for k, v in d.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield from _leaves(v, (*path, i))
    elif isinstance(d, int | float) and not isinstance(d, bool):
        yield path


_WMRA = yaml.safe_load((CONFIG_DIR / "wmra.yaml").read_text())
_PATHS = list(_leaves(_WMRA))


@settings(derandomize=True, max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(changes=st.lists(st.tuples(st.sampled_from(_PATHS), _HOSTILE_NUMBERS), min_size=1, max_size=3))
def test_fuzz_the_loader_gives_finite_bounded_geometry_or_its_own_error(tmp_path: Path, changes) -> None:
    d = copy.deepcopy(_WMRA)
    for path, value in changes:
        node = d
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    p = _write(tmp_path / "fuzz.yaml", d)
    try:
        arm = load_arm(p)
    except ConfigError as e:
        assert all(str(q).startswith(f"{p}: ") for q in e.problems)
        return
    for j in arm.joints:
        for a in (j.R_pre, j.p_pre_m, j.axis, j.R_post, j.p_post_m):
            assert np.all(np.isfinite(a)) and np.all(np.abs(a) < 100.0)
        assert 1.0 <= j.counts_per_rev <= 2.0**32
    for s in arm.sensors:
        assert np.all(np.isfinite(s.p_L_m)) and np.all(np.abs(s.p_L_m) < 100.0) and s.link in range(8)
