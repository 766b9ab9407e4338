"""The rules every raw sample meets, whichever door it comes in by (a recording file, an
import, the wire), those that need no config; and the place of a sample in its file.

A sample is refused when

- its time is not finite, or beyond :data:`TIME_LIMIT_S` from 0 (a float of seconds that
  large cannot tell two instants a microsecond apart: no clock a sensor runs on);
- its time does not increase within its stream (:class:`armfusion.sensors.samples.Stream`);
- it begins a short run of instants set apart from the rest of its recording by more than
  the node's clock window (:func:`apart_problem`);
- its stream's samples come, by their median step, faster than :data:`FASTEST_SAMPLING_HZ`
  (:func:`density_problem`: times in another unit than the second);
- one of its raw values lies beyond :data:`FEED_MIN` … :data:`FEED_MAX`, the 32-bit range
  of the encoder feed, which holds every register a supported device has (an ADXL345 axis
  -512…511, the MPU-9150's int16, the AK8975's 13 bits).

The device's own, narrower range comes from the sensor's description in the config and is
checked by :mod:`armfusion.models.sample_admission`, with the same words (:func:`range_words`); the
fusion node's admission (``armfusion.fusion.service.admission``) says its refusals with them too.

:func:`sample_place` names a sample in its file: ``row 5001 (line 5002)`` of a recording
CSV, ``topic raw/enc, message 12`` of an MCAP file, ``sample 12 of enc`` otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.sensors.samples import RAW_KINDS, TRUTH_KINDS, Recording, Stream

FEED_MIN, FEED_MAX = -(1 << 31), (1 << 31) - 1
"""The encoder feed's counts (:mod:`armfusion.sensors.encoders`: int32 per joint), the widest range a
raw value of any supported device can have."""

TIME_LIMIT_S = 2.0**52 * 1e-6
"""4.5e9 s (143 years: Unix time until 2112): beyond it the spacing of float64 seconds
exceeds a microsecond, a thousandth of the fastest sampling the node admits (1 kHz)."""

FASTEST_SAMPLING_HZ = 100e3
"""No supported device delivers its samples faster than 8 kHz (the MPU-9150's gyroscope at
its fastest; the ADXL345 3.2 kHz): a raw stream whose median step is under 10 µs is not
stamped in seconds of a sensor's clock."""

CLOCK_WINDOW_S = 2.0
RUN_SAMPLES = 16
"""A run of fewer than :data:`RUN_SAMPLES` instants set apart from the rest of a recording by
more than :data:`CLOCK_WINDOW_S` (or a hundred of its median steps, if longer) is not on the
sensors' clock: the fusion node's clock window and burst (``AdmissionSettings``'s
``clock_window_s`` and ``burst_samples``), applied to a file."""

SHOWN = 40
"""Characters of a value a message repeats at most."""

CSV_ROW_TIMES = "csv_row_t_s"
CSV_ROW_LINES = "csv_row_lines"
"""Keys of a CSV recording's ``meta``: every data row's time and line (for :func:`sample_place`)."""
MCAP_TOPICS = "mcap_topics"
"""Key of an MCAP recording's ``meta``: each stream's topic."""


def shown(value, quoted: bool = True) -> str:
    """``value`` for a message: its repr (or text), cut to :data:`SHOWN` characters."""
    text = repr(value) if quoted else str(value)
    return text if len(text) <= SHOWN else text[:SHOWN - 1] + "…"


def range_words(channel: str, value, t_s: float, lo, hi) -> str:
    """How a value beyond its range is said, at every door (the wire's ``out_of_range``)."""
    return f"{channel} = {shown(value)} at t = {float(t_s):.6g} s is beyond the device's range {lo}…{hi}"


@dataclass(frozen=True)
class SampleProblem:
    """Why sample ``index`` of stream ``stream`` is refused: ``reason`` (``out_of_range``,
    ``time_not_finite``, ``time_beyond_limit``, ``time_too_dense``, …) and ``words`` (one
    line, no place)."""

    stream: str
    index: int
    reason: str
    words: str


def time_problem(stream: str, t_s: np.ndarray) -> SampleProblem | None:
    """The first sample of ``t_s`` whose time is not finite or beyond :data:`TIME_LIMIT_S`."""
    t = np.asarray(t_s, dtype=np.float64)
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        return SampleProblem(stream, i, "time_not_finite", f"t = {float(t[i])!r} is not a finite time")
    bad = np.abs(t) > TIME_LIMIT_S
    if bad.any():
        i = int(np.argmax(bad))
        return SampleProblem(stream, i, "time_beyond_limit",
                             f"t = {float(t[i]):.6g} s is beyond any sensor's clock (|t| at most "
                             f"{TIME_LIMIT_S:.3g} s, where a float of seconds still resolves 1 µs)")
    return None


