"""A tracker's state as a JSON-ready dict (:func:`snapshot_of`) and back
(:func:`restore_into`): enough to resume after a restart of the process without a new
startup calibration, provided the encoders kept counting. Each part of the tracker writes
and reads its own entries."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from fusion.tracking.compass import Compass
from fusion.tracking.initial import ImuStill, restored_startup
from fusion.tracking.settings import F_AMBIGUOUS
from fusion.tracking.ukf import BatchedUKF


def snapshot_of(tr) -> dict:
    """The state of the :class:`fusion.tracking.filter.Tracker` ``tr`` (started)."""
    c = tr.compass.snapshot()
    return {
        "format": tr.SNAPSHOT_FORMAT,
        "arm": tr.arm.name,
        "state_names": list(tr.state_names),
        "t_s": tr._t,
        "x": tr._ukf._x.tolist(),
        "P": tr._ukf._P.tolist(),
        "q_enc": tr._q_enc.tolist(),
        "omega": None if tr._omega is None else np.asarray(tr._omega).tolist(),
        "encoder_fit": tr.enc_rates.snapshot(),
        "gyro_fit": tr.gyro_rates.snapshot(),
        "field": c["field"],
        "guard": c["guard"],
        "iron": c["iron"],
        "heading_status": c["status"],
        "compass_floor_var": c["fused_floor_var"],
        "counters": tr.health.counts.tolist(),
        "still": tr.still.snapshot(),
        "intensity": None if tr.intensity is None else tr.intensity.snapshot(),
        "shift": tr.slips.snapshot(),
        "consider": tr.observability.snapshot(),
        "ambiguous": tr.ambiguity_.snapshot(),
    }


def restore_into(tr, snap: Mapping) -> None:
    """Resume the :class:`fusion.tracking.filter.Tracker` ``tr`` from :func:`snapshot_of`
    (replaces its initialisation)."""
    if snap.get("format") != tr.SNAPSHOT_FORMAT:
        raise ValueError(f"not a tracker snapshot (format {snap.get('format')!r}, expected "
                         f"{tr.SNAPSHOT_FORMAT!r})")
    if snap.get("arm") != tr.arm.name or tuple(snap.get("state_names", ())) != tr.state_names:
        raise ValueError(f"the snapshot is for arm {snap.get('arm')!r} with another state; this "
                         f"tracker is for {tr.arm.name!r}")
    n, L = tr.arm.n_joints, tr.layout
    x = np.array(snap["x"], dtype=float)
    P = np.array(snap["P"], dtype=float)
    tr.initialise(restored_startup(tr.arm), float(snap["t_s"]),
                  imu=ImuStill(x[L.bias], 1e-3, None, None, Compass.field_from(snap)))
    tr._q_enc = np.array(snap["q_enc"], dtype=float)
    tr._ukf = BatchedUKF(x, P, tr._points, angle_states=(L.yaw,))
    tr._omega = None if snap.get("omega") is None else np.array(snap["omega"], dtype=float)
    tr.enc_rates.restore(snap["encoder_fit"])
    tr.gyro_rates.restore(snap["gyro_fit"])
    tr.compass.restore(snap)
    tr.health.counts = np.array(snap["counters"], dtype=np.int64)
    if "still" in snap:
        tr.still.restore(snap["still"])
    if tr.intensity is not None and snap.get("intensity") is not None:
        tr.intensity.restore(snap["intensity"])
    if "shift" in snap:
        tr.slips.restore(snap["shift"])
    if tr.ambiguity_.restore(snap.get("ambiguous"), n):  # rival branches still open
        tr._flags = np.where(tr.ambiguity_.joints, F_AMBIGUOUS, tr._flags).astype(np.int8)
    # the calibration's pull on the offsets so far
    tr.observability.restore(snap.get("consider", []), float(snap["t_s"]))
