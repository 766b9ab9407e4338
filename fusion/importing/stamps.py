"""What the import does with time stamps a logger got wrong, and says so.

Real loggers stamp badly: the rig's files hold some steps of 0 ms (two samples with one
time), other loggers step back after a buffer flush. A recording's time must increase
(:class:`armfusion.sensors.samples.Stream`), and the import changes no time: a row whose time is not
after every time before it is dropped, whole (every stream's values of that row: the later
of two samples stamped alike is the one that has no instant of its own), and a row without a
time (NaN) too; :class:`StampReport` counts them and names the first few rows, for the
import's summary. Nothing is interpolated or re-spaced. A dropped row that copies the row
before it in every column read (:func:`copies_dropped`: the rig's logger writing one row
twice) loses nothing; any other loses a sample, and the import exits 1 for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FIRST_ROWS = 10
"""How many of the rows dropped the report names (the count is always whole)."""


@dataclass(frozen=True)
class StampReport:
    """Rows dropped for their time: ``not_increasing`` and ``no_time`` counts, the first few
    rows of each (1-based rows of the source file) with their times, and the largest step
    back (s; 0 when every bad step is a repeat)."""

    not_increasing: int
    not_increasing_rows: tuple[int, ...]
    not_increasing_t_s: tuple[float, ...]
    largest_step_back_s: float
    no_time: int
    no_time_rows: tuple[int, ...]

    def words(self) -> list[str]:
        """One sentence per change, for a person (empty when nothing was dropped)."""
        out = []
        if self.not_increasing:
            back = (f", the largest step back {self.largest_step_back_s * 1e3:.3f} ms"
                    if self.largest_step_back_s > 0 else " (each a repeat of the time before)")
            rows = ", ".join(f"{r} (t = {t:.6g} s)" for r, t in
                             zip(self.not_increasing_rows, self.not_increasing_t_s, strict=True))
            more = " …" if self.not_increasing > len(self.not_increasing_rows) else ""
            out.append(f"dropped {self.not_increasing} row(s) whose time does not increase{back}: "
                       f"rows {rows}{more}")
        if self.no_time:
            rows = ", ".join(map(str, self.no_time_rows))
            more = " …" if self.no_time > len(self.no_time_rows) else ""
            out.append(f"dropped {self.no_time} row(s) without a time (NaN): rows {rows}{more}")
        return out

    def as_json(self) -> dict:
        return {
            "policy": "a row whose time is not after every earlier time is dropped whole (the later "
                      "of two samples stamped alike); a row without a time too; no time is changed",
            "not_increasing": {"count": self.not_increasing, "first_rows": list(self.not_increasing_rows),
                               "first_t_s": list(self.not_increasing_t_s),
                               "largest_step_back_s": self.largest_step_back_s},
            "no_time": {"count": self.no_time, "first_rows": list(self.no_time_rows)},
        }


def increasing_rows(t_s: np.ndarray, first_row: int = 1) -> tuple[np.ndarray, StampReport]:
    """The mask of the rows kept (time finite and after every earlier kept time) and the
    report; ``first_row`` is the source file's row number of ``t_s[0]`` (for the report)."""
    t = np.asarray(t_s, dtype=np.float64)
    has_time = ~np.isnan(t)
    tt = np.where(has_time, t, -np.inf)
    before = np.maximum.accumulate(np.concatenate([[-np.inf], tt[:-1]])) if t.size else tt
    keep = has_time & (tt > before)
    back = has_time & ~keep
    rows_back = np.flatnonzero(back)
    steps = before[rows_back] - t[rows_back]
    no_time = np.flatnonzero(~has_time)
    report = StampReport(
        int(rows_back.size), tuple((rows_back[:FIRST_ROWS] + first_row).tolist()),
        tuple(t[rows_back[:FIRST_ROWS]].tolist()), float(steps.max()) if steps.size else 0.0,
        int(no_time.size), tuple((no_time[:FIRST_ROWS] + first_row).tolist()))
    return keep, report


def copies_dropped(keep: np.ndarray, columns) -> int:
    """How many of the rows ``keep`` drops copy the row before them in every one of
    ``columns`` (arrays over the same rows; NaN equal to NaN): rows whose loss loses nothing."""
    drop = np.flatnonzero(~np.asarray(keep, bool))
    drop = drop[drop > 0]
    same = np.ones(len(drop), bool)
    for column in columns:
        a, b = np.asarray(column)[drop], np.asarray(column)[drop - 1]
        same &= (a == b) | (np.isnan(a) & np.isnan(b))
    return int(same.sum())
