"""The pose saved at the last clean shutdown: the prior that picks between branches.

Written atomically (a temporary file in the same folder, flushed and fsynced, then
renamed over the old one), so a power cut leaves either the old pose or the new one,
never half a file. A file for another arm, or one that does not parse, is not used.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.fusion.configfile import read_bounded
from armfusion.models.arm import ArmModel

FORMAT = "armfusion.saved_pose.v1"
MAX_POSE_BYTES = 65_536
"""A saved pose is a few hundred bytes (its angles and joint names); a larger file is not one,
and is not read further (``/dev/zero`` would not end)."""


@dataclass(frozen=True)
class SavedPose:
    arm: str
    q_rad: np.ndarray
    saved_unix_s: float


def save_pose(path: str | Path, arm: ArmModel, q_rad: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    q = np.asarray(q_rad, dtype=float)
    if q.shape != (arm.n_joints,) or not np.all(np.isfinite(q)):
        raise ValueError(f"pose to save must be {arm.n_joints} finite angles, got {q.tolist()}")
    doc = {"format": FORMAT, "arm": arm.name, "joint_names": list(arm.joint_names),
           "q_rad": q.tolist(), "saved_unix_s": time.time()}
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def load_pose(path: str | Path, arm: ArmModel) -> tuple[SavedPose | None, str | None]:
    """The saved pose, or None and the reason it cannot be used."""
    path = Path(path)
    if not path.exists():
        return None, f"no saved pose at {path}; the ready pose is the prior"
    try:
        doc = json.loads(read_bounded(path, MAX_POSE_BYTES, "a saved pose"))
        if doc.get("format") != FORMAT:
            return None, f"{path}: not an armfusion saved pose (format {doc.get('format')!r})"
        if doc.get("arm") != arm.name:
            return None, f"{path}: saved for arm {doc.get('arm')!r}, not {arm.name!r}; not used"
        q = np.asarray(doc["q_rad"], dtype=float)
        if q.shape != (arm.n_joints,) or not np.all(np.isfinite(q)):
            return None, f"{path}: q_rad must be {arm.n_joints} finite numbers; not used"
        return SavedPose(doc["arm"], q, float(doc.get("saved_unix_s", 0.0))), None
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        return None, f"{path}: unreadable saved pose ({e}); not used"
