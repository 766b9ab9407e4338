"""Configs against hostile and broken files (issue 16): read safely and within bounds,
every field (the ``calibration:`` block and the effects included) checked at load, each
problem one line naming the file and key, values quoted short."""

from __future__ import annotations

import copy
import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from fusion.cli.main import app
from fusion.configfile import MAX_YAML_VALUES, load_arm, read_yaml
from models.arm_config import ConfigError

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
