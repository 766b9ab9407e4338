"""Starting a tracker from a recording (:func:`start_from_recording`, how: :class:`StartOptions`):
the first still stretch's startup calibration (:func:`armfusion.fusion.startup.solve.solve_still`,
on readings the config's effects corrected), the gyro bias, heading and Earth-field reference
from the same window (:func:`armfusion.fusion.tracking.imu_still.imu_still_from_recording`), and,
offline, the choice between rival branches by the motion that follows
(:func:`armfusion.fusion.tracking.branch_motion.branch_by_motion`). :func:`warm_up` compiles (or
loads) the tracker's kernels before a node takes samples."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from armfusion.fusion.startup.prior import StartupPrior
from armfusion.fusion.startup.results import StartupResult
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.fusion.startup.static import Segment, StaticDetectionSettings, find_static_segments
from armfusion.fusion.tracking.branch_motion import branch_by_motion
from armfusion.fusion.tracking.differentiator import prime
from armfusion.fusion.tracking.filter import Tracker
from armfusion.fusion.tracking.imu_still import imu_still_from_recording
from armfusion.fusion.tracking.initial import ImuStill
from armfusion.fusion.tracking.run import joint_free_clock
from armfusion.fusion.tracking.settings import ENC, GYRO, IMU_ACC, MAG, TrackerSettings
from armfusion.models.arm import ArmModel
from armfusion.models.sensor_models import encoder_angles_at, mpu9150_temperature_c, stream_models
from armfusion.sensors.samples import Recording


@dataclass(frozen=True)
class Start:
    """How a tracker was started from a recording: the still window, the startup
    calibration, what the IMU said, and the notes on sensors left out."""

    t_start_s: float
    t_end_s: float
    startup: StartupResult
    imu: ImuStill
    notes: tuple[str, ...]
    geometric: StartupResult | None = None
    """The startup before the config's joint effects were undone (what a later still
    window's solve compares with, through :func:`armfusion.fusion.startup.solve.prior_after_move`)."""
    encoder_rad: np.ndarray | None = None
    """The encoders' angles (counts / counts per rad) at the end of the still window."""


class NoStillWindowError(ValueError):
    """The recording has no still stretch to calibrate from."""


MOVING_WINDOW_SAMPLES = 5
"""Encoder samples averaged by a moving start (:func:`moving_window`)."""
MOVING_SEARCH_S = 5.0
"""How far into the recording a moving start looks for its least-moving instants."""


