"""The fusion node's saved state: what ``armfusion serve`` needs to resume after a restart
without asking the arm to be still again.

``serve --state-file PATH`` writes, every ``save_period_s`` of wall time and when it stops,
one JSON document (atomically: a temporary file in the same directory, flushed to disk,
then renamed over the old one, so a crash leaves either the old or the new state, never
half of one)::

    {"format": "armfusion.serve-state/1", "robot": "chair1", "arm": "wmra",
     "config_sha256": "3f9a…", "saved_wall_s": 1790000000.0, "t_s": 812.35,
     "encoder_counts": [...], "rates_hz": {"acc1": 100.0, ...},
     "tracker": {... Tracker.snapshot() ...}}

``config_sha256`` is the SHA-256 of the config file the node tracked with
(:func:`config_fingerprint`): the tracker's offsets, biases and learnt iron hold only under
that sensor model, so a state saved under another config (a sensor calibration applied
since, or the shipped config instead of the calibrated one) is not resumed, nor is its iron
reused. ``tracker`` holds the filter's state and covariance (the encoder offsets, the base's
attitude and acceleration, the gyro bias), the encoders' angles and the heading's field
reference; ``encoder_counts`` and ``t_s`` are the last encoder sample the tracker fused.

On restart the node reads the file and waits for the first encoder sample. It resumes
from the saved state only when :func:`resume_problem` finds nothing wrong: the same robot,
arm and config, saved less than ``max_age_s`` ago (wall time) and no more than ``max_age_s``
of sample time before the new sample, the sample clock not gone back (the rig did not
restart), and every joint's encoder count moved no further than the joint could have
turned in the gap (``max_joint_rate_rad_s``): the encoders kept counting; then
:func:`resumed_tracker` restores the tracker. Otherwise it says why and falls back to a
startup calibration on a still arm.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.fusion.tracking.tracker import Tracker

log = logging.getLogger("armfusion.service")

STATE_FORMAT = "armfusion.serve-state/1"


class StateFileError(ValueError):
    """The state file cannot be used; the message says why."""


def save_state(path: Path | str, doc: Mapping) -> None:
    """Write ``doc`` to ``path`` atomically (temporary file, fsync, rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.dumps(doc, separators=(",", ":")).encode()
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename itself survives a power cut once the directory is synced
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def load_state(path: Path | str) -> dict:
    """The saved state at ``path``; raises :class:`StateFileError` saying what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise StateFileError(f"no saved state at {path}")
    try:
        doc = json.loads(path.read_bytes())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise StateFileError(f"{path}: cannot read the saved state: {e}") from e
    if not isinstance(doc, dict) or doc.get("format") != STATE_FORMAT:
        fmt = doc.get("format") if isinstance(doc, dict) else None
        raise StateFileError(f"{path}: not a saved fusion state (format {fmt!r}, expected {STATE_FORMAT!r})")
    missing = [k for k in ("robot", "arm", "saved_wall_s", "t_s", "encoder_counts", "rates_hz", "tracker")
               if k not in doc]
    if missing:
        raise StateFileError(f"{path}: the saved state lacks {', '.join(missing)}")
    return doc


def config_fingerprint(arm) -> str:
    """The SHA-256 (hex) of the config file ``arm`` was loaded from, or empty when it came
    from no file (an arm built in code)."""
    try:
        return hashlib.sha256(Path(arm.source).read_bytes()).hexdigest() if arm.source else ""
    except OSError:
        return ""


def state_document(robot: str, arm_name: str, t_s: float, encoder_counts, rates_hz: Mapping[str, float],
                   tracker_snapshot: Mapping, saved_wall_s: float | None = None,
                   config_sha256: str = "") -> dict:
    return {"format": STATE_FORMAT, "robot": robot, "arm": arm_name, "config_sha256": config_sha256,
            "saved_wall_s": time.time() if saved_wall_s is None else float(saved_wall_s),
            "t_s": float(t_s), "encoder_counts": [int(c) for c in encoder_counts],
            "rates_hz": {k: float(v) for k, v in rates_hz.items()}, "tracker": dict(tracker_snapshot)}


def save_tracker_state(path: Path | str, robot: str, arm_name: str, t_enc_s: float, encoder_counts,
                       rates_hz: Mapping[str, float], tracker_snapshot: Mapping,
                       config_sha256: str = "") -> bool:
    """Save the tracker's state (atomically): its snapshot, and the last encoder sample it
    fused (``t_enc_s``, ``encoder_counts``), which is the document's ``t_s`` (the snapshot's own
    time is the last fused instant). False, with a log line, when it cannot be written."""
    doc = state_document(robot, arm_name, t_enc_s, encoder_counts, rates_hz, tracker_snapshot,
                         config_sha256=config_sha256)
    try:
        save_state(path, doc)
    except OSError as e:
        log.warning("serve: cannot save the state to %s: %s", path, e)
        return False
    return True


def saved_compass_calibration(doc: Mapping | None, robot: str, arm_name: str,
                              config_sha256: str = "") -> dict | None:
    """The compass's iron as the saved state's tracker had learnt it (the online hard and
    soft iron, :mod:`armfusion.fusion.tracking.compass_calibration`), for the same robot and arm (and,
    given ``config_sha256``, config: the iron learnt is what the config's own correction
    left); None otherwise. Unlike the rest of the state it does not go stale: the chair's
    iron does not change while it is switched off, and a tracker started afresh reuses it."""
    if not doc or doc.get("robot") != robot or doc.get("arm") != arm_name:
        return None
    if _other_config(doc, config_sha256):
        return None
    tracker = doc.get("tracker")
    iron = tracker.get("iron") if isinstance(tracker, Mapping) else None
    return iron if isinstance(iron, Mapping) else None


def _other_config(doc: Mapping, config_sha256: str) -> bool:
    """Whether ``doc`` was saved under another config than the one of ``config_sha256`` (a
    state that names none, or a node that knows none, is not told apart)."""
    saved = doc.get("config_sha256") or ""
    return bool(saved and config_sha256 and saved != config_sha256)


@dataclass(frozen=True)
class ResumeChecks:
    """What a saved state is checked against before the node resumes from it: the node's
    ``robot``; the state saved at most ``max_age_s`` ago (wall time, and of sample time before
    the new sample); every joint's encoder moved no faster than ``max_joint_rate_rad_s`` in
    between; ``config_sha256``, the node's config (:func:`config_fingerprint`; empty: not told
    apart). After a gap of more than ``max_gap_s`` of sample time the tracker's causal fits
    of the encoders and the gyro start afresh rather than differentiate across the gap."""

    robot: str
    max_age_s: float
    max_joint_rate_rad_s: float
    max_gap_s: float
    config_sha256: str = ""


def resume_problem(doc: Mapping, arm, checks: ResumeChecks, *, t_s: float, encoder_counts,
                   now_wall_s: float) -> str | None:
    """Why the saved state ``doc`` must not be resumed at the encoder sample
    (``t_s``, ``encoder_counts``) of ``arm`` at wall time ``now_wall_s``, or ``None`` when it may."""
    robot, arm_name, max_age_s = checks.robot, arm.name, checks.max_age_s
    max_joint_rate_rad_s = checks.max_joint_rate_rad_s
    if doc["robot"] != robot or doc["arm"] != arm_name:
        return (f"it is robot {doc['robot']!r} with arm {doc['arm']!r}; this node serves {robot!r} "
                f"with arm {arm_name!r}")
    if _other_config(doc, checks.config_sha256):
        return ("it was saved under another config (the sensors' model differs: a calibration "
                "applied or undone since), whose offsets and biases do not hold under this one")
    age_s = now_wall_s - float(doc["saved_wall_s"])
    if not math.isfinite(age_s) or age_s > max_age_s:
        return f"it is stale: saved {age_s:.0f} s ago (more than {max_age_s:g} s)"
    t_saved = float(doc["t_s"])
    gap_s = t_s - t_saved
    if gap_s < -1e-9:
        return (f"the sample clock went back from {t_saved:.3f} s to {t_s:.3f} s: the sensors "
                "restarted, so their encoder counts did too")
    if gap_s > max_age_s:
        return f"it is stale: {gap_s:.0f} s of samples since it was saved (more than {max_age_s:g} s)"
    saved = np.asarray(doc["encoder_counts"], dtype=float)
    now = np.asarray(encoder_counts, dtype=float)
    cpr = np.asarray(arm.counts_per_rad, dtype=float)
    if saved.shape != now.shape or saved.shape != cpr.shape:
        return f"it has {saved.size} encoder counts; the arm has {cpr.size} joints"
    moved_rad = np.abs(now - saved) / cpr
    allowed_rad = max_joint_rate_rad_s * gap_s + 2.0 / cpr  # two counts of quantisation
    bad = np.flatnonzero(moved_rad > allowed_rad)
    if bad.size:
        j = int(bad[np.argmax(moved_rad[bad] - allowed_rad[bad])])
        return (f"joint {arm.joint_names[j]}'s encoder jumped {math.degrees(moved_rad[j]):.1f}° in "
                f"{gap_s:.3f} s, more than it can turn at {max_joint_rate_rad_s:g} rad/s: the "
                "encoders were reset or lost counts")
    return None


def resumed_tracker(doc: Mapping, arm, settings, checks: ResumeChecks, *, t_s: float, encoder_counts):
    """``(tracker, None)``: the tracker restored from the saved state ``doc`` at the first
    encoder sample (``t_s``, ``encoder_counts``) when it passes ``checks``; or ``(None, why not)``."""
    try:
        problem = resume_problem(doc, arm, checks, t_s=t_s, encoder_counts=encoder_counts,
                                 now_wall_s=time.time())
    except (TypeError, ValueError, KeyError) as e:  # a hand-edited or damaged file
        return None, f"it is malformed: {type(e).__name__}: {e}"
    if problem is not None:
        return None, problem
    snap = dict(doc["tracker"])
    if t_s - float(doc["t_s"]) > checks.max_gap_s:
        snap["encoder_fit"] = {**snap["encoder_fit"], "n": 0}
        snap["gyro_fit"] = {**snap["gyro_fit"], "n": 0}
        snap["omega"] = None
    try:
        tracker = Tracker(arm, settings, rates_hz=doc["rates_hz"])
        tracker.restore(snap)
    except (ValueError, KeyError, TypeError) as e:
        return None, f"the tracker cannot restore it: {e}"
    return tracker, None
