"""A tracker's state as a value, :class:`TrackerState`: the filter's mean and covariance
(the offsets, biases, attitude and the base's motion are states of it), the encoders' angles,
the differentiators' windows, the compass's learnt field, iron and floor, the health counters,
the stillness and motion averages, the slip detector's and the calibration's pull, the rival
branches, the model-change alarm's active alarms.
:meth:`armfusion.fusion.tracking.filter.Tracker.state` makes it and
:meth:`armfusion.fusion.tracking.filter.Tracker.resume` takes it; :meth:`TrackerState.to_dict` and
:meth:`TrackerState.from_dict` are the JSON-ready snapshot (enough to resume after a restart
of the process without a new startup calibration, provided the encoders kept counting)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

SNAPSHOT_FORMAT = "armfusion.tracker/1"


@dataclass(frozen=True)
class TrackerState:
    """What a started tracker knows, by value (arrays are copies; the parts' entries are
    their own ``snapshot()`` values)."""

    t_s: float
    x: np.ndarray
    """The filter's mean (names: :attr:`armfusion.fusion.tracking.filter.Tracker.state_names`)."""
    P: np.ndarray
    """Its covariance."""
    q_enc: np.ndarray
    """The encoders' angles at ``t_s`` (rad): the joints are these plus the offsets in ``x``."""
    omega: np.ndarray | None
    """The last gyro reading, base axes (rad/s); None before any."""
    encoder_fit: Any
    gyro_fit: Any
    compass: Mapping
    """:meth:`armfusion.fusion.tracking.compass.Compass.snapshot`: the field, the guard, the iron, the
    heading's status and its floor."""
    counters: np.ndarray
    still: Any = None
    intensity: Any = None
    shift: Any = None
    consider: Any = ()
    ambiguous: Any = None
    alarm: Any = None
    """:meth:`armfusion.fusion.tracking.alarm.ModelChangeAlarm.snapshot`: the active alarms and
    their sensors' widening (None in a snapshot from before the alarm was kept)."""

    def to_dict(self, arm_name: str, state_names: tuple[str, ...]) -> dict:
        """The JSON-ready snapshot of this state, for the arm ``arm_name`` whose filter's
        states are ``state_names``."""
        c = self.compass
        return {
            "format": SNAPSHOT_FORMAT,
            "arm": arm_name,
            "state_names": list(state_names),
            "t_s": self.t_s,
            "x": self.x.tolist(),
            "P": self.P.tolist(),
            "q_enc": self.q_enc.tolist(),
            "omega": None if self.omega is None else np.asarray(self.omega).tolist(),
            "encoder_fit": self.encoder_fit,
            "gyro_fit": self.gyro_fit,
            "field": c["field"],
            "guard": c["guard"],
            "iron": c["iron"],
            "heading_status": c["status"],
            "compass_floor_var": c["fused_floor_var"],
            "compass_iron_gain": c.get("iron_gain"),
            "counters": np.asarray(self.counters).tolist(),
            "still": self.still,
            "intensity": self.intensity,
            "shift": self.shift,
            "consider": self.consider,
            "ambiguous": self.ambiguous,
            "alarm": self.alarm,
        }

    @classmethod
    def from_dict(cls, snap: Mapping, arm_name: str, state_names: tuple[str, ...]) -> TrackerState:
        """The state a snapshot (:meth:`to_dict`) holds, checked to be one for the arm
        ``arm_name`` with the filter states ``state_names``."""
        if snap.get("format") != SNAPSHOT_FORMAT:
            raise ValueError(f"not a tracker snapshot (format {snap.get('format')!r}, expected "
                             f"{SNAPSHOT_FORMAT!r})")
        if snap.get("arm") != arm_name or tuple(snap.get("state_names", ())) != tuple(state_names):
            raise ValueError(f"the snapshot is for arm {snap.get('arm')!r} with another state; this "
                             f"tracker is for {arm_name!r}")
        return cls(
            t_s=float(snap["t_s"]), x=np.array(snap["x"], dtype=float), P=np.array(snap["P"], dtype=float),
            q_enc=np.array(snap["q_enc"], dtype=float),
            omega=None if snap.get("omega") is None else np.array(snap["omega"], dtype=float),
            encoder_fit=snap["encoder_fit"], gyro_fit=snap["gyro_fit"],
            compass={"field": snap.get("field"), "guard": snap.get("guard"), "iron": snap.get("iron"),
                     "status": snap.get("heading_status"), "fused_floor_var": snap.get("compass_floor_var"),
                     "iron_gain": snap.get("compass_iron_gain")},
            counters=np.array(snap["counters"], dtype=np.int64), still=snap.get("still"),
            intensity=snap.get("intensity"), shift=snap.get("shift"), consider=snap.get("consider", []),
            ambiguous=snap.get("ambiguous"), alarm=snap.get("alarm"))
