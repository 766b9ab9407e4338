"""The calibration applies itself: a calibrated accelerometer read at any temperature is
undone to the ideal sensor's reading, its notes say truthfully which of the config's effects
the tracker applies, and every effect name the fusion code keys on is one the models know."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from armfusion.fusion.calibration import (
    APPLIED,
    COMPASS_MAP_EFFECTS,
    GYRO_MAP_EFFECTS,
    IMU_PARTLY_APPLIED,
    NOT_APPLIED,
    PARTLY_APPLIED,
    UNKNOWN_EFFECT,
    Calibration,
)
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.correction import startup_correction
from armfusion.fusion.tracking.alarm import EFFECTS as ALARM_EFFECTS
from armfusion.fusion.tracking.alarm_naming import MODEL_EFFECT
from armfusion.models.effects import Model, build_effect, model_from_arm
from armfusion.models.effects.library import EFFECTS, AccelBias, AccelScale, BaseMount, TemperatureDrift
from armfusion.models.motion import MotionState

DRIFT_G_PER_C = [0.0004, -0.0003, 0.0011]
ENTRIES = (
    {"effect": AccelBias.name, "target": "acc1", "params": {"bias_g": [0.03, -0.02, 0.01]}},
    {"effect": AccelScale.name, "target": "acc1", "params": {"scale_error": [0.01, 0.0, -0.02]}},
    {"effect": TemperatureDrift.name, "target": "acc1", "params": {"drift_g_per_c": DRIFT_G_PER_C}},
)


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


@pytest.fixture(scope="module")
def drifting(arm):
    """The WMRA with acc1 biased, scaled and drifting with temperature."""
    return dataclasses.replace(arm, effects=ENTRIES)


def _seen_and_ideal(arm, temperature_c: float):
    """acc1's still reading at the ready pose at ``temperature_c`` (g): as the calibrated
    sensor reads it, and as an ideal one would."""
    model = Model(arm, [build_effect(arm, e["effect"], e["target"]) for e in ENTRIES])
    st = MotionState.static(np.array(arm.ready_pose_rad)[None], temperature_c=temperature_c)
    x = model.pack({f"{e['target']}.{e['effect']}": list(e["params"].values())[0] for e in ENTRIES})
    seen = model.predict(st, x, ["acc1"], units="physical")["acc1"][0]
    ideal = Model(arm).predict(st, None, ["acc1"], units="physical")["acc1"][0]
    return seen, ideal


def test_the_calibration_undoes_a_reading_at_the_temperature_it_was_taken(drifting):
    """Made at 25 °C, the calibration undoes readings taken at 31 °C and at 43 °C (one at a
    time and as a batch with a temperature each) to the ideal sensor's, to rounding; at
    the wrong temperature it is off by the drift it did not undo."""
    cal = startup_correction(drifting, 25.0)
    assert isinstance(cal, Calibration) and cal.drifts_with_temperature
    seen_31, ideal_31 = _seen_and_ideal(drifting, 31.0)
    seen_43, ideal_43 = _seen_and_ideal(drifting, 43.0)
    np.testing.assert_allclose(cal.ideal("acc1", seen_31, 31.0), ideal_31, atol=1e-12)
    np.testing.assert_allclose(cal.ideal("acc1", seen_43, 43.0), ideal_43, atol=1e-12)
    batch = cal.ideal("acc1", np.array([seen_31, seen_43]), np.array([31.0, 43.0]))
    np.testing.assert_allclose(batch, [ideal_31, ideal_43], atol=1e-12)
    off = cal.ideal("acc1", seen_43, 25.0) - ideal_43
    assert np.linalg.norm(off) > 18.0 * 0.8 * np.linalg.norm(DRIFT_G_PER_C)  # 18 °C of drift left in


def test_a_stream_without_a_calibration_is_read_as_it_is(drifting):
    cal = startup_correction(drifting, 25.0)
    y = np.array([0.1, -0.2, 0.97])
    np.testing.assert_array_equal(cal.ideal("acc2", y, 40.0), y)
    assert cal.undo_map("acc2") is None
    assert "acc2" not in cal.offset_per_c


def test_the_calibration_says_truthfully_what_the_tracker_applies(arm):
    """A known effect is applied; the base IMU's mount is applied only in part, and says
    what is left out; an effect the tracker has no code for is said not applied, with why."""

    class AccelWobble(AccelScale):
        """An accelerometer effect the tracker has no code for (a new one in the library)."""

        name = "accel_wobble"

    bias = build_effect(arm, AccelBias.name, "acc2")
    mount = build_effect(arm, BaseMount.name, arm.imu.name)
    wobble = AccelWobble(arm, "acc3")
    model = model_from_arm(arm).with_effects([bias, mount, wobble])
    applied, not_applied = Calibration(model).effects_applied()
    assert bias.block_name in applied
    assert f"{mount.block_name} ({PARTLY_APPLIED[BaseMount.name]})" in applied
    assert "not to its gyro and compass" in PARTLY_APPLIED[BaseMount.name]
    assert not_applied == [f"{wobble.block_name} ({UNKNOWN_EFFECT})"]


def test_every_effect_name_the_fusion_code_keys_on_is_one_the_models_know():
    """The tracker's notes, the maps the correction builds and the model effects the alarm
    names are all keyed by the models' own names: a renamed effect fails here, not silently."""
    used = (set(APPLIED) | set(NOT_APPLIED) | set(PARTLY_APPLIED) | set(IMU_PARTLY_APPLIED)
            | set(COMPASS_MAP_EFFECTS) | set(GYRO_MAP_EFFECTS) | set(MODEL_EFFECT.values()))
    assert used - set(EFFECTS) == set()
    assert set(MODEL_EFFECT) == set(ALARM_EFFECTS)  # every change the alarm reports says which effect


FUSION = Path(__file__).resolve().parents[2] / "fusion"


def _effect_names_spelled_out(path: Path) -> list[tuple[int, str]]:
    """The string literals in ``path`` that are an effect's name (docstrings and f-string
    parts aside): each a copy of a name the models own, which a rename would leave behind."""
    tree = ast.parse(path.read_text())
    text_only = {id(v) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr) for v in n.values}
    text_only |= {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in EFFECTS
            and id(n) not in text_only]


def test_the_fusion_code_names_effects_by_their_classes_never_by_a_copied_string():
    spelled = {str(p.relative_to(FUSION)): found for p in sorted(FUSION.rglob("*.py"))
               if (found := _effect_names_spelled_out(p))}
    assert spelled == {}
