"""How the fusion node starts tracking, and starts again: from its saved state, when the
encoders say it still holds (:func:`resume_from`), else from a startup calibration on the
first still stretch of the samples it keeps (:func:`first_start`); again on the still arm
now, on request (:func:`start_on_still_now`), and on a later still stretch to tell apart the
branches its startup left ambiguous (:func:`resolve_again`). Each gives what to track with
(:class:`Began`) or why not, in a line for the status."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.fusion.service import state_file
from armfusion.fusion.service.restart import ambiguity_note, solve_ambiguity_again
from armfusion.fusion.startup.solve import StartupPrior
from armfusion.fusion.tracking.tracker import (
    NoStillWindowError,
    Start,
    StartOptions,
    Tracker,
    TrackerSettings,
    start_from_recording,
)
from armfusion.models.arm import ArmModel
from armfusion.sensors.samples import Recording

log = logging.getLogger("armfusion.service")


@dataclass(frozen=True)
class Began:
    """A tracker to track with from its time on, the startup it runs on (``None`` when
    resumed from a saved state), and what the status says of it."""

    tracker: Tracker
    start: Start | None
    message: str


def kept_rates_hz(rec: Recording) -> dict[str, float]:
    """Each sensor's rate in ``rec`` (100 Hz when it cannot say)."""
    return {k: (v.rate_hz or 100.0) for k, v in rec.raw().items()}


def parked_prior(arm: ArmModel, assume_parked: bool) -> StartupPrior | None:
    """The ready pose as evidence for the startup's branches only when the caller says the
    arm is parked there (``serve --assume-parked``); by default nothing but the data chooses."""
    return StartupPrior.assume_parked(arm) if assume_parked else None


def first_start(arm: ArmModel, rec: Recording, settings: TrackerSettings | None, *, assume_parked: bool,
                saved_iron: dict | None, state_path: Path | None) -> Began | str:
    """The startup calibration on the first still stretch of the kept samples ``rec``, the
    compass's iron as learnt before (``saved_iron``, from the state file at ``state_path``)
    restored; or why not (no still stretch yet, the calibration failed)."""
    try:
        # (the unlock-move search is for a person asking: calibrate on request shows it)
        tracker, start = start_from_recording(arm, rec, settings,
                                              options=StartOptions(propose_unlock=False,
                                                                   prior=parked_prior(arm, assume_parked)))
    except NoStillWindowError as e:
        return f"waiting for a still arm: {e}"
    except (ValueError, KeyError) as e:
        message = f"startup calibration failed: {e}"
        log.warning("serve: %s", message)
        return message
    assumed = ("; its branches rest on an assumption: the arm parked at its ready pose "
               "(--assume-parked)" if assume_parked else "")
    compass = ""
    try:
        if tracker.compass.restore_iron(saved_iron):
            compass = f"; the compass's iron as learnt before, from {state_path}"
    except ValueError as e:
        compass = f"; the saved compass calibration not used: {e}"
    return Began(tracker, start, f"startup calibration on the still stretch {start.t_start_s:.2f}"
                                 f"-{start.t_end_s:.2f} s; tracking" + assumed + ambiguity_note(start)
                 + compass)


def resume_from(doc: dict, arm: ArmModel, settings: TrackerSettings | None, checks: state_file.ResumeChecks,
                *, t_s: float, encoder_counts: np.ndarray, state_path: Path | None) -> Began | str:
    """The tracker restored from the saved state ``doc``, read from ``state_path``, at the first
    encoder sample (``t_s``, ``encoder_counts``) when it passes ``checks``; or why not, in a line
    for the status."""
    tracker, problem = state_file.resumed_tracker(doc, arm, settings, checks, t_s=t_s,
                                                  encoder_counts=encoder_counts)
    if problem is not None:
        return f"saved state in {state_path} not used: {problem}; a startup calibration on a still arm"
    moved = np.abs(np.asarray(encoder_counts, float) - np.asarray(doc["encoder_counts"], float))
    moved_deg = float(np.degrees(np.max(moved / arm.counts_per_rad)))
    return Began(tracker, None, f"resumed from the state saved in {state_path} "
                                f"{time.time() - float(doc['saved_wall_s']):.1f} s ago at t = "
                                f"{float(doc['t_s']):.3f} s; the encoders moved up to {moved_deg:.2f}° "
                                "since: no startup calibration needed")


def start_on_still_now(arm: ArmModel, still, settings: TrackerSettings | None, *, prior: StartupPrior | None,
                       last_estimate, why: str) -> Began | str:
    """The startup calibration again on the still stretch the arm is in now (``still``, of
    :meth:`armfusion.fusion.service.restart.RecentSamples.still_now`: a segment and its
    samples, or why there is none); ``last_estimate``: the running tracker's last estimate,
    whose pose and sigma go to the startup as a saved pose (checked against the still data)
    and seed the joints it cannot read, or ``None``; ``why``: how the message begins. Or why
    not (the arm moves, no still stretch yet, no samples)."""
    e = last_estimate
    pose = {} if e is None else {"prior_q_rad": np.asarray(e.q_rad, float),
                                 "prior_sigma_rad": np.asarray(e.sigma_rad, float)}
    if isinstance(still, str):
        return still
    _, window = still
    try:
        tracker, start = start_from_recording(arm, window, settings, **pose,
                                              options=StartOptions(prior=prior))
    except NoStillWindowError as e:
        return f"the arm moves: {e}"
    except (ValueError, KeyError) as e:
        return f"the startup calibration failed: {e}"
    message = (f"{why} on the still stretch {start.t_start_s:.2f}-{start.t_end_s:.2f} s"
               f"; tracking from it: {start.startup.summary or ''}").rstrip(": ")
    return Began(tracker, start, message)


def resolve_again(arm: ArmModel, settings: TrackerSettings | None, start: Start, still,
                  ambiguous: set[str]) -> Began | str | None:
    """Joints ``ambiguous`` the startup ``start`` left so: solved again on the still stretch
    ``still`` (as :func:`start_on_still_now`'s) after it
    (:func:`armfusion.fusion.service.restart.solve_ambiguity_again`); what to track with when
    that tells branches apart, the status's message when it does not, ``None`` when there
    is nothing to solve again on. Nothing here moves the arm: the status names the move
    that would help."""
    if isinstance(still, str) or start.geometric is None or start.encoder_rad is None:
        return None
    again = solve_ambiguity_again(arm, settings, start, still, ambiguous)
    if again is None:
        return None
    seg = again.segment
    if again.tracker is None:
        return (f"{', '.join(again.still_ambiguous)} still ambiguous after the still stretch "
                f"{seg.t_start_s:.2f}-{seg.t_end_s:.2f} s" + ambiguity_note(start))
    return Began(again.tracker, again.start, (
        f"the branches of {', '.join(again.resolved)} told apart on the still stretch "
        f"{seg.t_start_s:.2f}-{seg.t_end_s:.2f} s (the startup's candidates carried through the "
        "encoder counts); tracking from it" + ambiguity_note(again.start)))
