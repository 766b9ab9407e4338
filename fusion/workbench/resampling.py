"""A stream resampled by linear interpolation from a lower rate, recognised from its noise.

A logger that reads a 100 Hz sensor and writes 125 Hz rows (two clocks merged by time)
writes each row as a mix of the two nearest samples, at a fraction that repeats every five
rows: a row that falls on a sample keeps its noise, one half-way between two has half its
variance. The noise's variance, and that of its second difference (which removes a smooth
motion), then repeats with that period. :func:`resampling` tests each period (the
Brown-Forsythe test of equal spread across the rows' phases), and where one is beyond chance
matches the pattern linear interpolation from each rate ``rate · q / p`` would leave, to name
the source rate.

What it means for a model: the stream's noise is not white (neighbouring rows share samples)
and its σ varies by row; the fit's window means average over whole periods, so a window of a
multiple of the period (5 rows at 125 Hz from 100 Hz) sees the same noise in every window.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import gcd
from typing import Any

import numpy as np
from scipy.stats import levene

MAX_PERIOD = 10
"""Periods tried (rows): 2 to this."""
ALPHA = 1e-6
"""False-alarm rate of the test (Bonferroni over the periods and the axes)."""


@dataclass(frozen=True)
class Resampling:
    """A stream whose noise says it was linearly interpolated from a lower rate."""

    stream: str
    period: int
    """Rows after which the pattern repeats."""
    rate_hz: float
    """The stream's rate (its rows)."""
    source_hz: float
    """The rate it was interpolated from (``rate_hz · q / period``)."""
    p_value: float
    pattern: tuple[float, ...]
    """The second difference's variance at each phase, over its mean."""

    def words(self) -> str:
        return (f"{self.stream}: resampled by linear interpolation from about {self.source_hz:.0f} Hz to "
                f"{self.rate_hz:.0f} Hz (its noise's second difference varies with a period of "
                f"{self.period} rows, {', '.join(f'{v:.2f}' for v in self.pattern)} of its mean; "
                f"p = {self.p_value:.1e}): neighbouring rows share samples, the noise is not white; "
                f"window means of a multiple of {self.period} rows average it evenly")

    def as_dict(self) -> dict[str, Any]:
        return {"stream": self.stream, "period_rows": self.period, "rate_hz": round(self.rate_hz, 3),
                "source_hz": round(self.source_hz, 3), "p_value": self.p_value,
                "pattern": [round(v, 4) for v in self.pattern], "words": self.words()}


def interpolation_pattern(period: int, q: int, phase: float) -> np.ndarray:
    """The variance of the second difference of white noise at ``q`` samples per ``period``
    rows, interpolated linearly, at each of the period's rows (relative to its mean)."""
    n = 4 * period + 3
    pos = (np.arange(n) * q) / period + phase  # each row's position in source samples
    W = np.zeros((n, int(np.ceil(pos[-1])) + 2))
    i0 = np.floor(pos).astype(int)
    f = pos - i0
    W[np.arange(n), i0] = 1.0 - f
    W[np.arange(n), i0 + 1] += f
    d2 = W[2:] - 2.0 * W[1:-1] + W[:-2]
    v = np.sum(d2**2, 1)  # row k+1's second difference
    per = np.array([np.mean(v[(np.arange(len(v)) + 1) % period == r]) for r in range(period)])
    return per / per.mean()


def resampling(stream: str, t_s: np.ndarray, values: np.ndarray) -> Resampling | None:
    """Whether ``values (N, k)`` sampled at ``t_s`` were interpolated from a lower rate (None:
    no period beyond chance)."""
    v = np.asarray(values, float)
    ok = np.all(np.isfinite(v), 1)
    if ok.sum() < 20 * MAX_PERIOD:
        return None
    # the longest run of rows without a gap: the phases count rows
    idx = np.flatnonzero(ok)
    breaks = np.flatnonzero(np.diff(idx) != 1)
    starts = np.r_[0, breaks + 1]
    ends = np.r_[breaks + 1, len(idx)]
    k = int(np.argmax(ends - starts))
    run = idx[starts[k]:ends[k]]
    if len(run) < 20 * MAX_PERIOD:
        return None
    y = v[run]
    d2 = y[2:] - 2.0 * y[1:-1] + y[:-2]
    scale = np.median(np.abs(d2), 0)
    scale = np.where(scale > 0, scale, np.std(d2, 0))
    keep = scale > 0  # an axis whose second difference is all zero (quantised, constant) has no noise to read
    if not keep.any():
        return None
    d2 = d2[:, keep] / scale[keep]  # each axis in its own units
    rows = np.arange(1, len(d2) + 1)
    tests = (MAX_PERIOD - 1) * d2.shape[1]
    best = None
    for p in range(2, MAX_PERIOD + 1):
        for a in range(d2.shape[1]):
            groups = [d2[rows % p == r, a] for r in range(p)]
            pv = float(levene(*groups, center="median").pvalue) * tests
            if pv < ALPHA and (best is None or pv < best[0]):
                best = (pv, p, a)
    if best is None:
        return None
    pv, p, a = best
    # a multiple of a shorter period that is significant on its own: the shorter one
    for q in range(2, p):
        if p % q == 0:
            groups = [d2[rows % q == r, a] for r in range(q)]
            if float(levene(*groups, center="median").pvalue) * tests < ALPHA:
                p = q
                break
    var = np.array([np.mean(d2[rows % p == r, a] ** 2) for r in range(p)])
    var = var / var.mean()
    rate = 1.0 / float(np.median(np.diff(t_s[run])))
    fits = []
    for q in range(1, p):
        if gcd(q, p) != 1:
            continue
        for phase in np.arange(p) / p:
            pat = interpolation_pattern(p, q, phase)
            fits.append((float(np.sum((pat - var) ** 2)), q))
    q = min(fits)[1] if fits else 1
    return Resampling(stream, p, rate, rate * q / p, min(pv, 1.0), tuple(float(x) for x in var))


def resampled_streams(rec, streams) -> list[Resampling]:
    """Every stream of ``streams`` in the recording ``rec`` that was resampled."""
    out = []
    for s in streams:
        if s not in rec.streams:
            continue
        st = rec.streams[s]
        r = resampling(s, np.asarray(st.t_s, float), np.asarray(st.values, float).reshape(len(st.t_s), -1))
        if r is not None:
            out.append(r)
    return out
