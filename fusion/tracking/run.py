"""A tracker's run over a whole recording: :func:`run_recording` feeds every instant of it
through the filter's one path (:meth:`armfusion.fusion.tracking.filter.Tracker.step`, the same as
live), with the conversions to SI units and the saturation checks done for the whole span
at once, and the differentiators' fits and the kinematic frames for a block of instants at
once (:func:`prepare_block`, one compiled call each), and
keeps what the filter said at each (:class:`RunArrays`), as a :class:`TrackRun`; with truth
in the recording, scored by :mod:`armfusion.fusion.tracking.scoring`."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.measurement import AccelReadings
from armfusion.fusion.tracking.run_results import (  # noqa: F401 (TrackRun and combination_column: imported from here)
    RunArrays,
    TrackRun,
    combination_column,
)
from armfusion.fusion.tracking.scoring import truth_at
from armfusion.fusion.tracking.settings import (
    C_SAMPLES,
    C_SATURATED,
    ENC,
    GYRO,
    MAG,
)
from armfusion.fusion.tracking.update import InstantReadings, MagReading
from armfusion.models.sensor_models import mpu9150_temperature_c
from armfusion.sensors.samples import Recording, Stream

PREPARED_MAX = 1024
"""The most instants whose kinematic frames a run holds at once (about 2 kB each)."""


def joint_free_clock(rec: Recording) -> Stream:
    """An arm with no joints has no encoder: its instants are the base gyro's, as an encoder
    stream of no counts (``(N, 0)``), so that the filter's one path steps on them."""
    g = rec.get(GYRO)
    if g is None or not len(g):
        raise ValueError("an arm with no joints is tracked from its base IMU, and the recording "
                         "has no gyro stream 'imu_gyro'")
    return Stream(ENC, "encoder", g.t_s, np.zeros((len(g.t_s), 0), dtype=np.int64), ())


def run_recording(tr, rec: Recording, t_stop_s: float | None = None, truth: bool = True,
                  block: int = 256, progress: Callable[[float], None] | None = None) -> TrackRun:
    """Fuse every sample of ``rec`` after the tracker ``tr``'s current time (up to
    ``t_stop_s``), instant by instant through its one filter path. The counts are turned
    into SI units (at the IMU's temperature then) and checked for saturation for the whole
    span at once. The encoders and the gyro go through the differentiators, and the
    kinematic frames are made, a ``block`` of instants at a time, with the offsets and gyro
    bias of the block's start (live: of the instant): their drift since is carried exactly
    by the product of exponentials, and enters the motion term only to first order (the
    frames of a long block are made :data:`PREPARED_MAX` instants at a time, all with the
    block's start's). With ``truth``
    and truth streams in ``rec``, errors and NEES are kept too. ``progress(fraction_done)``
    is called after every block."""
    if isinstance(block, bool) or not isinstance(block, int | np.integer) or block < 1:
        raise ValueError(f"block must be a whole number of instants, at least 1; got {str(block)[:40]!r}")
    block = int(block)
    t0_wall = time.perf_counter()
    raw, times = _span_streams(tr, rec, t_stop_s)
    span = _span_samples(tr, raw, times, _temperatures(tr, rec))
    T = len(times)
    has_truth = truth and rec.get("true_q") is not None and rec.get("true_base") is not None
    out = RunArrays(T, tr.arm.n_joints, len(tr.sensor_names), keep_cov=has_truth, size=tr.layout.size)
    for b0 in range(0, T, block):
        b1 = min(T, b0 + block)
        x_block = tr.x  # the frames' offsets and gyro bias: the block's start's
        for c0 in range(b0, b1, PREPARED_MAX):  # (a long block: its frames a part at a time)
            _run_part(tr, span, c0, min(b1, c0 + PREPARED_MAX), x_block, out)
        if progress is not None:
            progress(b1 / T)
    elapsed = time.perf_counter() - t0_wall
    truth_q = rec.get("true_q") if truth else None
    truth_b = rec.get("true_base") if truth else None
    tq = truth_at(truth_q, times) if truth_q is not None and len(truth_q) else None
    tb = truth_at(truth_b, times, angles=True) if truth_b is not None and len(truth_b) else None
    return out.finish(tr, times, elapsed, tq, tb)


