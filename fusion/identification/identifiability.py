"""Identifiability: which elements the data cannot tell from their priors or from each
other, held at their priors with the combination in words and the motion that would
separate them.

The weighted Jacobian, scaled by the prior σ, says which combinations of parameters the
data know no better than their priors. Each such combination is reported in words and one
element of it (the one that carries most of it) is **held** at its prior, as Ceres holds a
parameter block (here element by element, like a subset manifold). The other elements then
carry the combination; their σ includes the held ones' prior uncertainty (a consider
covariance, :func:`armfusion.fusion.identification.identify.identify`), so it stays honest.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.identification.problem import ATTITUDE
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.models.effects.library import (
    AccelAxes,
    AccelBias,
    AccelScale,
    Backlash,
    BaseMount,
    EncoderScale,
    GyroBias,
    GyroScale,
    JointOffset,
    LinkCompliance,
    MagArmDisturbance,
    MagHardIron,
    MagSoftIron,
    MotionAcceleration,
    MountRotation,
    TemperatureDrift,
    TimeDrift,
    TimeOffset,
)


@dataclass(frozen=True)
class Hold:
    """One element held at its prior, and why."""

    element: str
    partners: tuple[tuple[str, float], ...]
    data_to_prior: float
    message: str
    suggestion: str


_SUGGEST = {
    JointOffset.name: "move the joints between {j} and the sensor so that {j}'s axis turns in the "
                      "sensor's frame, or tilt {j}'s axis away from vertical",
    MountRotation.name: "turn the sensor about each of its axes (move the joints just before it)",
    AccelAxes.name: "turn the sensor so that every axis points up and down in turn",
    AccelBias.name: "turn the sensor so that each axis sees gravity both up (+1 g) and down (-1 g)",
    AccelScale.name: "turn the sensor so that each axis sees gravity both up (+1 g) and down (-1 g)",
    TemperatureDrift.name: "record while the electronics warm up (a temperature change of 10 °C or more)",
    BaseMount.name: "park the chair on a ramp facing up, down and across (renk-ramp) so the base "
                    "attitude and the IMU's mount separate; its angle about the first joint's axis no "
                    "tilt can separate from that joint's zero: read the base's tilt with an "
                    "inclinometer in the first stance (calibrate sensors --base-tilt)",
    GyroBias.name: "hold the chair still for a while (the gyro bias is its reading at rest)",
    GyroScale.name: "turn the chair on the spot (a full turn both ways at 30 °/s or more)",
    MagHardIron.name: "turn the chair on the spot through a full circle (the compass readings "
                      "trace a circle around the hard iron)",
    MagSoftIron.name: "turn the chair through a full circle and tilt it (the readings trace an "
                      "ellipsoid)",
    MagArmDisturbance.name: "move {j} through its range while the chair is still",
    LinkCompliance.name: "move {j} so that its gravity torque changes sign and size",
    Backlash.name: "move {j} so that its gravity torque changes sign",
    EncoderScale.name: "move {j} through most of its range",
    MotionAcceleration.name: "swing the joints before the sensor fast (centripetal and tangential "
                             "acceleration)",
    TimeOffset.name: "move faster: a time offset is seen only through the rate of change",
    TimeDrift.name: "move fast both early and late in the recording: a drifting offset is seen through "
                    "the rate of change, at different times",
    "attitude": "the base attitude: tilt the chair, or turn it on the spot for the heading",
}


def _element_effect(name: str) -> tuple[str, str]:
    """``'acc3.mount_rotation[z]'`` -> (effect, target)."""
    block = name.split("[")[0]
    target, _, effect = block.partition(".")
    return ("attitude" if block == ATTITUDE else effect), target


def suggestion_for(element: str, partners: Sequence[str] = ()) -> str:
    effect, target = _element_effect(element)
    text = _SUGGEST.get(effect, "a motion that changes these parameters' effects differently")
    j = target
    if "{j}" in text and not target.startswith("j"):
        js = [_element_effect(p)[1] for p in partners if _element_effect(p)[1].startswith("j")]
        j = js[0] if js else "the joint"
    zeros = [_element_effect(p)[1] for p in partners if _element_effect(p)[0] == JointOffset.name]
    if effect == JointOffset.name and any(_element_effect(p)[0] == MountRotation.name for p in partners):
        zeros = [target]
        effect = MountRotation.name
    if effect == MountRotation.name and zeros:
        # a gauge: the sensor turned about the joint's axis and the joint's zero turned back
        # read the same in every motion; only an outside reference of the angle separates them
        return (f"no motion separates it from {zeros[0]}'s zero: give {zeros[0]}'s angle once, at a "
                f"mechanical index or a pose the installer confirms (calibrate sensors --reference "
                f"{zeros[0]}=DEG)")
    if effect == BaseMount.name and zeros:
        text += f", or give {zeros[0]}'s angle once (calibrate sensors --reference {zeros[0]}=DEG)"
    return text.format(j=j)


def analyse_identifiability(Jw: np.ndarray, sigma0: np.ndarray, names: Sequence[str],
                            free: np.ndarray, settings: IdentifySettings | None = None) -> list[Hold]:
    """Which free elements the data cannot tell from their priors or from each other.

    ``Jw`` is the noise-weighted Jacobian (rows: readings; columns: ``names``), ``sigma0``
    the prior σ. In prior-σ units the data's information is ``H = (Jw σ0)ᵀ(Jw σ0)``. A
    pivoted Cholesky factorisation takes the best-known element first, then the one best
    known given those taken, and so on (a rank-revealing order); an element whose
    information given the others is below ``1/hold_ratio²`` (data σ above ``hold_ratio``
    prior σ) is held, and its partners are the taken elements it is a combination of
    (regression of its column on theirs).
    """
    return analyse_information(Jw.T @ Jw, sigma0, names, free, settings)


def analyse_information(H_data: np.ndarray, sigma0: np.ndarray, names: Sequence[str],
                        free: np.ndarray, settings: IdentifySettings | None = None) -> list[Hold]:
    """:func:`analyse_identifiability` from the data's information ``JwᵀJw`` (as the
    estimator accumulates it chunk by chunk)."""
    st = settings or IdentifySettings()
    free = np.array(free, bool)
    H = H_data * np.outer(sigma0, sigma0)
    idx = np.flatnonzero(free)
    # pivoted Cholesky: take the most informative element first; an element whose
    # information, given every element already taken, is below 1/hold_ratio² is held
    taken: list[int] = []
    left = list(idx)
    d = {j: H[j, j] for j in left}
    L = np.zeros((len(H), 0))
    limit = 1.0 / st.hold_ratio**2
    while left:
        j = max(left, key=lambda c: d[c])
        if d[j] < limit:
            break
        col = (H[:, j] - L @ L[j]) / np.sqrt(d[j])
        L = np.hstack([L, col[:, None]])
        taken.append(j)
        left.remove(j)
        for c in left:
            d[c] = H[c, c] - float(L[c] @ L[c])
    holds: list[Hold] = []
    Ht = H[np.ix_(taken, taken)] if taken else np.zeros((0, 0))
    for j in sorted(left, key=lambda c: -H[c, c]):
        ratio = 1.0 / np.sqrt(max(d[j], 1e-300))
        partners: tuple[tuple[str, float], ...] = ()
        if taken and H[j, j] >= limit:
            beta = np.linalg.lstsq(Ht, H[taken, j], rcond=None)[0]
            big = np.max(np.abs(beta)) if len(beta) else 0.0
            order = np.argsort(-np.abs(beta))
            partners = tuple((names[taken[m]], float(beta[m])) for m in order
                             if big > 0 and abs(beta[m]) >= st.partner_weight * big)[:6]
        if partners:
            msg = (f"{names[j]} cannot be separated from {', '.join(p for p, _ in partners[:4])}"
                   f"{' …' if len(partners) > 4 else ''}: the data see only their combination "
                   f"(alone it would be known to {min(ratio, 1e6):.3g} prior σ); held at its prior")
        else:
            msg = (f"{names[j]} is not seen by the data (its effect on the readings is below the "
                   f"noise: known to {min(ratio, 1e6):.3g} prior σ); held at its prior")
        holds.append(Hold(names[j], partners, float(ratio), msg,
                          suggestion_for(names[j], [p for p, _ in partners])))
    return holds
