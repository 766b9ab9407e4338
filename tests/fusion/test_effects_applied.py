"""What the tracker's note says about the config's effects is true of the tracker: every
effect of the library is either applied (and where) or named as not applied with why, and an
effect the tracker has no code for is never reported as applied."""

from __future__ import annotations

from armfusion.fusion.calibration import (
    APPLIED,
    NOT_APPLIED,
    UNKNOWN_EFFECT,
    effects_applied,
)
from armfusion.fusion.configfile import load_arm
from armfusion.models.effects import build_effect, model_from_arm
from armfusion.models.effects.accelerometer import AccelScale
from armfusion.models.effects.library import EFFECTS


def test_every_effect_of_the_library_has_the_trackers_word():
    """A new effect added to the library without tracker code must be decided here: the
    note would otherwise have nothing true to say of it."""
    assert set(EFFECTS) == set(APPLIED) | set(NOT_APPLIED)
    assert not set(APPLIED) & set(NOT_APPLIED)


class _AccelWobble(AccelScale):
    """An accelerometer effect the tracker has no code for (a new one in the library)."""

    name = "accel_wobble"


def test_an_effect_the_tracker_does_not_know_is_said_not_applied():
    arm = load_arm("wmra")
    bias = build_effect(arm, "accel_bias", "acc2")
    drift = build_effect(arm, "time_drift", "acc2")
    wobble = _AccelWobble(arm, "acc3")
    applied, not_applied = effects_applied(model_from_arm(arm).with_effects([bias, drift, wobble]))
    assert bias.block_name in applied
    assert any(s.startswith(drift.block_name) and "not applied" in s for s in not_applied)
    assert any(s.startswith(wobble.block_name) and UNKNOWN_EFFECT in s for s in not_applied)
    assert not any(s.startswith(wobble.block_name) for s in applied)