def _span_streams(tr, rec: Recording, t_stop_s: float | None) -> tuple[dict[str, Stream], np.ndarray]:
    """The streams of ``rec`` the tracker ``tr`` takes, from a little before its current time
    to ``t_stop_s`` (the tracker's rates set from them), and every instant after its current
    time in that span, where any of them has a sample."""
    raw = {s: rec.get(s) for s in tr.sensor_names if rec.get(s) is not None and len(rec.get(s))}
    if ENC not in raw and tr.arm.n_joints == 0 and GYRO in raw:
        raw[ENC] = joint_free_clock(rec)
    if ENC not in raw:
        raise ValueError("the recording has no encoder stream 'enc': nothing to track")
    tr.set_rates({s: (v.rate_hz or 100.0) for s, v in raw.items()})
    t_from = tr.t_s
    t_stop = np.inf if t_stop_s is None else float(t_stop_s)
    raw = {s: v.between(t_from - 2.0, t_stop + 1e-6) for s, v in raw.items()}
    raw = {s: v for s, v in raw.items() if len(v)}
    if ENC not in raw:
        raise ValueError(f"the recording has no encoder sample after t = {t_from:.3f} s")
    times = np.unique(np.concatenate([v.t_s for v in raw.values()]))
    return raw, times[(times > t_from + 1e-9) & (times <= t_stop + 1e-9)]


@dataclass(frozen=True)
class _SpanSamples:
    """Every sample of a span, converted and checked at once, laid out by instant (``T``
    instants) for the filter's per-instant path."""

    times: np.ndarray
    q_enc_all: np.ndarray
    """The encoders' angles (rad), by encoder sample."""
    gyro_B: np.ndarray | None
    """The gyro (rad/s, base axes), by gyro sample."""
    mag_B: np.ndarray | None
    """The compass (base axes), by compass sample; ``mag_counts`` as the device gave them."""
    mag_counts: np.ndarray | None
    ok_rows: dict[str, np.ndarray]
    """Per instant, the row of the encoder's, gyro's and compass's valid sample (-1: none)."""
    acc_idx: np.ndarray
    """The accelerometers with samples in the span (indices in the tracker's sensors),
    ``acc_info`` their selection."""
    acc_info: object
    acc_counts: np.ndarray
    """``(T, Sa, 3)``: each instant's accelerometer samples as the devices gave them; ``acc_phys`` in g."""
    acc_phys: np.ndarray
    acc_ok: np.ndarray
    """``(T, Sa)``: a valid (unsaturated) sample; ``acc_seen``: any sample; ``all_ok (T,)``:
    every one valid."""
    acc_seen: np.ndarray
    all_ok: np.ndarray


