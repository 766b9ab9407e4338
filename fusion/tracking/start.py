"""Starting a tracker from a recording: the first still stretch's startup calibration
(:func:`armfusion.fusion.startup.solve.solve_still`, on readings the config's effects corrected), the
gyro bias, heading and Earth-field reference from the same window
(:func:`imu_still_from_recording`), and, offline, the choice between rival branches by the
motion that follows (:func:`_branch_by_motion`). :func:`warm_up` compiles (or loads) the
tracker's kernels before a node takes samples."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from armfusion.fusion.identification.correction import startup_correction
from armfusion.fusion.startup.solve import StartupResult
from armfusion.fusion.startup.static import Segment, StaticDetectionSettings, find_static_segments
from armfusion.fusion.tracking.calibrated import effects_applied, undo_map
from armfusion.fusion.tracking.compass import compass_map, compass_unmodelled_rad
from armfusion.fusion.tracking.differentiator import prime
from armfusion.fusion.tracking.filter import Tracker
from armfusion.fusion.tracking.heading import FieldReference, heading_sigma_rad, tilt_compensated_heading
from armfusion.fusion.tracking.initial import ImuStill
from armfusion.fusion.tracking.run import joint_free_clock
from armfusion.fusion.tracking.settings import ENC, GYRO, IMU_ACC, MAG, TrackerSettings
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, up_from_tilt
from armfusion.models.sensor_models import encoder_angles_at, mpu9150_temperature_c, stream_models
from armfusion.sensors.samples import Recording


def imu_still_from_recording(arm: ArmModel, rec: Recording, t_start_s: float, t_end_s: float,
                             startup: StartupResult, settings: TrackerSettings | None = None,
                             correction=None) -> ImuStill:
    """The gyro bias, initial heading and Earth-field reference from a still window, the
    gyro and the compass read as the tracker reads them (the config's calibrated errors
    undone). ``correction``: the config's
    :class:`armfusion.fusion.identification.identify.StartupCorrection`, when the caller has it (else
    made here when the config has effects)."""
    st = settings or TrackerSettings()
    if correction is None and arm.effects:
        correction = startup_correction(arm)
    sm = stream_models(arm)
    R_0I = arm.imu.R_LS if arm.imu is not None else np.eye(3)
    bias = np.zeros(3)
    bias_sigma = 0.5 * DEG  # no gyro samples: a wide guess
    g = rec.get(GYRO)
    if g is not None:
        w = g.between(t_start_s, t_end_s + 1e-9)
        if len(w) >= 3:
            rate = w.rate_hz or 100.0
            omega = sm[GYRO].from_counts(w.values)
            undo = undo_map(correction, GYRO)
            if undo is not None:  # the config's gyro scale and bias, as the tracker undoes them
                omega = (omega - undo[1]) @ undo[0]
            omega = omega @ R_0I.T
            bias = omega.mean(axis=0)
            noise = st.gyro_noise_dps_per_sqrt_hz * DEG * np.sqrt(rate / 2.0)
            # the window's own scatter where it is above the datasheet's (a vibrating base):
            # the mean of a few shaken samples is no better than they are
            scatter = float(np.max(np.std(omega, axis=0, ddof=1)))
            if scatter < noise * (1.0 + 3.0 / np.sqrt(2.0 * (len(w) - 1))):
                scatter = noise  # within what the datasheet's noise scatters by
            bias_sigma = float(max(scatter / np.sqrt(len(w)), 2e-5))
    yaw = yaw_sigma = None
    field_ref = None
    m = rec.get(MAG)
    if m is not None:
        w = m.between(t_start_s, t_end_s + 1e-9)
        if len(w) >= 1:
            y = sm[MAG].from_counts(w.values)
            undo = compass_map(arm, correction)
            if undo is not None:  # the config's hard and soft iron, as the tracker undoes them
                y = (y - undo[1]) @ undo[0]
            mB = y @ R_0I.T
            up = up_from_tilt(np.array(startup.roll_rad), np.array(startup.pitch_rad))
            if st.heading.reference == "model":
                field_ref = FieldReference.from_world_field()
            else:
                declination_rad = float(np.radians(arm.magnetic_declination_deg or 0.0))
                field_ref = FieldReference.from_samples(mB, up, declination_rad)
            mean = mB.mean(axis=0)
            yaw = float(tilt_compensated_heading(mean, startup.roll_rad, startup.pitch_rad,
                                                 field_ref.declination_rad))
            sig = heading_sigma_rad(field_ref, st.heading.noise_ut) / np.sqrt(len(w))
            tilt_sig = np.hypot(startup.roll_sigma_rad, startup.pitch_sigma_rad) * np.tan(field_ref.dip_rad)
            iron_sig = compass_unmodelled_rad(arm, field_ref)
            yaw_sigma = float(np.sqrt(sig**2 + tilt_sig**2 + iron_sig**2) + 0.2 * DEG)
    return ImuStill(bias, bias_sigma, yaw, yaw_sigma, field_ref)


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
    tr, _ = start_from_recording(arm, first, settings, propose_unlock=False)  # then 2 s more
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


def start_from_recording(arm: ArmModel, rec: Recording, settings: TrackerSettings | None = None,
                         prior_q_rad: np.ndarray | None = None, window_s: float = 1.0,
                         startup_settings=None, propose_unlock: bool = True,
                         prior=None, resolve_by_motion_s: float | None = None,
                         moving_start: bool = False,
                         prior_sigma_rad: np.ndarray | None = None,
                         start_at_s: float | None = None,
                         sigma_given_conventions: bool = False) -> tuple[Tracker, Start]:
    """A tracker initialised from the recording's first still stretch: the startup
    calibration there (:func:`armfusion.fusion.startup.solve.solve_still`), the gyro bias, heading and field
    reference from the same window; it starts tracking at the window's end: the still
    stretch's end less ``settings.settle_s`` where the stretch is long enough
    (:func:`settled_split`), so that the filter settles on the still chair before it moves.
    ``propose_unlock`` False: no search for a move that would unlock gravity-blind joints
    (about 2 s of the startup's time, for a caller that does not show it).
    ``prior_q_rad``: a pose saved at the last clean shutdown, checked against the still data
    before it may choose a branch (:class:`armfusion.fusion.startup.solve.StartupPrior`); ``prior``: any
    other startup prior (e.g. ``StartupPrior.assume_parked``).
    ``resolve_by_motion_s``: for a whole recording (not live), when the startup left joints
    ``ambiguous``, track each candidate branch over the next this many seconds and keep the
    one the motion's readings favour (:func:`_branch_by_motion`); they stay ambiguous when no
    branch is decisively better (the arm did not move enough).
    Where it starts is :func:`choose_start`'s: the earliest still stretch near the
    recording's start (or ``start_at_s``), a short one's σ widened
    (:func:`short_still_readings`). ``moving_start`` (or ``start_at_s``): with no still
    stretch near there (an arm that never stops), start from the readings of the
    least-moving instants there instead (:func:`moving_window`), their σ widened by the
    motion; else the first still stretch anywhere, and :class:`NoStillWindowError` with none.
    ``prior_sigma_rad``: with ``prior_q_rad``, how well it is known per joint (a running
    tracker's pose handed on, the arm unmoved): a joint the startup cannot read starts at
    ``prior_q_rad`` with that sigma instead of ``TrackerSettings.unknown_joint_sigma_deg``.
    ``sigma_given_conventions``: a calibrated config's doubt taken relative to its joint-zero
    conventions (:meth:`armfusion.fusion.identification.correction.StartupCorrection.given_conventions`):
    the σ against the calibration's own zeros, for scoring against a reference those zeros
    aligned (the default, the absolute σ, is what a user's controller needs)."""
    from armfusion.fusion.startup.solve import StartupPrior, readings_from_recording, solve_still

    if prior is None and prior_q_rad is not None:
        prior = StartupPrior.saved_pose(prior_q_rad)
    choice = choose_start(arm, rec, window_s, start_at_s, moving_start)
    notes: list[str] = [choice.note] if choice.note else []
    t_still_end = None  # where the still stretch ends, when the startup leaves its end to the tracker
    if choice.segment is not None:
        still = choice.segment
        seg = settled_split(still, window_s, (settings or TrackerSettings()).settle_s)
        if seg.t_end_s < still.t_end_s:
            t_still_end = still.t_end_s
        readings, checks = readings_from_recording(arm, rec, seg.t_start_s, seg.t_end_s, window_s)
        if choice.short:
            readings, note = short_still_readings(arm, rec, seg, readings)
            notes.append(note)
    else:
        seg, readings, checks, note = moving_window(arm, rec.between(choice.from_s, np.inf))
        notes.append(note)
    notes += [c.message for c in checks]
    corr = None
    if arm.effects:  # a calibrated config: the startup works on corrected readings
        from armfusion.fusion.identification.identify import startup_correction

        temp = rec.get("imu_temp")
        still_temp = temp.between(seg.t_start_s, seg.t_end_s) if temp is not None else None
        if still_temp is None or not len(still_temp):
            still_temp = temp
        # corrected at the temperature of the still stretch (the tracker follows it after)
        temperature_c = (float(mpu9150_temperature_c(np.mean(still_temp.values)))
                         if still_temp is not None and len(still_temp) else 25.0)
        corr = startup_correction(arm, temperature_c, include_joint_offsets=True)
        if sigma_given_conventions:
            corr = corr.given_conventions()
        readings = corr.readings(readings)
        applied, not_applied = effects_applied(corr.model)
        notes.append("the config's effects applied: " + (", ".join(applied) or "none"))
        if not_applied:
            notes.append("the config's effects NOT applied by the tracker: " + "; ".join(not_applied))
    notes.extend(delay_notes(arm))
    startup = solve_still(arm, readings, startup_settings, prior=prior,
                          propose_unlock=propose_unlock)
    notes.extend(startup.notes)
    geometric = startup
    if corr is not None:
        startup = corr.controller_result(startup)
    imu = imu_still_from_recording(arm, rec, seg.t_start_s, seg.t_end_s, startup, settings, corr)
    enc = rec.get(ENC) if arm.n_joints else joint_free_clock(rec)
    if enc is None or not len(enc):
        raise ValueError("the recording has no encoder stream 'enc': nothing to track")
    t_track = seg.t_end_s
    if t_still_end is not None:
        if any(j.flag == "ambiguous" for j in startup.joints):
            # a filter on one of rival branches that fit the still readings alike grows sure of
            # the one it sits on while the arm stands: it starts where the motion can decide
            t_track = t_still_end
            notes.append(f"the startup calibration on {seg.t_start_s:.2f}-{seg.t_end_s:.2f} s of the still "
                         f"stretch, the tracker from its end ({t_still_end:.2f} s): rival branches")
        else:
            notes.append(f"the startup calibration on {seg.t_start_s:.2f}-{seg.t_end_s:.2f} s of the still "
                         f"stretch (to {t_still_end:.2f} s); the tracker from there, settling on the still "
                         f"{'arm' if arm.fixed_base is not None else 'chair'} before it moves")
    k, enc_rad = encoder_angles_at(arm, enc, t_track)
    rates = {s: (v.rate_hz or 100.0) for s, v in rec.raw().items()}

    def tracker_from(result: StartupResult) -> Tracker:
        t = Tracker(arm, settings, rates_hz=rates, correction=corr)
        t.initialise(result, float(enc.t_s[k]), encoder_counts=enc.values[k], imu=imu,
                     prior_q_rad=prior_q_rad, prior_sigma_rad=prior_sigma_rad)
        _prime(t, rec)
        return t

    if resolve_by_motion_s and startup.candidates_rad is not None and len(startup.candidates_rad) > 1:
        chosen, note = _branch_by_motion(startup, tracker_from, rec, float(enc.t_s[k]),
                                         resolve_by_motion_s, startup_settings)
        notes.append(note)
        if chosen is not None:
            startup = chosen
    tr = tracker_from(startup)
    return tr, Start(seg.t_start_s, seg.t_end_s, startup, imu, tuple(notes), geometric, enc_rad)


def settled_split(seg: Segment, window_s: float, settle_s: float) -> Segment:
    """The part of the still stretch ``seg`` the startup calibrates on: all of it but its
    last ``settle_s``, which the tracker takes on a still chair, and never less than the
    startup's ``window_s``. (A still stretch ends because something set off: a filter
    started at that instant meets the motion before it has learnt what a still chair reads.)"""
    end = max(seg.t_start_s + window_s, seg.t_end_s - max(settle_s, 0.0))
    return seg if end >= seg.t_end_s else Segment(seg.t_start_s, end)


def _branch_by_motion(startup: StartupResult, tracker_from, rec: Recording, t0_s: float,
                      horizon_s: float, startup_settings=None,
                      decisive_nis: float = 50.0) -> tuple[StartupResult | None, str]:
    """The candidate branch the motion after a still window favours, offline.

    Twins that read the same still read differently once the arm or the chair moves (as a
    disambiguating move makes them). Each candidate of ``startup`` seeds a tracker, run over
    ``horizon_s`` of the recording after ``t0_s``; the link accelerometers' normalised
    innovations (NIS) summed over that stretch are the evidence. A candidate is chosen when
    it beats every other by ``decisive_nis`` (a log-likelihood ratio of 25); it is then a
    startup with those joints numbered (the candidate's own covariance), and the note says
    so. Otherwise ``None``: the joints stay ``ambiguous``."""
    from armfusion.fusion.startup.solve import StartupSettings

    st = startup_settings or StartupSettings()
    n = len(startup.joints)
    amb = [j for j, je in enumerate(startup.joints) if je.flag == "ambiguous"]
    names = ", ".join(startup.joints[j].name for j in amb)
    covs = (startup.candidates_covariance if startup.candidates_covariance is not None
            else np.repeat(np.asarray(startup.covariance)[None], len(startup.candidates_rad), 0))
    window = rec.between(-np.inf, t0_s + horizon_s)
    totals, variants = [], []
    for cand, cov in zip(startup.candidates_rad, covs, strict=True):
        sig = np.sqrt(np.clip(np.diag(cov)[:n], 0, None))
        joints = tuple(
            replace(je, angle_rad=float(cand[j]), sigma_rad=float(sig[j]), alternatives_rad=(),
                    flag="ok" if sig[j] <= st.sigma_limit_deg * DEG else "ill_conditioned")
            if j in amb else je for j, je in enumerate(startup.joints))
        v = replace(startup, joints=joints, q_rad=np.array(cand, float), covariance=np.array(cov),
                    candidates_rad=np.array(cand, float)[None], candidates_covariance=np.array(cov)[None],
                    disambiguating_move=None)
        tr = tracker_from(v)
        tr.run(window, truth=False)
        total = 0.0
        for s_ in tr.link_names:
            lg = tr.innovations(s_)
            ok = np.isfinite(lg.nis) & (lg.t_s > t0_s)
            total += float(np.sum(lg.nis[ok]))
        totals.append(total)
        variants.append(v)
    order = np.argsort(totals)
    best, second = totals[order[0]], totals[order[1]]
    if second - best >= decisive_nis:
        return variants[order[0]], (
            f"{names}: the branch chosen by the motion after the still window (the candidates' "
            f"summed NIS over {horizon_s:g} s: {best:.0f} against {second:.0f} at the next)")
    return None, (f"{names}: ambiguous, and the motion after the still window does not tell the "
                  f"branches apart (summed NIS over {horizon_s:g} s: {best:.0f} and {second:.0f})")


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
