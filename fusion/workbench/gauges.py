"""Gauges: directions of an effect's parameters that change nothing the fit does not already
change. Before a candidate is fitted (and whenever a model is fitted) its parameters are
checked against what the fit already makes free (the recording's joint zeros, the base
attitude, the other sensors' terms); a direction they take up entirely is held at its prior
and named, with the reference or motion that would separate it.

Two kinds:

- **by the model's structure** (:func:`own_axis_gauges`): a sensor's mount rotation about the
  axis of the joint its link turns on is that joint's zero: the same gravity reading in every
  pose (they differ only in the motion's acceleration at the sensor, since the zero also moves
  the sensor, a lever arm's second-order term). The direction is found from the model's own
  Jacobians (the mount's three columns against the joint zero's column, at a few of the
  recording's poses held still), so it holds for any kinematics (DH or URDF) and any nominal
  mount; it is held whether or not the recording happens to tell it.
- **by the recording** (:func:`candidate_gauges`): the candidate's directions whose columns,
  with the fitted parameters' columns projected out, the data know no better than the
  candidate's prior (the score test's own criterion: ``fusion.workbench.scores``). Those
  whose information the fitted parameters take up to all but :data:`STRUCTURAL_SHARE` are
  reported as structural too (a gauge of the model, not of this motion).

A direction is held by holding the element of the block that carries most of it (as Ceres
holds a parameter, and as :mod:`fusion.identification.identifiability` does): the other
elements then describe the same readings, the gauge fixed at that element's prior.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusion.identification.data import FitData, with_encoder_zeros
from fusion.identification.identifiability import suggestion_for
from models.effects import Model

STRUCTURAL_SHARE = 1e-6
"""A direction whose information, with the fitted parameters projected out, is below this
share of its own is taken up by them exactly: a gauge of the model (rounding leaves ~1e-12)."""
OWN_AXIS_POINTS = 40
"""Points (evenly spread) the own-axis check reads the Jacobians at."""
OWN_AXIS_TOLERANCE = 1e-6
"""The mount's columns along the direction must reproduce the joint zero's column to this
share of its norm: an identity of the kinematics, not a coincidence of the motion."""


@dataclass(frozen=True)
class Gauge:
    """One direction of a block held at its prior, and why."""

    block: str
    held: str
    """The element held (the one carrying most of the direction)."""
    direction: tuple[tuple[str, float], ...]
    """The direction in the block's elements (a unit vector), largest first."""
    partners: tuple[str, ...]
    """The fitted parameters that take it up (largest first)."""
    structural: bool
    """True: a gauge of the model (no motion separates it); False: this recording's."""
    suggestion: str

    @property
    def message(self) -> str:
        d = ", ".join(f"{k.split('[')[-1].rstrip(']')} {v:+.2f}" for k, v in self.direction if abs(v) >= 0.05)
        why = ("the model's structure makes it the same as" if self.structural
               else "this recording cannot tell it from")
        who = ", ".join(self.partners[:3]) or "its prior"
        return (f"{self.block} along ({d}): {why} {who}; held at its prior ({self.held}). "
                f"To separate it: {self.suggestion}")

    def as_dict(self) -> dict[str, Any]:
        return {"block": self.block, "held": self.held, "direction": dict(self.direction),
                "partners": list(self.partners), "structural": self.structural,
                "message": self.message, "suggestion": self.suggestion}


def own_axis_gauges(model: Model, data: FitData, blocks: Sequence[str] | None = None) -> list[Gauge]:
    """Every ``mount_rotation`` block of ``model`` (or of ``blocks``) against the zero of the
    joint its sensor's link turns on: the rotation vector ``v`` whose columns reproduce that
    joint zero's column at every point (``J_mount v = J_zero``) is that zero. ``model`` may lack
    the joint zeros (they are added for the check)."""
    m = with_encoder_zeros(model)
    arm = m.arm
    names = [b.name for b in m.blocks if b.effect == "mount_rotation"
             and (blocks is None or b.name in blocks)]
    if not names or data.n == 0:
        return []
    stride = max(1, data.n // OWN_AXIS_POINTS)
    sub = data.subset(slice(None, None, stride))
    # the recording's poses held still: the joint zero also moves the sensor's position, which
    # changes the motion's acceleration there (a lever arm's difference, second order in the
    # rates, that no calibration should lean on); gravity's part is the identity
    st = sub.state
    still = st.replace(qd_rad_s=np.zeros_like(st.qd_rad_s), qdd_rad_s2=np.zeros_like(st.qdd_rad_s2))
    out = []
    for name in names:
        eff = m.effect(name)
        sensor = arm.sensor(eff.target)
        if sensor.link < 1:
            continue
        joint = arm.joint_names[sensor.link - 1]
        zero = f"{joint}.joint_offset"
        stream = eff.streams[0]
        _, jac = m.predict_with_jacobian(still, None, [stream], blocks=[name, zero])
        Jm = jac.get(stream, {}).get(name)
        Jz = jac.get(stream, {}).get(zero)
        if Jm is None or Jz is None:
            continue
        A = Jm.reshape(-1, Jm.shape[-1])
        y = Jz.reshape(-1)
        ny = float(np.linalg.norm(y))
        if ny == 0.0:
            continue
        v, *_ = np.linalg.lstsq(A, y, rcond=None)
        if np.linalg.norm(A @ v - y) > OWN_AXIS_TOLERANCE * ny or not np.any(v):
            continue
        out.append(_gauge(m, name, v / np.linalg.norm(v), (zero,), True,
                          suggestion_for(f"{name}[x]", [f"{zero}[0]"])))
    return out


def candidate_gauges(model: Model, block: str, V_elem: np.ndarray, structural: Sequence[bool],
                     partners: Sequence[Sequence[str]], held_already: Sequence[str] = ()) -> list[Gauge]:
    """Gauges of ``block`` along the columns of ``V_elem`` (element space, one direction a
    column), each held at a different element (a pivoted choice: the element that carries
    most of the direction, among those not held yet, ``held_already`` included)."""
    out: list[Gauge] = []
    el = model.block(block).element_names()
    taken: set[int] = {el.index(h) for h in held_already if h in el}
    for k in range(V_elem.shape[1]):
        v = V_elem[:, k] / max(float(np.linalg.norm(V_elem[:, k])), 1e-300)
        order = [int(i) for i in np.argsort(-np.abs(v)) if int(i) not in taken]
        if not order:
            break
        taken.add(order[0])
        first = [p for p in partners[k] if p.endswith(".joint_offset")]
        sugg = suggestion_for(model.block(block).element_names()[order[0]],
                              [f"{p}[0]" for p in first] or [f"{p}[0]" for p in partners[k]])
        out.append(_gauge(model, block, v, tuple(partners[k]), bool(structural[k]), sugg, order[0]))
    return out


def _gauge(m: Model, block: str, v: np.ndarray, partners: tuple[str, ...], structural: bool,
           suggestion: str, held: int | None = None) -> Gauge:
    el = m.block(block).element_names()
    i = int(np.argmax(np.abs(v))) if held is None else held
    v = v * np.sign(v[i])
    direction = tuple((el[q], float(v[q])) for q in np.argsort(-np.abs(v)))
    return Gauge(block, el[i], direction, partners, structural, suggestion)


def held_elements(gauges: Sequence[Gauge]) -> list[str]:
    return list(dict.fromkeys(g.held for g in gauges))