def moving_window(arm: ArmModel, rec: Recording, search_s: float = MOVING_SEARCH_S,
                  samples: int = MOVING_WINDOW_SAMPLES,
                  magnitude_range_g: tuple[float, float] = (0.8, 1.2)):
    """The startup's readings on an arm that never stands still: the ``samples`` encoder
    instants over which the joints travel least, averaged, among those at which every link
    accelerometer (and the base IMU's) can be used: no sample saturated and every sample
    within ``magnitude_range_g`` of gravity (the startup's own check,
    :func:`armfusion.fusion.startup.readings.readings_from_recording`, which leaves a sensor out
    otherwise; a shaft accelerometer reading 1.26 g at the least-moving instants of a fast
    trial left the startup nothing to solve from). The first ``search_s`` are searched; where
    no instant there can be used, the whole recording. Each link accelerometer's σ is
    widened by what that travel turns gravity by (up to 1 g per radian of the joints before
    it), by its reading's spread in the window, and by how far its mean's magnitude is from
    1 g (at least that much of it is the motion's acceleration, not gravity), so that the
    startup's σ covers the motion; the tracker refines the angles from there. Returns
    ``(window, readings, checks, note)``; :class:`NoStillWindowError` when too short, or
    when no instant has every accelerometer within range (saying which one never was)."""
    from armfusion.fusion.startup.solve import readings_from_recording

    enc = rec.get(ENC)
    if enc is None or len(enc) < samples:
        raise NoStillWindowError("no still stretch, and too few encoder samples to start on a moving arm")
    t = enc.t_s
    q = enc.values / arm.counts_per_rad
    models = stream_models(arm)
    names = [m.name for m in arm.link_accelerometers] + ([IMU_ACC] if arm.imu is not None else [])
    usable = np.ones(len(t) - samples + 1, dtype=bool)  # per window of encoder instants
    never = []
    for name in names:
        s = rec.get(name)
        if s is None or not len(s) or name not in models:
            continue
        m = models[name]
        bad = m.saturated(s.values).any(axis=1)
        mag = np.linalg.norm(m.from_counts(s.values), axis=1)
        bad |= (mag < magnitude_range_g[0]) | (mag > magnitude_range_g[1])
        # a window [t_k, t_k+samples-1] is unusable where a bad sample of this sensor falls in it
        nbad = np.concatenate([[0], np.cumsum(bad)])
        lo = np.searchsorted(s.t_s, t[:len(usable)], side="left")
        hi = np.searchsorted(s.t_s, t[samples - 1:], side="right")
        ok = (nbad[hi] - nbad[lo] == 0) & (hi > lo)
        if not ok.any():
            never.append(name)
        usable &= ok
    if not usable.any():
        raise NoStillWindowError(
            "no still stretch, and no instant on the moving arm at which every accelerometer can be used "
            f"(each sample within {magnitude_range_g[0]:g}-{magnitude_range_g[1]:g} g, none saturated)"
            + (f": {', '.join(never)} never is" if never else "") + ": nothing to start from")
    last = max(int(np.searchsorted(t, t[0] + search_s)), samples)
    last = min(last, len(t))
    windows = np.lib.stride_tricks.sliding_window_view(q, samples, axis=0)  # (W, n, samples)
    travel = np.ptp(windows, axis=2)  # (W, n)
    cost = np.where(usable, travel.sum(axis=1), np.inf)
    first = cost[:last - samples + 1]
    searched = search_s
    if np.isfinite(first).any():
        k = int(np.argmin(first))
    else:  # none usable in the first search_s: the first usable instants of the least travel
        k = int(np.argmin(cost))
        searched = float(t[-1] - t[0])
    t0, t1 = float(t[k]), float(t[k + samples - 1])
    readings, checks = readings_from_recording(arm, rec, t0, t1, t1 - t0 + 1e-9, magnitude_range_g)
    sig = {}
    for m in arm.link_accelerometers:
        if m.name in readings.accel_sigma_g:
            turned = float(np.sum(travel[k][: m.link]))
            s = rec.get(m.name).between(t0, t1 + 1e-9)
            spread = np.std(models[m.name].from_counts(s.values), axis=0) if len(s) > 1 else 0.0
            off_g = abs(float(np.linalg.norm(readings.accel_mean_g[m.name])) - 1.0)
            sig[m.name] = np.sqrt(readings.accel_sigma_g[m.name] ** 2 + turned**2 + spread**2 + off_g**2)
    readings = replace(readings, accel_sigma_g={**readings.accel_sigma_g, **sig})
    note = (f"no still stretch near the start: started on the moving arm at t = {t0:.2f}..{t1:.2f} s (the "
            f"least joint travel of the {searched:g} s from t = {float(t[0]):.2f} s at which every "
            "accelerometer can be used: "
            f"{np.degrees(travel[k].max()):.2f} deg), its readings' sigma widened by that motion")
    return Segment(t0, t1), readings, checks, note


SHORT_STILL_WINDOW_S = 0.2
"""The still detector's window when it looks for a still stretch shorter than a second near the
start (two of its 0.1 s grid steps: a 0.6 s stretch still shows as about 0.4 s)."""
SHORT_STILL_MIN_S = 0.3
"""The shortest still stretch a start takes (at 100 Hz, 30 samples of each sensor)."""
LONG_STILL_S = 1.0
"""A still stretch at least this long is read as it always was; a shorter one has its readings'
σ widened (:func:`short_still_readings`)."""


@dataclass(frozen=True)
class StartChoice:
    """Where a start calibrates: a still stretch (``segment``; ``short`` when under
    :data:`LONG_STILL_S`), or, ``segment`` None, the least-moving instants from ``from_s``;
    ``note`` says why, when it is not the first still stretch at the recording's start."""

    segment: Segment | None
    short: bool
    from_s: float
    note: str | None


