"""Effects as people write them: the arm config's ``effects:`` list, ``--effect`` options,
and the effects part of a simulation's truth file. All three have the same shape::

    - effect: mount_rotation        # a name from the library
      target: acc3                  # a sensor, joint or device (optional where only one fits)
      params: {rotvec_rad: [0.01, 0.02, 0.0]}   # the block's key carries its units
      sigma:  {rotvec_rad: [0.002, 0.002, 0.002]}

Every problem is reported together, each naming the entry's key
(``effects[2].effect: unknown effect 'acel_bias'; known: …``), as the config loader does.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.arm_config import ConfigError, ConfigProblem
from armfusion.models.effects.base import Effect, ParamBlock, TargetError
from armfusion.models.effects.library import EFFECTS
from armfusion.models.effects.model import Model


def effect_names() -> tuple[str, ...]:
    return tuple(EFFECTS)


def build_effect(arm: ArmModel, name: str, target: str | None = None) -> Effect:
    """One effect of the library bound to ``target`` (raises ``KeyError``/``TargetError``)."""
    if name not in EFFECTS:
        raise KeyError(_unknown_effect(name))
    return EFFECTS[name](arm, target)


def _unknown_effect(name: Any) -> str:
    msg = f"unknown effect {name!r}; known: {', '.join(EFFECTS)}"
    close = difflib.get_close_matches(str(name), list(EFFECTS), n=1)
    return msg + (f" (did you mean {close[0]!r}?)" if close else "")


def all_effects(arm: ArmModel, names: Iterable[str] | None = None) -> list[Effect]:
    """Every effect of the library (or of ``names``) on every target it fits on this arm."""
    out = []
    for name in (EFFECTS if names is None else names):
        cls = EFFECTS[name]
        for target in cls.valid_targets(arm):
            try:
                out.append(cls(arm, target))
            except TargetError:
                continue
    return out


def _describe_block(b: ParamBlock) -> str:
    labels = ", ".join(b.labels)
    return f"{b.size} value{'s' if b.size != 1 else ''} ({labels}) in {b.units}"


def _as_array(v: Any, b: ParamBlock) -> tuple[np.ndarray | None, str | None]:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return None, f"must be numbers: {_describe_block(b)}"
    if a.size != b.size:
        return None, f"expected {_describe_block(b)}, got {a.size}"
    if not np.all(np.isfinite(a)):
        return None, "contains a non-finite number"
    return a.reshape(-1), None


def entry_dict(e: Any) -> dict:
    if hasattr(e, "model_dump"):
        return e.model_dump()
    if isinstance(e, Mapping):
        return dict(e)
    return {"effect": e}


def _effect_of(arm: ArmModel, e: dict, k: str, source: str) -> Effect | ConfigProblem:
    """The effect entry ``e`` (at key ``k``) names, or the problem with its name or target."""
    name = e.get("effect")
    if name not in EFFECTS:
        return ConfigProblem(source, f"{k}.effect", name, _unknown_effect(name))
    target = e.get("target")
    try:
        return EFFECTS[name](arm, target)
    except TargetError as err:
        return ConfigProblem(source, f"{k}.target", target, str(err))


def _given_value(e: dict, b: ParamBlock, name: str, k: str, source: str,
                 ) -> tuple[np.ndarray | None, list[ConfigProblem]]:
    """The block's value entry ``e`` gives (``params: {key: ...}`` or ``value:``), checked
    against the block's shape and bounds; None where it gives none."""
    problems = []
    value = None
    params = dict(e.get("params") or {})
    if "value" in e and e["value"] is not None:
        params.setdefault(b.key, e["value"])
    for pk, pv in params.items():
        if pk != b.key:
            problems.append(ConfigProblem(source, f"{k}.params.{pk}", pv,
                                          f"unknown parameter {pk!r} of {name}; it has "
                                          f"{b.key!r}: {_describe_block(b)}"))
            continue
        a, msg = _as_array(pv, b)
        if msg:
            problems.append(ConfigProblem(source, f"{k}.params.{pk}", pv, msg))
            continue
        out = (a < b.lower) | (a > b.upper)
        if np.any(out):
            j = int(np.flatnonzero(out)[0])
            problems.append(ConfigProblem(
                source, f"{k}.params.{pk}", pv,
                f"{b.labels[j]} = {a[j]:g} is outside the bounds [{b.lower[j]:g}, "
                f"{b.upper[j]:g}] {b.units} of {name}"))
            continue
        value = a
    return value, problems


