"""One-time joint references as rows of a fit: each a pseudo-measurement of a joint's
geometric angle over a still stretch of the recording
(:class:`~armfusion.fusion.identification.data.JointReference`), which pins the joint's zero.

:class:`ReferenceRows` holds what the rows need besides the estimate: each reference's joint,
angle and σ, the encoder angles there, the point and the parked stance it stands in, and the
unknowns that can move it (:class:`~armfusion.fusion.identification.problem.FitProblem` evaluates
the angles and differentiates them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.fusion.identification.data import FitData, JointReference
from armfusion.models.effects import Model
from armfusion.models.effects.base import JointEffect
from armfusion.models.effects.library import EncoderScale
from armfusion.models.rotations import wrap_angle


@dataclass(frozen=True)
class ReferenceRows:
    """The one-time joint references of a fit's data, ready to be its rows."""

    refs: tuple[JointReference, ...]
    joint: np.ndarray
    """Each reference's joint, as its index on the arm."""
    angle_rad: np.ndarray
    sigma_rad: np.ndarray
    encoder_rad: np.ndarray
    """Every joint's relative encoder angle at each reference ``(R, n_joints)``."""
    point: np.ndarray
    """The fit point nearest each reference's middle."""
    stance: np.ndarray
    """The parked stance each reference stands in (its nearest point's): the base attitude
    its sag and play see."""
    cols: np.ndarray
    """The unknowns that can move a joint's geometric angle at a still instant: the joint
    stage (offsets, sag, play), the encoder scales, the base attitude (sag follows the tilt)."""
    stream: str
    """The stream whose context the angles are read in (the first link accelerometer's)."""

    @classmethod
    def of(cls, model: Model, data: FitData, size: int, encoder_scale: bool) -> ReferenceRows | None:
        """The references of ``data`` for a fit of ``model`` over ``size`` unknowns (the base
        attitude's after the model's), or None without references; ``ValueError`` for a
        reference the arm cannot take."""
        refs = tuple(data.joint_references)
        if not refs:
            return None
        arm = model.arm
        if not arm.link_accelerometers:
            raise ValueError("a joint reference needs the arm's link accelerometers")
        for r in refs:
            if r.joint not in arm.joint_names:
                raise ValueError(f"joint reference: no joint {r.joint[:20]!r} on this arm")
        t_pts = data.state.t_s.reshape(data.n, data.nodes).mean(1)
        near = np.array([int(np.argmin(np.abs(t_pts - 0.5 * (r.t_start_s + r.t_end_s)))) for r in refs])
        cols: list[int] = []
        for e in model.effects:
            if isinstance(e, JointEffect) or (encoder_scale and e.name == EncoderScale.name):
                sl = model.index[e.block_name]
                cols += range(sl.start, sl.stop)
        cols += range(model.size, size)
        return cls(refs, np.array([arm.joint_names.index(r.joint) for r in refs]),
                   np.array([r.angle_rad for r in refs], float), np.array([r.sigma_rad for r in refs], float),
                   np.array([np.asarray(r.encoder_rad, float) for r in refs]), near,
                   np.zeros(len(near), int) if data.stance is None else data.stance[near],
                   np.array(sorted(cols), int), arm.link_accelerometers[0].name)

    def residual(self, angles_rad: np.ndarray) -> np.ndarray:
        """The weighted residuals of the joints' geometric angles ``angles_rad`` at the references."""
        return wrap_angle(angles_rad - self.angle_rad) / self.sigma_rad