def choose_start(arm: ArmModel, rec: Recording, window_s: float = 1.0, start_at_s: float | None = None,
                 moving_start: bool = False, near_s: float = MOVING_SEARCH_S) -> StartChoice:
    """Where the startup calibrates: at the recording's start, or from ``start_at_s``.

    The earliest still stretch that begins within ``near_s`` of there, however short (down to
    :data:`SHORT_STILL_MIN_S`: the detector run again with a :data:`SHORT_STILL_WINDOW_S`
    window); where it is the first stretch of a second or more, exactly as that one is found.
    With none there: with ``moving_start`` or ``start_at_s``, the least-moving usable
    instants from there (:func:`moving_window`); else the first still stretch anywhere (the
    note says how far in it is). :class:`NoStillWindowError` when there is nothing to start on."""
    models = stream_models(arm)
    t0 = rec.t_start_s
    if start_at_s is not None:
        if not rec.t_start_s <= start_at_s < rec.t_end_s:
            raise NoStillWindowError(f"the start at t = {start_at_s:g} s is outside the recording "
                                     f"(t = {rec.t_start_s:.2f}..{rec.t_end_s:.2f} s)")
        t0 = float(start_at_s)
        rec = rec.between(t0, np.inf)
    longs = find_static_segments(rec, StaticDetectionSettings(window_s=min(window_s, 1.0)), models)
    shorts = find_static_segments(rec, StaticDetectionSettings(window_s=SHORT_STILL_WINDOW_S,
                                                               min_duration_s=SHORT_STILL_MIN_S), models)
    near = [s for s in shorts if s.t_start_s <= t0 + near_s]
    where = "the recording's start" if start_at_s is None else f"t = {t0:g} s (--start-at)"
    if near:
        first = near[0]
        same = next((s for s in longs if s.t_start_s < first.t_end_s and first.t_start_s < s.t_end_s), None)
        if same is not None:
            return StartChoice(same, False, t0, None if start_at_s is None else
                               f"the startup on the first still stretch from {where}")
        return StartChoice(first, first.duration_s < LONG_STILL_S, t0, None)
    if moving_start or start_at_s is not None:
        return StartChoice(None, False, t0, None)
    if longs:
        s = longs[0]
        return StartChoice(s, False, t0, (
            f"no still stretch within {near_s:g} s of {where}: the startup on the first one, "
            f"{s.t_start_s - t0:.1f} s in; nothing before it is tracked (--moving-start starts at the "
            "start on the moving arm)"))
    if shorts:
        return StartChoice(shorts[0], shorts[0].duration_s < LONG_STILL_S, t0, None)
    raise NoStillWindowError(
        f"no still stretch in the recording (accelerometers, gyro and encoders quiet for at least "
        f"{SHORT_STILL_MIN_S:g} s): the startup calibration needs a still arm (track --moving-start "
        "starts on a moving one)")


def short_still_readings(arm: ArmModel, rec: Recording, seg: Segment, readings):
    """The readings of a still stretch shorter than :data:`LONG_STILL_S`, each link
    accelerometer's σ widened by what so short a stretch leaves unsure: its samples' own
    scatter (above the datasheet's noise, where it is) over their number, and the drift of
    its mean from the stretch's first half to its second (an arm still settling from a move
    reads a trend a second would average out). Returns ``(readings, note)``."""
    models = stream_models(arm)
    sig, widest = {}, 0.0
    for name, sigma in readings.accel_sigma_g.items():
        s = rec.get(name)
        if s is None or name not in models:
            continue
        w = s.between(seg.t_start_s, seg.t_end_s + 1e-9)
        if len(w) < 4:
            continue
        g = models[name].from_counts(w.values)
        half = len(g) // 2
        scatter = np.std(g, axis=0, ddof=1) / np.sqrt(len(g))
        drift = np.abs(g[half:].mean(axis=0) - g[:half].mean(axis=0))
        sig[name] = np.sqrt(sigma**2 + scatter**2 + drift**2)
        widest = max(widest, float(np.max(np.sqrt(scatter**2 + drift**2))))
    readings = replace(readings, accel_sigma_g={**readings.accel_sigma_g, **sig})
    note = (f"the startup on a still stretch of only {seg.duration_s:.2f} s (t = {seg.t_start_s:.2f}.."
            f"{seg.t_end_s:.2f} s; {LONG_STILL_S:g} s is the usual least): each link accelerometer's "
            f"sigma widened by its samples' scatter and its drift over so short a stretch (up to "
            f"{widest * 1e3:.1f} mg)")
    return readings, note


