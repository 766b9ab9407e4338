"""A fit against a simulation's truth (``REC.truth.json``): the true value of every model
element, and each estimate's error in σ; and what a simulated installer's one-time
references say (:func:`installer_reference`)."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.identification.result import Identification
from armfusion.fusion.startup.static import find_static_segments
from armfusion.models.effects.library import JointOffset
from armfusion.models.motion import MotionState
from armfusion.models.simulator import build_model as true_model


def truth_values(result: Identification, truth: dict) -> dict[str, float]:
    """The true value of every model element from a ``REC.truth.json`` dict (0 where the
    truth has no such effect). Joint offsets are shifted by the encoder-zero difference
    ``truth['encoder_zero_rad'] - q_ref`` that they absorb in the fit."""
    m = result.model
    vals = {}
    true_blocks = {f"{e['target']}.{e['effect']}": np.asarray(list(e['params'].values())[0], float).ravel()
                   for e in truth.get("effects", [])}
    zero = np.asarray(truth.get("encoder_zero_rad", np.zeros(m.arm.n_joints)), float)
    for b in m.blocks:
        v = true_blocks.get(b.name, np.zeros(b.size))
        if b.effect == JointOffset.name:
            j = m.arm.joint_names.index(b.target)
            v = v + (zero[j] - result.q_ref_rad[j])
        for lab, x in zip(b.labels, v, strict=True):
            vals[f"{b.name}[{lab}]"] = float(x)
    return vals


def compare_with_truth(result: Identification, truth: dict) -> list[dict]:
    """Each model element: estimate, σ, truth and the error in σ (held ones included)."""
    tv = truth_values(result, truth)
    rows = []
    for i, n in enumerate(result.names):
        if n not in tv:
            continue
        z = (result.x[i] - tv[n]) / result.sigma[i] if result.sigma[i] > 0 else np.inf
        rows.append({"name": n, "estimate": float(result.x[i]), "sigma": float(result.sigma[i]),
                     "truth": tv[n], "z": float(z), "held": bool(result.held[i])})
    return rows


def installer_reference(arm, rec, joints, sigma_deg: float, seed: int,
                        true_effects: list[dict] | None = None) -> list[tuple]:
    """What an installer's one-time references say (``calibrate sensors --reference``): each of
    ``joints``' true geometric angle over the recording's first still segment (the controller's
    angle through seed ``seed``'s true joint stage: zero offset, sag and play at the true base
    tilt) plus N(0, ``sigma_deg``) (seeded), as ``(joint, angle_rad, sigma_rad, None)``."""
    seg = find_static_segments(rec)[0]
    model, x = true_model(arm, true_effects, realistic=true_effects is None, seed=seed)
    out = []
    tq, tb = rec.get("true_q").between(seg.t_start_s, seg.t_end_s), rec.get("true_base").between(
        seg.t_start_s, seg.t_end_s)
    rpy = tb.values.mean(0)
    st = MotionState.static(tq.values.mean(0), rpy[0], rpy[1], rpy[2])
    q_geom = model.context(st, x, (arm.link_accelerometers[0].name,)).q_geom[0]
    rng = np.random.default_rng([seed, 0x5EF])
    sig = np.radians(sigma_deg)
    for j in joints:
        k = arm.joint_names.index(j)
        out.append((j, float(q_geom[k] + rng.normal(0.0, sig)), float(sig), None))
    return out
