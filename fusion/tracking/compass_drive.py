"""A drive's turns as the config's compass calibration: the tracker run over a driving
recording, its online iron estimate (:mod:`armfusion.fusion.tracking.compass_calibration`) turned
into the config's ``mag_hard_iron`` and ``mag_soft_iron`` entries
(``armfusion calibrate sensors --compass-drive``)."""

from __future__ import annotations

import math

import numpy as np
from armfusion.fusion.tracking.calibrated import undo_map
from armfusion.fusion.tracking.compass_calibration import drive_compass_entries
from armfusion.fusion.tracking.settings import MAG
from armfusion.fusion.tracking.tracker import start_from_recording


def calibrate_compass_on_drive(arm, rec, source: str = "a drive",
                               settings=None) -> tuple[list[dict] | None, str]:
    """Track the driving recording ``rec`` with ``arm``'s config and return the compass
    entries its turns made (:func:`drive_compass_entries`) and a line for a person; None
    (and why) where the config estimates no iron (it states its compass known) or the drive
    did not turn enough to know it."""
    tr, _ = start_from_recording(arm, rec, settings)
    tr.run(rec)
    c = tr.compass
    if c.iron is None:
        return None, ("the config states its compass known well enough to fuse as it is: nothing to "
                      "learn from the drive")
    if c.iron.readings == 0 or not np.isfinite(c.iron_sigma_rad):
        return None, f"the drive gave the compass no readings to learn from ({source})"
    doubt_deg = math.degrees(c.iron_sigma_rad)
    line = (f"compass from the turns in {source}: {c.iron.coverage_deg:.0f}° of headings seen, "
            f"heading doubt {doubt_deg:.2f}°, hard iron sigma "
            + " / ".join(f"{v:.2f}" for v in c.iron.hard_iron_sigma_ut()) + " µT")
    if c.status == "calibrating":
        return None, line + ": not enough turning to know its iron (turn once on the spot)"
    return drive_compass_entries(undo_map(tr.correction, MAG), c.iron, arm.imu.name, source), line
