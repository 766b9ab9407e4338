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
  candidate's prior (the score test's own criterion: ``armfusion.fusion.workbench.scores``). Those
  whose information the fitted parameters take up to all but :data:`STRUCTURAL_SHARE` are
  reported as structural too (a gauge of the model, not of this motion).

A direction is held by holding the element of the block that carries most of it (as Ceres
holds a parameter, and as :mod:`armfusion.fusion.identification.identifiability` does): the other
elements then describe the same readings, the gauge fixed at that element's prior.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from armfusion.fusion.identification.data import FitData, fitted_streams, with_encoder_zeros
from armfusion.fusion.identification.identifiability import suggestion_for
from armfusion.models.effects import Model
from scipy.linalg import qr

STRUCTURAL_SHARE = 1e-6
"""A direction whose information, with the fitted parameters projected out, is below this
share of its own is taken up by them exactly: a gauge of the model (rounding leaves ~1e-12)."""
OWN_AXIS_POINTS = 40
"""Points (evenly spread) the structural check reads the Jacobians at."""


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


def still_jacobian(model: Model, data: FitData) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Every element's column of the fitted streams' readings at a few of the recording's
    poses held still (:data:`OWN_AXIS_POINTS`), each column in its prior σ and each stream's
    rows scaled to its largest column. Returns ``(J, element names, prior σ)``. The model's
    joint zeros are added where it lacks them."""
    m = with_encoder_zeros(model)
    stride = max(1, data.n // OWN_AXIS_POINTS)
    st = data.subset(slice(None, None, stride)).state
    # the recording's poses held still: a joint zero also moves the sensors after it, which
    # changes the motion's acceleration there (a lever arm's difference, second order in the
    # rates, that no calibration should lean on); gravity's part is the identity
    still = st.replace(qd_rad_s=np.zeros_like(st.qd_rad_s), qdd_rad_s2=np.zeros_like(st.qdd_rad_s2))
    streams = fitted_streams(m.stream_models())
    _, jac = m.predict_with_jacobian(still, None, streams)
    names = m.element_names()
    sig = m.prior_sigma
    rows = []
    for s in streams:
        blocks = jac.get(s, {})
        if not blocks:
            continue
        N, k = next(iter(blocks.values())).shape[:2]
        Js = np.zeros((N * k, m.size))
        for b, Jb in blocks.items():
            Js[:, m.index[b]] = Jb.reshape(N * k, -1)
        Js *= sig
        top = float(np.max(np.linalg.norm(Js, axis=0), initial=0.0))
        if top > 0:
            rows.append(Js / top)
    return (np.concatenate(rows) if rows else np.zeros((0, m.size))), names, sig


def structural_gauges(model: Model, data: FitData, eligible: Sequence[str] | None = None,
                      held: Sequence[str] = (), jacobian=None) -> list[Gauge]:
    """The directions of ``model``'s parameters (its joint zeros included) that change no
    reading in any still pose: the null space of :func:`still_jacobian`, elements already
    ``held`` and those no reading sees left out. Each is held at one element of ``eligible``
    (default: every element but the joint zeros, which belong to the recording): a pivoted
    choice, the element that carries most of what is left. A mount rotation about its own
    joint's axis is one where nothing else sees that joint's zero (the last sensor's joint,
    or parallel axes: on a UR5 the forearm's turn about the elbow's axis is the elbow's zero
    less wrist 1's)."""
    J, names, _ = still_jacobian(model, data) if jacobian is None else jacobian
    if J.size == 0:
        return []
    norms = np.linalg.norm(J, axis=0)
    hset = set(held)
    active = np.flatnonzero((norms > 1e-9 * max(norms.max(), 1e-300))
                            & np.array([n not in hset for n in names]))
    if eligible is None:
        ok = [i for i in active if ".joint_offset[" not in names[i]]
    else:
        es = set(eligible)
        ok = [i for i in active if names[i] in es]
    if not ok:
        return []
    _, sv, Vt = np.linalg.svd(J[:, active], full_matrices=True)
    sv = np.concatenate([sv, np.zeros(len(active) - len(sv))]) if len(sv) < len(active) else sv
    null = Vt[sv <= STRUCTURAL_SHARE * sv[0]].T  # (active, k)
    if null.shape[1] == 0:
        return []
    pos = {c: r for r, c in enumerate(active)}
    Ne = null[[pos[i] for i in ok]]  # eligible rows
    _, R, piv = qr(Ne.T, pivoting=True)
    diag = np.abs(np.diag(R)) if R.size else np.zeros(0)
    rank = int(np.sum(diag > 1e-3))
    chosen = [ok[p] for p in piv[:rank]]
    m = with_encoder_zeros(model) if jacobian is None else model
    out = []
    for i in chosen:
        # the null vector that is 1 at this element and 0 at the other chosen ones
        A = null[[pos[c] for c in chosen]]
        coef = np.linalg.lstsq(A, (np.array(chosen) == i).astype(float), rcond=None)[0]
        n = null @ coef
        block = names[i].split("[")[0]
        in_block = {names[c]: float(n[pos[c]]) for c in active if names[c].split("[")[0] == block}
        big = float(np.max(np.abs(n)))
        partners = tuple(dict.fromkeys(names[c].split("[")[0] for c in active[np.argsort(-np.abs(n))]
                                       if names[c].split("[")[0] != block and abs(n[pos[c]]) >= 0.02 * big))
        if not partners:
            # seen by no still reading at all (an axis gravity never reaches): not a gauge of
            # the structure; motion may see it, and the fit's identifiability analysis decides
            continue
        v = np.array([in_block.get(e, 0.0) for e in m.block(block).element_names()])
        own = _own_joint_zero(m, block)
        partners = tuple(sorted(partners, key=lambda p: p != own))  # the sensor's own joint first
        zeros = [f"{p}[0]" for p in partners if p.endswith(".joint_offset")]
        if zeros:  # the same as a joint's zero in every pose: only an outside reference separates them
            j = zeros[0].split(".")[0]
            sugg = (f"no motion separates it from {j}'s zero: give {j}'s angle once, at a mechanical "
                    f"index or a pose the installer confirms (calibrate sensors --reference {j}=DEG)")
        else:
            sugg = suggestion_for(names[i], [f"{p}[0]" for p in partners])
        out.append(_gauge(m, block, v / max(float(np.linalg.norm(v)), 1e-300), partners, True, sugg,
                          m.block(block).element_names().index(names[i])))
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


def _own_joint_zero(m: Model, block: str) -> str | None:
    """The zero of the joint the target sensor's link turns on (None: not a link sensor)."""
    target = m.block(block).target
    try:
        link = m.arm.sensor(target).link
    except (KeyError, ValueError, AttributeError):
        return None
    return f"{m.arm.joint_names[link - 1]}.joint_offset" if link >= 1 else None


def held_elements(gauges: Sequence[Gauge]) -> list[str]:
    return list(dict.fromkeys(g.held for g in gauges))
