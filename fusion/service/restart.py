"""A startup again on the latest still stretch: the fusion node's recent samples, the still
stretch the arm is in now, and what the node says of a startup.

``armfusion serve`` keeps the last ``span_s`` of every sensor's accepted batches
(:class:`RecentSamples`). On a calibration request, and to tell apart the branches of joints
its startup left ambiguous, it runs the startup calibration again on the latest still stretch
in them, if the arm is still now (:meth:`RecentSamples.still_now`).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.reorder import merge_batches
from armfusion.fusion.startup.solve import prior_after_move
from armfusion.fusion.startup.static import Segment, StaticDetectionSettings, find_static_segments
from armfusion.fusion.tracking.tracker import (
    ENC,
    NoStillWindowError,
    Start,
    StartOptions,
    Tracker,
    TrackerSettings,
    start_from_recording,
)
from armfusion.models.arm import ArmModel
from armfusion.models.sensor_models import encoder_angles_at
from armfusion.sensors.samples import Recording, Stream

log = logging.getLogger("armfusion.service")  # the fusion node's own log

STILL_WINDOW_S = 1.0
"""The shortest still stretch a startup runs on."""


class RecentSamples:
    """The last ``span_s`` of each sensor's batches (a batch is dropped once a later one of
    the same sensor is ``span_s`` newer). ``models``: the streams' count models (the arm's),
    which turn the still detection's physical limits into the units the batches hold."""

    def __init__(self, span_s: float, models=None):
        self.span_s = span_s
        self.models = models
        self._parts: dict[str, deque[Stream]] = {}

    def keep(self, s: Stream) -> None:
        parts = self._parts.setdefault(s.name, deque())
        parts.append(s)
        while len(parts) > 1 and parts[0].t_s[-1] < s.t_s[-1] - self.span_s:
            parts.popleft()

    def forget(self, name: str) -> None:
        """Drop what is kept of ``name`` (its clock was refuted)."""
        self._parts.pop(name, None)

    def recording(self, t_from_s: float = -np.inf) -> Recording:
        return merge_batches({k: list(v) for k, v in self._parts.items()}, t_from_s=t_from_s)

    def still_now(self, tolerance_s: float) -> tuple[Segment, Recording] | str:
        """The latest still stretch (of at least :data:`STILL_WINDOW_S`) and the samples from
        its start on, when it ended no more than ``tolerance_s`` before the newest sample;
        else why not, in a line for a person."""
        rec = self.recording()
        if not rec.streams:
            return "no samples received yet"
        if rec.get(ENC) is None:
            return "no encoder samples received yet"
        segs = find_static_segments(rec, StaticDetectionSettings(window_s=STILL_WINDOW_S), self.models)
        if not segs:
            return (f"the arm moves: no still stretch of at least {STILL_WINDOW_S:g} s in the last "
                    f"{rec.duration_s:.1f} s of samples; ask again when it has been still for a second")
        seg = segs[-1]
        since_s = rec.t_end_s - seg.t_end_s
        if since_s > tolerance_s:
            return (f"the arm moves: it was last still {since_s:.1f} s ago "
                    f"({seg.t_start_s:.2f}-{seg.t_end_s:.2f} s); ask again when it is still")
        return seg, self.recording(seg.t_start_s)


def ambiguity_note(start: Start) -> str:
    """What the status says of joints the startup could not choose a branch for."""
    amb = [j for j in start.startup.joints if j.flag == "ambiguous"]
    if not amb:
        return ""
    cands = "; ".join(f"{j.name} " + " or ".join(f"{np.degrees(a):.1f}" for a in j.alternatives_rad)
                      + " deg" for j in amb)
    move = start.startup.disambiguating_move
    how = (move.describe() if move is not None else
           "no safe move of up to 45 deg separates them: a person must confirm the pose")
    return f"; not tracked as known, ambiguous: {cands}; to tell them apart: {how}"


def calibration_reply(robot: str, joint_names, start: Start) -> pl.Calibration:
    res = start.startup
    return pl.Calibration(
        robot, True, res.summary or "calibrated", float(start.t_start_s), float(start.t_end_s),
        tuple(joint_names),
        tuple(None if j.angle_rad is None else float(j.angle_rad) for j in res.joints),
        tuple(None if j.sigma_rad is None else float(j.sigma_rad) for j in res.joints),
        tuple(j.flag for j in res.joints), float(res.roll_rad), float(res.pitch_rad))


@dataclass(frozen=True)
class SolvedAgain:
    """A startup again on a still stretch after an ambiguous one: the ``tracker`` and
    ``start`` that tell some branches apart (None when none is told apart), the joints
    ``resolved`` and those ``still_ambiguous``, and the still stretch ``segment``."""

    tracker: Tracker | None
    start: Start | None
    resolved: tuple[str, ...]
    still_ambiguous: tuple[str, ...]
    segment: Segment


def solve_ambiguity_again(arm: ArmModel, settings: TrackerSettings, start: Start, still,
                          ambiguous: set[str]) -> SolvedAgain | None:
    """Solve the startup again on the still stretch ``still`` (``(segment, window)`` of
    :meth:`RecentSamples.still_now`) with the startup's candidates carried through the
    encoder counts (:func:`armfusion.fusion.startup.solve.prior_after_move`). None when the stretch
    is the startup's own or the solve fails (logged); else what it told apart of the
    joints ``ambiguous`` now."""
    seg, window = still
    if seg.t_start_s <= start.t_end_s + 1e-6:  # the startup's own still stretch
        return None
    moved = encoder_angles_at(arm, window.get(ENC), seg.t_end_s)[1] - start.encoder_rad
    prior = prior_after_move(start.geometric, moved, arm)
    try:
        tracker, again = start_from_recording(arm, window, settings,
                                              options=StartOptions(prior=prior, propose_unlock=False))
    except (NoStillWindowError, ValueError, KeyError) as e:
        log.info("serve: the ambiguous joints were not solved again: %s", e)
        return None
    left = {j.name for j in again.startup.joints if j.flag == "ambiguous"}
    if left >= ambiguous:
        return SolvedAgain(None, None, (), tuple(sorted(ambiguous)), seg)
    return SolvedAgain(tracker, again, tuple(sorted(ambiguous - left)), tuple(sorted(left)), seg)