def warm_up(arm: ArmModel, settings: TrackerSettings | None = None) -> float:
    """Compile (the first run after an install) or load (later runs) the tracker's compiled
    kernels with the signatures the live path uses, by tracking 2 s of a simulated arm
    sample by sample after a startup on the 2 s before, so that a node does not pay for it
    while samples queue up. Returns the seconds it took."""
    from armfusion.models.simulator import simulate

    t0 = time.perf_counter()
    rec, _ = simulate(arm, "daily-use", 4.0, seed=0)
    first = rec.between(0.0, 2.0)
    # started on the first two seconds; the next two are fused below
    tr, _ = start_from_recording(arm, first, settings, options=StartOptions(propose_unlock=False))
    values = {s: rec.get(s).values for s in tr.sensor_names if s in rec.streams}
    t_enc = rec.get(ENC).t_s
    n = min(len(v) for v in values.values())
    for i in range(int(np.searchsorted(t_enc, tr.t_s + 1e-9)), n):
        t = float(t_enc[i])
        if i % 2:  # every sensor at one instant, and one device at a time
            tr.update_instant(t, {s: v[i] for s, v in values.items()})
        else:
            for k, (s, v) in enumerate(values.items()):
                tr.update(s, t + 1e-4 * k, v[i])
    return time.perf_counter() - t0


def delay_notes(arm: ArmModel) -> list[str]:
    """What the tracker does with the delays the sensors' descriptions declare (``delay_s``):
    the gyroscope's is made up for (:func:`armfusion.fusion.tracking.process.gyro_newer_weight`), the
    accelerometers' and the compass's too (each reading turned to its stamp by its sensor's
    turn rate over the delay), any other stream's is not, and the notes say which."""
    delays = {k: m.delay_s for k, m in stream_models(arm).items() if m.delay_s > 0}
    out = []
    if GYRO in delays:
        gyro_ms = delays.pop(GYRO) * 1e3
        out.append(f"the gyroscope's delay ({gyro_ms:.3g} ms) made up for (up to half a sample period): "
                   "the attitude turns by the rate at each interval's midpoint")
    accelerometers = {a.name for a in arm.link_accelerometers} | {IMU_ACC}
    turned = [k for k in delays if k == MAG or k in accelerometers]
    if turned:
        out.append("delays made up for by turning each reading to its stamp with its sensor's turn rate: "
                   + ", ".join(f"{k} {delays.pop(k) * 1e3:.3g} ms" for k in turned))
    if delays:
        out.append("delays NOT made up for by the tracker (read at their stamps): "
                   + ", ".join(f"{k} {d * 1e3:.3g} ms" for k, d in delays.items()))
    return out


@dataclass(frozen=True)
class StartOptions:
    """How :func:`start_from_recording` finds its start and solves the startup there; the
    defaults: the earliest still stretch near the recording's start, a one-second window,
    the startup's own settings, the unlock-move search on, no prior but a saved pose."""

    window_s: float = 1.0
    """The startup's still window (s)."""
    moving_start: bool = False
    """With no still stretch near the start (an arm that never stops), start from the
    readings of the least-moving instants there (:func:`moving_window`)."""
    start_at_s: float | None = None
    """Start near this time (s, the recording's clock) rather than at its start; as
    ``moving_start`` where no still stretch is near."""
    startup_settings: StartupSettings | None = None
    propose_unlock: bool = True
    """False: no search for a move that would unlock gravity-blind joints (about 2 s of the
    startup's time, for a caller that does not show it)."""
    prior: StartupPrior | None = None
    """A startup prior other than the saved pose (e.g. ``StartupPrior.assume_parked``)."""
    resolve_by_motion_s: float | None = None
    """For a whole recording (not live), when the startup left joints ``ambiguous``: track
    each candidate branch over the next this many seconds and keep the one the motion's
    readings favour (:func:`armfusion.fusion.tracking.branch_motion.branch_by_motion`)."""
    sigma_given_conventions: bool = False
    """A calibrated config's doubt taken relative to its joint-zero conventions
    (:meth:`armfusion.fusion.identification.correction.StartupCorrection.given_conventions`):
    the σ against the calibration's own zeros, for scoring against a reference those zeros
    aligned (the default, the absolute σ, is what a user's controller needs)."""


