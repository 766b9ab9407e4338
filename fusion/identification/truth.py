"""A fit against a simulation's truth (``REC.truth.json``): the true value of every model
element, and each estimate's error in σ."""

from __future__ import annotations

import numpy as np

from fusion.identification.result import Identification


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
        if b.effect == "joint_offset":
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