def range_problem(stream: Stream, lo, hi) -> SampleProblem | None:
    """The first sample of ``stream`` with a value beyond ``lo`` … ``hi`` (or not finite)."""
    v = stream.values
    if not v.size:
        return None
    if v.dtype.kind == "f":
        bad = ~((v >= lo) & (v <= hi))  # NaN too
    else:
        if int(v.min()) >= lo and int(v.max()) <= hi:
            return None
        bad = (v < lo) | (v > hi)
    if not bad.any():
        return None
    i, j = (int(x) for x in np.argwhere(bad)[0])
    return SampleProblem(stream.name, i, "out_of_range",
                         range_words(stream.channels[j], v[i, j].item(), stream.t_s[i], lo, hi))


def truth_problem(stream: Stream) -> SampleProblem | None:
    """The first ground-truth angle of ``stream`` that is infinite or whose degrees overflow a
    float (beyond 3e306 rad): no angle, and every error against it would be one. An empty
    (NaN) value is a gap, not refused."""
    v = np.asarray(stream.values, dtype=np.float64)
    with np.errstate(over="ignore"):
        bad = np.isinf(np.degrees(v))
    if not bad.any():
        return None
    i, j = (int(x) for x in np.argwhere(bad)[0])
    return SampleProblem(stream.name, i, "truth_not_finite",
                         f"{stream.channels[j]} = {shown(v[i, j].item())} rad at t = "
                         f"{float(stream.t_s[i]):.6g} s is not an angle (its degrees are not a finite "
                         "number)")


def density_problem(stream: Stream) -> SampleProblem | None:
    """``stream`` refused as a whole (at its second sample) when its median step is shorter
    than one sample at :data:`FASTEST_SAMPLING_HZ`."""
    if len(stream) < 3:
        return None
    step_s = float(np.median(np.diff(np.asarray(stream.t_s, dtype=np.float64))))
    if not step_s < 1.0 / FASTEST_SAMPLING_HZ:
        return None
    return SampleProblem(stream.name, 1, "time_too_dense",
                         f"a sample every {step_s:.3g} s (the stream's median step), faster than any "
                         f"sensor delivers ({FASTEST_SAMPLING_HZ / 1e3:.0f} kHz at most): are its times in "
                         f"seconds?")


def apart_problem(rec: Recording) -> SampleProblem | None:
    """The first instant of a short run set apart from the rest of ``rec`` (see
    :data:`RUN_SAMPLES`): a last row stamped 10^9 s after a minute of samples, say."""
    times = [s.t_s for s in rec.streams.values() if len(s)]
    if not times:
        return None
    t = np.unique(np.concatenate(times))
    if t.size < 2:
        return None
    step = np.diff(t)
    apart_s = max(CLOCK_WINDOW_S, 100.0 * float(np.median(step)))
    cuts = np.flatnonzero(step > apart_s) + 1
    if not cuts.size:
        return None
    starts, ends = np.concatenate([[0], cuts]), np.concatenate([cuts, [t.size]])
    sizes = ends - starts
    body = int(np.argmax(sizes))
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        if b - a >= RUN_SAMPLES or a == starts[body]:
            continue
        at = float(t[a])
        for s in rec.streams.values():
            i = int(np.searchsorted(s.t_s, at))
            if i < len(s) and s.t_s[i] == at:
                return SampleProblem(
                    s.name, i, "time_apart",
                    f"t = {at:.6g} s begins a run of {b - a} instant(s) more than {apart_s:.3g} s apart "
                    f"from the rest of the recording (its {int(sizes[body])} instants at t = "
                    f"{float(t[starts[body]]):.6g} … {float(t[ends[body] - 1]):.6g} s): not on the "
                    "sensors' clock")
    return None


def feed_problems(rec: Recording) -> list[SampleProblem]:
    """The first refused sample of each stream of ``rec`` by the rules above (time; raw
    values within the feed's range), config order, then an instant apart from the rest
    (:func:`apart_problem`); empty when every sample passes."""
    out = []
    for s in rec.streams.values():
        p = time_problem(s.name, s.t_s)
        if p is None and s.kind in RAW_KINDS:
            p = range_problem(s, FEED_MIN, FEED_MAX) or density_problem(s)
        elif p is None and s.kind in TRUTH_KINDS:
            p = truth_problem(s)
        if p is not None:
            out.append(p)
    if not out:
        p = apart_problem(rec)
        if p is not None:
            out.append(p)
    return out


def sample_place(rec: Recording, stream: str, index: int) -> str:
    """Where sample ``index`` of ``stream`` is in the file ``rec`` was read from."""
    s = rec.get(stream)
    meta = rec.meta
    if s is not None and CSV_ROW_TIMES in meta and 0 <= index < len(s):
        rows = meta[CSV_ROW_TIMES]
        r = int(np.searchsorted(rows, s.t_s[index]))
        if r < len(rows) and rows[r] == s.t_s[index]:
            return f"row {r + 1} (line {meta[CSV_ROW_LINES][r]}), stream {stream}"
    topic = meta.get(MCAP_TOPICS, {}).get(stream)
    if topic is not None:
        return f"topic {topic}, message {index + 1}"
    return f"sample {index + 1} of {stream}"