def start_from_recording(arm: ArmModel, rec: Recording, settings: TrackerSettings | None = None,
                         prior_q_rad: np.ndarray | None = None, prior_sigma_rad: np.ndarray | None = None,
                         options: StartOptions = StartOptions()) -> tuple[Tracker, Start]:
    """A tracker initialised from the recording's first still stretch: the startup
    calibration there (:func:`armfusion.fusion.startup.solve.solve_still`), the gyro bias, heading and field
    reference from the same window; it starts tracking at the window's end: the still
    stretch's end less ``settings.settle_s`` where the stretch is long enough
    (:func:`settled_split`), so that the filter settles on the still chair before it moves.
    ``prior_q_rad``: a pose saved at the last clean shutdown, checked against the still data
    before it may choose a branch (:class:`armfusion.fusion.startup.solve.StartupPrior`);
    ``options.prior``: any other startup prior.
    Where it starts is :func:`choose_start`'s: the earliest still stretch near the
    recording's start (or ``options.start_at_s``), a short one's σ widened
    (:func:`short_still_readings`). ``options.moving_start`` (or ``start_at_s``): with no
    still stretch near there, start from the least-moving instants there instead
    (:func:`moving_window`), their σ widened by the motion; else the first still stretch
    anywhere, and :class:`NoStillWindowError` with none.
    ``prior_sigma_rad``: with ``prior_q_rad``, how well it is known per joint (a running
    tracker's pose handed on, the arm unmoved): a joint the startup cannot read starts at
    ``prior_q_rad`` with that sigma instead of ``TrackerSettings.unknown_joint_sigma_deg``.
    The rest of the options: :class:`StartOptions`."""
    from armfusion.fusion.startup.solve import solve_still

    prior = options.prior
    if prior is None and prior_q_rad is not None:
        prior = StartupPrior.saved_pose(prior_q_rad)
    window = _startup_window(arm, rec, settings, options)
    corr, readings, notes = _corrected_readings(arm, rec, window, options)
    notes = [*window.notes, *notes, *delay_notes(arm)]
    startup = solve_still(arm, readings, options.startup_settings, prior=prior,
                          propose_unlock=options.propose_unlock)
    notes.extend(startup.notes)
    geometric = startup
    if corr is not None:
        startup = corr.controller_result(startup)
    seg = window.segment
    imu = imu_still_from_recording(arm, rec, seg.t_start_s, seg.t_end_s, startup, settings, corr)
    enc = rec.get(ENC) if arm.n_joints else joint_free_clock(rec)
    if enc is None or not len(enc):
        raise ValueError("the recording has no encoder stream 'enc': nothing to track")
    t_track, note = _tracking_from(arm, window, startup)
    notes += [note] if note else []
    k, enc_rad = encoder_angles_at(arm, enc, t_track)
    rates = {s: (v.rate_hz or 100.0) for s, v in rec.raw().items()}

    def tracker_from(result: StartupResult) -> Tracker:
        t = Tracker(arm, settings, rates_hz=rates, correction=corr)
        t.initialise(result, float(enc.t_s[k]), encoder_counts=enc.values[k], imu=imu,
                     prior_q_rad=prior_q_rad, prior_sigma_rad=prior_sigma_rad)
        _prime(t, rec)
        return t

    if (options.resolve_by_motion_s and startup.candidates_rad is not None
            and len(startup.candidates_rad) > 1):
        chosen, note = branch_by_motion(startup, tracker_from, rec, float(enc.t_s[k]),
                                        options.resolve_by_motion_s, options.startup_settings)
        notes.append(note)
        if chosen is not None:
            startup = chosen
    tr = tracker_from(startup)
    return tr, Start(seg.t_start_s, seg.t_end_s, startup, imu, tuple(notes), geometric, enc_rad)


@dataclass(frozen=True)
class _StartupWindow:
    """Where the startup calibrates: its ``segment`` and averaged ``readings`` (with the
    notes on how they were chosen and checked), and where the still stretch ends when the
    startup leaves its end to the tracker (``t_still_end_s``, else None)."""

    segment: Segment
    readings: object
    notes: list[str]
    t_still_end_s: float | None


def _startup_window(arm: ArmModel, rec: Recording, settings: TrackerSettings | None,
                    options: StartOptions) -> _StartupWindow:
    """The startup's window: the still stretch :func:`choose_start` picks, less the part the
    tracker settles on (:func:`settled_split`), a short one's σ widened; or the
    least-moving instants (:func:`moving_window`)."""
    from armfusion.fusion.startup.solve import readings_from_recording

    choice = choose_start(arm, rec, options.window_s, options.start_at_s, options.moving_start)
    notes: list[str] = [choice.note] if choice.note else []
    t_still_end = None
    if choice.segment is not None:
        still = choice.segment
        seg = settled_split(still, options.window_s, (settings or TrackerSettings()).settle_s)
        if seg.t_end_s < still.t_end_s:
            t_still_end = still.t_end_s
        readings, checks = readings_from_recording(arm, rec, seg.t_start_s, seg.t_end_s, options.window_s)
        if choice.short:
            readings, note = short_still_readings(arm, rec, seg, readings)
            notes.append(note)
    else:
        seg, readings, checks, note = moving_window(arm, rec.between(choice.from_s, np.inf))
        notes.append(note)
    notes += [c.message for c in checks]
    return _StartupWindow(seg, readings, notes, t_still_end)


