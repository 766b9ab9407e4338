"""The settings of a fit (:func:`armfusion.fusion.identification.identify.identify`): when the
identifiability analysis holds an element and names its partners, how long the solver may go on,
and which unknowns besides the model's effects the fit estimates."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class IdentifySettings:
    """How a fit holds, solves and what it estimates besides the model's effects."""

    hold_ratio: float = 1.0
    """Hold a combination whose data-only σ exceeds this many prior σ (data know it no
    better than the prior)."""
    partner_weight: float = 0.25
    """An element is named as part of a combination when its share exceeds this."""
    max_nfev: int = 100
    """Most Jacobians (Levenberg-Marquardt iterations) per solve, its coarse start's
    included (:func:`armfusion.fusion.identification.solver.solve`)."""
    estimate_attitude: bool = True
    """Estimate the base attitude (gravity and Earth-field directions); else take it as zero
    (the base level and facing magnetic north) or as the data's state says."""
    encoder_scale: bool = False
    """Let ``encoder_scale`` effects act on the fit's joint angles (they come from the
    encoders: ``q_ref + encoder angle / (1 + s)``). ``calibrate sensors`` and the workbench's
    fits turn it on; off, an encoder's scale is invisible to the fit."""