def _given_sigma(e: dict, b: ParamBlock, name: str, k: str, source: str,
                 ) -> tuple[np.ndarray | None, list[ConfigProblem]]:
    """The block's prior sigma entry ``e`` gives (``sigma: {key: ...}``, one number for every
    element or one each), every one positive; None where it gives none."""
    problems = []
    sigma = None
    for sk, sv in dict(e.get("sigma") or {}).items():
        if sk != b.key:
            problems.append(ConfigProblem(source, f"{k}.sigma.{sk}", sv,
                                          f"unknown parameter {sk!r} of {name}; it has {b.key!r}"))
            continue
        a, msg = _as_array([sv] * b.size if np.ndim(sv) == 0 else sv, b)
        if msg is None and np.any(a <= 0):
            msg = "every sigma must be positive"
        if msg:
            problems.append(ConfigProblem(source, f"{k}.sigma.{sk}", sv, msg))
            continue
        sigma = a
    return sigma, problems


def model_problems(
    arm: ArmModel, entries: Iterable[Any], source: str = "(effects)", key: str = "effects",
    **model_kwargs,
) -> tuple[Model | None, list[ConfigProblem]]:
    """Validate effect entries; the model they make (None if any problem) and the problems."""
    problems: list[ConfigProblem] = []
    effects: list[Effect] = []
    values: dict[str, np.ndarray] = {}
    sigmas: dict[str, np.ndarray] = {}
    seen: dict[str, int] = {}
    for i, raw in enumerate(entries):
        e = entry_dict(raw)
        k = f"{key}[{i}]"
        eff = _effect_of(arm, e, k, source)
        if isinstance(eff, ConfigProblem):
            problems.append(eff)
            continue
        name = e.get("effect")
        if eff.block_name in seen:
            problems.append(ConfigProblem(source, k, f"{name}:{eff.target}",
                                          f"{name} on {eff.target} is already given by "
                                          f"{key}[{seen[eff.block_name]}]"))
            continue
        seen[eff.block_name] = i
        b = eff.block()
        value, value_problems = _given_value(e, b, name, k, source)
        sigma, sigma_problems = _given_sigma(e, b, name, k, source)
        problems += value_problems + sigma_problems
        if value is not None:
            values[eff.block_name] = value
        if sigma is not None:
            sigmas[eff.block_name] = sigma
        if not value_problems and not sigma_problems:
            effects.append(eff)
    if problems:
        return None, problems
    return Model(arm, effects, values, sigmas, **model_kwargs), []


def model_from_entries(arm: ArmModel, entries: Iterable[Any], source: str = "(effects)",
                       key: str = "effects", **model_kwargs) -> Model:
    """A :class:`Model` from effect entries, or :class:`ConfigError` naming every problem."""
    model, problems = model_problems(arm, entries, source, key, **model_kwargs)
    if problems:
        raise ConfigError(problems)
    assert model is not None
    return model


def model_from_arm(arm: ArmModel, **model_kwargs) -> Model:
    """The model the arm config's ``effects:`` list describes (validated, named errors)."""
    return model_from_entries(arm, arm.effects, arm.source or "(arm config)", "effects", **model_kwargs)


def parse_effect_option(text: str) -> dict:
    """``NAME[:TARGET]=V1,V2,…`` (the command line's ``--effect``) as an entry dict."""
    head, sep, value = text.partition("=")
    if not sep or not value.strip():
        raise ValueError(f"--effect {text!r}: expected NAME[:TARGET]=VALUE (vector values comma "
                         "separated, in the effect's documented units)")
    name, _, target = head.strip().partition(":")
    try:
        vals = [float(v) for v in value.split(",")]
    except ValueError:
        raise ValueError(f"--effect {text!r}: the value must be numbers separated by commas") from None
    return {"effect": name.strip(), "target": target.strip() or None, "value": vals}


def entries_from_model(model: Model, x: np.ndarray | None = None, with_sigma: bool = True) -> list[dict]:
    """The model's effects and values (default: its current ones) as JSON-ready entries."""
    vals = model.unpack(x)
    out = []
    for e, b in zip(model.effects, model.blocks, strict=True):
        d: dict[str, Any] = {"effect": e.name, "target": e.target,
                             "params": {b.key: vals[b.name].tolist()}}
        if with_sigma:
            d["sigma"] = {b.key: b.prior_sigma.reshape(b.shape).tolist()}
        d["note"] = f"{b.key} in {b.units}: {e.summary}"
        out.append(d)
    return out


def realistic_values(model: Model, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Every block of ``model`` drawn at its datasheet-typical magnitude."""
    return {e.block_name: e.draw(rng).reshape(e.shape) for e in model.effects}


def describe_effects() -> list[dict]:
    """The library as a table (for docs and ``--help``): one row per effect."""
    rows = []
    for name, cls in EFFECTS.items():
        rows.append({
            "effect": name, "stage": cls.stage, "targets": cls.target_kind, "key": cls.key,
            "shape": list(cls.shape), "units": cls.units, "labels": list(cls.labels),
            "summary": cls.summary, "description": cls.description, "seen_in": cls.seen_in,
        })
    return rows