def _corrected_readings(arm: ArmModel, rec: Recording, window: _StartupWindow, options: StartOptions):
    """For a calibrated config: its correction at the still stretch's temperature (the
    tracker follows the temperature after) and the window's readings corrected by it, with
    notes of the effects applied; ``(None, readings, [])`` for a config with no effects.
    Returns ``(correction, readings, notes)``."""
    if not arm.effects:
        return None, window.readings, []
    from armfusion.fusion.identification.identify import startup_correction

    seg = window.segment
    temp = rec.get("imu_temp")
    still_temp = temp.between(seg.t_start_s, seg.t_end_s) if temp is not None else None
    if still_temp is None or not len(still_temp):
        still_temp = temp
    temperature_c = (float(mpu9150_temperature_c(np.mean(still_temp.values)))
                     if still_temp is not None and len(still_temp) else 25.0)
    corr = startup_correction(arm, temperature_c, include_joint_offsets=True)
    if options.sigma_given_conventions:
        corr = corr.given_conventions()
    applied, not_applied = corr.effects_applied()
    notes = ["the config's effects applied: " + (", ".join(applied) or "none")]
    if not_applied:
        notes.append("the config's effects NOT applied by the tracker: " + "; ".join(not_applied))
    return corr, corr.readings(window.readings), notes


def _tracking_from(arm: ArmModel, window: _StartupWindow, startup: StartupResult) -> tuple[float, str | None]:
    """Where the tracker starts, with a note when that is not the window's end: the still
    stretch's end where the startup left it, when the startup left rival branches (a filter
    on one of rival branches that fit the still readings alike grows sure of the one it
    sits on while the arm stands: it starts where the motion can decide); else the
    window's end, the tracker settling on the still arm before it moves."""
    seg, t_still_end = window.segment, window.t_still_end_s
    if t_still_end is None:
        return seg.t_end_s, None
    if any(j.flag == "ambiguous" for j in startup.joints):
        return t_still_end, (f"the startup calibration on {seg.t_start_s:.2f}-{seg.t_end_s:.2f} s of the "
                             f"still stretch, the tracker from its end ({t_still_end:.2f} s): rival branches")
    return seg.t_end_s, (f"the startup calibration on {seg.t_start_s:.2f}-{seg.t_end_s:.2f} s of the still "
                         f"stretch (to {t_still_end:.2f} s); the tracker from there, settling on the still "
                         f"{'arm' if arm.fixed_base is not None else 'chair'} before it moves")


def settled_split(seg: Segment, window_s: float, settle_s: float) -> Segment:
    """The part of the still stretch ``seg`` the startup calibrates on: all of it but its
    last ``settle_s``, which the tracker takes on a still chair, and never less than the
    startup's ``window_s``. (A still stretch ends because something set off: a filter
    started at that instant meets the motion before it has learnt what a still chair reads.)"""
    end = max(seg.t_start_s + window_s, seg.t_end_s - max(settle_s, 0.0))
    return seg if end >= seg.t_end_s else Segment(seg.t_start_s, end)


def _prime(tr: Tracker, rec: Recording) -> None:
    """Fill the tracker's causal differentiators with the recording's samples up to its
    current time (the still window), so that the first instants have a full window."""
    enc = rec.get(ENC)
    if enc is not None and len(enc):
        prime(tr.enc_rates, enc.t_s, enc.values / tr.counts_per_rad, tr.t_s)
    g = rec.get(GYRO)
    if g is not None and len(g):
        wB = tr.readings.physical(GYRO, g.values) @ tr.R_0I.T
        prime(tr.gyro_rates, g.t_s, wB, tr.t_s)
        k = int(np.searchsorted(g.t_s, tr.t_s + 1e-9)) - 1
        if k >= 0:
            tr.last_gyro_B = wB[k]