def _span_samples(tr, raw: dict[str, Stream], times: np.ndarray,
                  temperature_at: Callable[[np.ndarray], np.ndarray | None]) -> _SpanSamples:
    """The span's samples in SI units (at the IMU's temperature then: ``temperature_at``) and checked for
    saturation at once, counted in the tracker's health, laid out by instant; the filter
    started at the first encoder sample if it was not."""
    T = len(times)
    rows, phys, valid = {}, {}, {}
    counts = tr.health.counts
    for s, v in raw.items():
        rows[s] = _rows_at(times, v.t_s)
        c = v.values.astype(float)
        ok = ~tr.readings.models[s].saturated(c).any(axis=1)
        valid[s] = ok
        phys[s] = tr.readings.physical(s, c, temperature_at(v.t_s))
        used = rows[s][rows[s] >= 0]
        i = tr.sensor_index[s]
        counts[i, C_SAMPLES] += len(used)
        counts[i, C_SATURATED] += int((~ok[used]).sum())
    enc = raw[ENC]
    q_enc_all = enc.values / tr.counts_per_rad
    if not tr.filter_started:  # the offsets are fixed by the first encoder sample
        tr.start_filter(q_enc_all[min(int(np.searchsorted(enc.t_s, tr.t_s - 1e-9)), len(enc) - 1)])
    acc_streams = [s for s in tr.accel_streams if s in raw]
    acc_idx = np.array([tr.sensor_index[s] for s in acc_streams], dtype=np.int64)
    # per instant: which accelerometers have a valid sample, as (T, Sa) row indices
    acc_rows = np.stack([np.where(rows[s] >= 0, rows[s], -1) for s in acc_streams], 1) \
        if acc_streams else np.full((T, 0), -1)
    acc_ok = np.stack([(rows[s] >= 0) & valid[s][np.maximum(rows[s], 0)] for s in acc_streams], 1) \
        if acc_streams else np.zeros((T, 0), bool)
    # every instant's accelerometer samples as (T, Sa, 3) arrays: one index per step
    Sa = len(acc_streams)
    acc_counts = np.zeros((T, Sa, 3))
    acc_phys = np.zeros((T, Sa, 3))
    for j, s in enumerate(acc_streams):
        have = acc_rows[:, j] >= 0
        acc_counts[have, j] = raw[s].values[acc_rows[have, j]]
        acc_phys[have, j] = phys[s][acc_rows[have, j]]
    ok_rows = {s: np.where((rows[s] >= 0) & valid[s][np.maximum(rows[s], 0)], rows[s], -1)
               for s in (ENC, GYRO, MAG) if s in rows}
    return _SpanSamples(
        times, q_enc_all, phys[GYRO] @ tr.R_0I.T if GYRO in raw else None,
        phys[MAG] @ tr.R_0I.T if MAG in raw else None, raw[MAG].values if MAG in raw else None,
        ok_rows, acc_idx, tr.measurements.selection(acc_idx), acc_counts, acc_phys, acc_ok, acc_rows >= 0,
        acc_ok.all(axis=1))


def _run_part(tr, span: _SpanSamples, c0: int, c1: int, x_block: np.ndarray, out: RunArrays) -> None:
    """The instants ``c0:c1`` of the span through the filter, one by one, their
    differentiators' fits and kinematic frames made first at once (:func:`prepare_block`),
    with the offsets and gyro bias ``x_block`` of their block's start; each recorded in ``out``."""
    times, q_enc_all, gyro_B, mag_B, mag_counts, ok_rows = (
        span.times, span.q_enc_all, span.gyro_B, span.mag_B, span.mag_counts, span.ok_rows)
    acc_idx, acc_info, acc_counts, acc_phys, acc_ok, acc_seen, all_ok = (
        span.acc_idx, span.acc_info, span.acc_counts, span.acc_phys, span.acc_ok, span.acc_seen, span.all_ok)
    health, step, readings_of = tr.health, tr.step, tr.measurements.readings
    # the per-instant rows as plain Python values (cheaper to test one by one)
    t_l = times[c0:c1].tolist()
    enc_l, gyro_l, mag_l = ([-1] * (c1 - c0) if s not in ok_rows else ok_rows[s][c0:c1].tolist()
                            for s in (ENC, GYRO, MAG))
    all_l = all_ok[c0:c1].tolist()
    ke_c = ok_rows[ENC][c0:c1]
    kg_c = ok_rows[GYRO][c0:c1] if GYRO in ok_rows else np.full(c1 - c0, -1)
    gyro_c = gyro_B[np.maximum(kg_c, 0)] if gyro_B is not None else np.zeros((c1 - c0, 3))
    km_c = ok_rows[MAG][c0:c1] if MAG in ok_rows else np.full(c1 - c0, -1)
    # a frame wherever something is fused: the accelerometers, or the compass alone
    prepared = prepare_block(tr, times[c0:c1], q_enc_all[np.maximum(ke_c, 0)], ke_c >= 0, gyro_c,
                             kg_c >= 0, all_ok[c0:c1] | acc_ok[c0:c1].any(axis=1) | (km_c >= 0),
                             x_block)
    for i in range(c0, c1):
        r = i - c0
        t = t_l[r]
        acc = None
        if all_l[r]:
            acc = AccelReadings(acc_idx, acc_counts[i], acc_phys[i], acc_info)
        else:
            ok = acc_ok[i]
            if ok.any():
                acc = readings_of(acc_idx[ok], acc_counts[i, ok], acc_phys[i, ok])
            if acc_seen[i].any():  # saturated samples: the sensors did speak
                health.heard(acc_idx[acc_seen[i]], t)
        ke, kg, km = enc_l[r], gyro_l[r], mag_l[r]
        step(t, InstantReadings(q_enc_all[ke] if ke >= 0 else None, gyro_B[kg] if kg >= 0 else None,
                                acc, MagReading(mag_counts[km], mag_B[km]) if km >= 0 else None),
             prepared[r])
        out.record(tr, i)


