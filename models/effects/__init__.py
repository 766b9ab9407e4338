"""The library of physical effects and the model that composes them.

- :mod:`armfusion.models.effects.base`: parameter blocks, stages, targets, the context;
- :mod:`armfusion.models.effects.library`: the effects themselves (``EFFECTS``);
- :mod:`armfusion.models.effects.model`: :class:`Model`, an ordered composition with one flat
  parameter vector, predictions in counts and their Jacobians by block name;
- :mod:`armfusion.models.effects.entries`: effects as written in configs, on the command line and
  in truth files, validated with messages that name the key.

See docs/effects.md.
"""

from armfusion.models.effects.base import (
    STAGES,
    Context,
    Effect,
    JointEffect,
    MountEffect,
    ParamBlock,
    SensorEffect,
    TargetError,
    TimeEffect,
)
from armfusion.models.effects.entries import (
    all_effects,
    build_effect,
    describe_effects,
    effect_names,
    entries_from_model,
    model_from_arm,
    model_from_entries,
    model_problems,
    parse_effect_option,
    realistic_values,
)
from armfusion.models.effects.library import EFFECTS
from armfusion.models.effects.model import Model

__all__ = [
    "EFFECTS", "STAGES", "Context", "Effect", "JointEffect", "Model", "MountEffect", "ParamBlock",
    "SensorEffect", "TargetError", "TimeEffect", "all_effects", "build_effect", "describe_effects",
    "effect_names", "entries_from_model", "model_from_arm", "model_from_entries", "model_problems",
    "parse_effect_option", "realistic_values",
]