def prepare_block(tr, t: np.ndarray, q_enc: np.ndarray, enc_has: np.ndarray, gyro: np.ndarray,
                  gyro_has: np.ndarray, need_frame: np.ndarray, x: np.ndarray):
    """For a block of B instants ``t`` that the tracker ``tr``'s ``step`` will then take in
    order (its started filter's): the encoders' angles ``q_enc (B, n)`` and the gyro ``(B, 3)``
    (rad/s, base axes) where ``enc_has``/``gyro_has``, through the differentiators at once,
    and the kinematic frame of each instant ``need_frame`` (those with accelerometers or the compass) made
    as ``Tracker._frame_now`` makes it, with the offsets and gyro bias of ``x``, in one
    compiled call. Returns, per instant, the encoder fit at it
    (None before any encoder sample) and its frame (or None), for ``step``'s
    ``prepared``; ``Tracker._frame_now`` and this hold the same inputs to the frame."""
    L = tr.layout
    e_at, _, e_have = tr.enc_rates.push_block(t, q_enc, enc_has)
    _, g_latest, g_have = tr.gyro_rates.push_block(t, gyro, gyro_has)
    B = len(t)
    # the gyro's reading at each instant, else its last (the filter's before it)
    last = np.maximum.accumulate(np.where(gyro_has, np.arange(B), -1))
    w = gyro[np.maximum(last, 0)]
    w_have = last >= 0
    if tr.last_gyro_B is not None:
        w[~w_have] = tr.last_gyro_B
        w_have[:] = True
    om = np.where(w_have[:, None], tr.process.rate(w, x), 0.0)
    omd = g_latest[:, 1]  # zero where the gyro has no fit yet, as _frame_now's None
    make = need_frame & e_have
    e_l = [e if h else None for e, h in zip(list(e_at), e_have.tolist(), strict=True)]
    if not make.any():
        return [(e, None) for e in e_l]
    fields = tr.frame_constants.fields_block(e_at, make, x[L.offset], om, omd,
                                             tr.settings.motion_compensation)
    frames = tr.measurements.with_noise(Frames.of(fields)).split()
    return [(e, f if m else None) for e, f, m in zip(e_l, frames, make.tolist(), strict=True)]



def _temperatures(tr, rec: Recording):
    """The IMU's latest temperature reading (°C) at each of some times (the tracker's, before
    any), when the config's corrections depend on it; else a function that gives None."""
    temp = rec.get("imu_temp")
    if temp is None or not len(temp) or not tr.readings.drifts_with_temperature:
        return lambda t: None
    temp_t, temp_c = temp.t_s, mpu9150_temperature_c(temp.values[:, 0])
    before = tr.readings.temperature_c

    def at(t: np.ndarray):
        k = np.searchsorted(temp_t, t, side="right") - 1
        return np.where(k >= 0, temp_c[np.maximum(k, 0)], before)
    return at


def _rows_at(times: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Index into ``t_s`` of the sample at each of ``times`` (-1 where there is none)."""
    pos = np.searchsorted(t_s, times)
    pos_c = np.minimum(pos, len(t_s) - 1)
    return np.where(np.abs(t_s[pos_c] - times) < 1e-9, pos_c, -1)
