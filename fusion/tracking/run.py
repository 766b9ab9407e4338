"""A tracker's run over a whole recording: :func:`run_recording` feeds every instant of it
through the filter's one path (:meth:`armfusion.fusion.tracking.filter.Tracker.step`, the same as
live), with the conversions to SI units and the saturation checks done for the whole span
at once, and the differentiators' fits and the kinematic frames for a block of instants at
once (:func:`prepare_block`, one compiled call each), and
keeps what the filter said at each (:class:`RunArrays`), as a :class:`TrackRun`; with truth
in the recording, scored by :mod:`armfusion.fusion.tracking.scoring`."""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.measurement import AccelReadings
from armfusion.fusion.tracking.process import attitude_sigma_rad
from armfusion.fusion.tracking.scoring import errors, truth_at, truth_summary
from armfusion.fusion.tracking.settings import (
    C_SAMPLES,
    C_SATURATED,
    ENC,
    GYRO,
    JOINT_FLAGS,
    MAG,
    SENSOR_STATUS,
)
from armfusion.fusion.tracking.tracker_kernels import state_row_into
from armfusion.fusion.tracking.update import InstantReadings, MagReading
from armfusion.models.sensor_models import mpu9150_temperature_c
from armfusion.sensors.samples import Recording, Stream
from scipy.stats import chi2

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
    times = times[(times > t_from + 1e-9) & (times <= t_stop + 1e-9)]
    T = len(times)
    rows, phys, valid = {}, {}, {}
    temperature_at = _temperatures(tr, rec)
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
    gyro_B = phys[GYRO] @ tr.R_0I.T if GYRO in raw else None
    mag_B = phys[MAG] @ tr.R_0I.T if MAG in raw else None
    if not tr.filter_started:  # the offsets are fixed by the first encoder sample
        tr.start_filter(q_enc_all[min(int(np.searchsorted(enc.t_s, t_from - 1e-9)), len(enc) - 1)])
    acc_streams = [s for s in tr.accel_streams if s in raw]
    acc_idx = np.array([tr.sensor_index[s] for s in acc_streams], dtype=np.int64)
    acc_info = tr.measurements.selection(acc_idx)
    # per instant: which accelerometers have a valid sample, as (T, Sa) row indices
    acc_rows = np.stack([np.where(rows[s] >= 0, rows[s], -1) for s in acc_streams], 1) \
        if acc_streams else np.full((T, 0), -1)
    acc_ok = np.stack([(rows[s] >= 0) & valid[s][np.maximum(rows[s], 0)] for s in acc_streams], 1) \
        if acc_streams else np.zeros((T, 0), bool)
    acc_seen = acc_rows >= 0
    # every instant's accelerometer samples as (T, Sa, 3) arrays: one index per step
    Sa = len(acc_streams)
    acc_counts = np.zeros((T, Sa, 3))
    acc_phys = np.zeros((T, Sa, 3))
    for j, s in enumerate(acc_streams):
        have = acc_rows[:, j] >= 0
        acc_counts[have, j] = raw[s].values[acc_rows[have, j]]
        acc_phys[have, j] = phys[s][acc_rows[have, j]]
    all_ok = acc_ok.all(axis=1)
    ok_rows = {s: np.where((rows[s] >= 0) & valid[s][np.maximum(rows[s], 0)], rows[s], -1)
               for s in (ENC, GYRO, MAG) if s in rows}
    mag_counts = raw[MAG].values if MAG in raw else None
    has_truth = truth and rec.get("true_q") is not None and rec.get("true_base") is not None
    out = RunArrays(T, tr.arm.n_joints, len(tr.sensor_names), keep_cov=has_truth, size=tr.layout.size)
    health, step, readings_of = tr.health, tr.step, tr.measurements.readings
    for b0 in range(0, T, block):
        b1 = min(T, b0 + block)
        x_block = tr.x  # the frames' offsets and gyro bias: the block's start's
        for c0 in range(b0, b1, PREPARED_MAX):  # (a long block: its frames a part at a time)
            c1 = min(b1, c0 + PREPARED_MAX)
            # the per-instant rows as plain Python values (cheaper to test one by one)
            t_l = times[c0:c1].tolist()
            enc_l, gyro_l, mag_l = ([-1] * (c1 - c0) if s not in ok_rows else ok_rows[s][c0:c1].tolist()
                                    for s in (ENC, GYRO, MAG))
            all_l = all_ok[c0:c1].tolist()
            # the differentiators' fits and the kinematic frames of these instants, at once, with
            # the offsets and gyro bias of the block's start
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
        if progress is not None:
            progress(b1 / T)
    elapsed = time.perf_counter() - t0_wall
    truth_q = rec.get("true_q") if truth else None
    truth_b = rec.get("true_base") if truth else None
    tq = truth_at(truth_q, times) if truth_q is not None and len(truth_q) else None
    tb = truth_at(truth_b, times, angles=True) if truth_b is not None and len(truth_b) else None
    return out.finish(tr, times, elapsed, tq, tb)


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
    if temp is None or not len(temp) or not tr.readings.per_c:
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


class RunArrays:
    """Per fused instant: the state, the diagonal of its covariance, the encoder angles and the
    flags, as the run goes (a few row copies per step); angles and sigmas are made from them
    at the end. The joint flags, sensor statuses and the calibration's share of the joints'
    variance change only now and then (the tracker replaces those arrays when they do): they
    are kept where they changed and spread over the instants at the end."""

    def __init__(self, T: int, n: int, S: int, keep_cov: bool = True, size: int | None = None):
        size = n + 9 if size is None else size
        self.x = np.full((T, size), np.nan)
        self.var = np.full((T, size), np.nan)
        self.q_enc = np.full((T, n), np.nan)
        self.flags = np.zeros((T, n), dtype=np.int8)
        self.magnetic = np.zeros(T, dtype=np.int8)
        self.heading_floor_var = np.zeros(T)  # what the heading cannot average away (rad^2)
        self.heading_status = np.zeros(T, dtype=np.int8)  # codes of HEADING_STATUS
        self.status = np.zeros((T, S), dtype=np.int8)
        self.sys_var = np.zeros((T, n))
        self.tilt_var = np.zeros((T, 2))  # the accelerometers' floor in the tilt (rad^2)
        self.att_cov = np.full((T, 9), np.nan)  # the attitude's (tangent space) covariance
        self._kept = None
        self.P = np.full((T, n + 3, n + 3), np.nan) if keep_cov else None
        # (the NEES states' covariance, flattened; no rows without truth)
        self._P_rows = np.zeros((0, 0)) if self.P is None else self.P.reshape(T, (n + 3) ** 2)
        self.T = T
        self._held = (None, None, None)
        self._heading_status = (None, None, 0)
        self._changes: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self._last = -1
        self._combo = (None, -np.inf, (), None, None)  # (flags, t, combinations, C, ix) found last
        self.combinations: dict[str, tuple[tuple, np.ndarray, np.ndarray]] = {}
        """Per combination ever reported (its name): its coefficients, and its value and sigma
        at every instant (NaN where it was not reported)."""

    def record(self, tr, i: int) -> None:
        """The tracker ``tr``'s state after instant ``i``."""
        if self._kept is None:  # the (row, column) pairs kept of P: the attitude's, the NEES states'
            a, ix = tr.attitude_index, tr.nees_index
            self._kept = (np.repeat(a, len(a)), np.tile(a, len(a)),
                          np.repeat(ix, len(ix)), np.tile(ix, len(ix)))
        # x, diag(P) and those entries of P into row i, compiled
        state_row_into(i, tr.mean, tr.covariance, *self._kept, self.x, self.var, self.att_cov, self._P_rows)
        self.q_enc[i] = tr.q_enc
        self.tilt_var[i] = tr.observability.tilt_var
        held = self._held
        flags, status, sys_var = tr.joint_flag_codes, tr.health.status_codes, tr.observability.sys_var
        self._record_combinations(tr, i, flags)
        if flags is not held[0] or status is not held[1] or sys_var is not held[2]:
            self._held = held = (flags, status, sys_var)
            self._changes.append((i, *held))
        self.heading_floor_var[i] = tr.compass.heading_floor_var
        # the heading's status follows the compass's and the sensors' statuses (that array is
        # replaced when they change): worked out again only when either changed
        hs = self._heading_status
        if tr.compass.status is not hs[0] or tr.health.status_codes is not hs[1]:
            self._heading_status = hs = (tr.compass.status, tr.health.status_codes, tr.heading_status_code())
        self.heading_status[i] = hs[2]
        mf = tr.compass.flags
        if mf[0] or mf[1]:
            self.magnetic[i] = (1 if mf[0] else 0) | (2 if mf[1] else 0)
        self._last = i

    def _record_combinations(self, tr, i: int, flags: np.ndarray) -> None:
        """What gravity reads together (:meth:`armfusion.fusion.tracking.filter.Tracker.combination_vectors`):
        which combinations, found again when the flags change and every observability window;
        their value and sigma at every instant."""
        held_flags, t_found, found, C, ix = self._combo
        t = tr.t_s
        if flags is not held_flags or t - t_found >= tr.settings.observability_window_s:
            found, C, ix = tr.combination_vectors()
            self._combo = (flags, t, found, C, ix)
            for c in found:
                if c.name not in self.combinations:
                    self.combinations[c.name] = (c.coefficients, np.full(self.T, np.nan),
                                                 np.full(self.T, np.nan))
        if found:
            v, sg = tr.combination_values(C, ix)
            for k, c in enumerate(found):
                _, vals, sigs = self.combinations[c.name]
                vals[i], sigs[i] = v[k], sg[k]

    def _spread_changes(self) -> None:
        """The flags, statuses and the calibration's share at every recorded instant, and that
        share added to the joints' variances."""
        ends = [c[0] for c in self._changes[1:]] + ([self._last + 1] if self._changes else [])
        for (i, flags, status, sys_var), j in zip(self._changes, ends, strict=True):
            self.flags[i:j] = flags
            self.status[i:j] = status
            self.sys_var[i:j] = sys_var
        n = self.sys_var.shape[1]
        self.var[:, :n] += self.sys_var  # the calibration's own uncertainty
        if self.P is not None:
            self.P[:, np.arange(n), np.arange(n)] += self.sys_var
        if self.tilt_var.any():  # the tilt's share no averaging lowers (roll, pitch)
            self.att_cov[:, 0] += self.tilt_var[:, 0]
            self.att_cov[:, 4] += self.tilt_var[:, 1]
            if self.P is not None:
                self.P[:, n, n] += self.tilt_var[:, 0]
                self.P[:, n + 1, n + 1] += self.tilt_var[:, 1]

    def _arrays(self, tr) -> None:
        L, n = tr.layout, tr.arm.n_joints
        self._spread_changes()
        d = np.sqrt(np.maximum(self.var, 0.0))
        self.q = tr.arm.angles_in_range(self.q_enc + self.x[:, :n], self.q_enc)
        self.sigma = d[:, :n]
        self.rpy = self.x[:, tr.attitude_index]
        self.rpy_sigma = attitude_sigma_rad(self.rpy, self.att_cov.reshape(-1, 3, 3), self.heading_floor_var)
        self.bias = self.x[:, L.bias]

    def finish(self, tr, times, elapsed, truth_q: np.ndarray | None,
               truth_b: np.ndarray | None) -> TrackRun:
        """``truth_q``, ``truth_b``: the truth at each instant (NaN where there is none)."""
        n = tr.arm.n_joints
        self._arrays(tr)
        q_err, yaw_err, nees = errors(self.q, self.rpy, self.P, truth_q, truth_b)
        return TrackRun(
            joint_names=tr.arm.joint_names, sensor_names=tr.sensor_names, t_s=np.asarray(times),
            q_rad=self.q, sigma_rad=self.sigma, flags=self.flags, rpy_rad=self.rpy,
            rpy_sigma_rad=self.rpy_sigma, gyro_bias_rad_s=self.bias, magnetic=self.magnetic,
            sensor_status=self.status, elapsed_s=elapsed, counters=tr.counters(), nis=tr.nis_stats(),
            q_error_rad=q_err, yaw_error_rad=yaw_err, nees=nees, nees_dof=n + 3,
            heading_status=self.heading_status, true_north=tr.arm.magnetic_declination_deg is not None,
            combinations=self.combinations,
        )



@dataclass(frozen=True)
class TrackRun:
    """A run over a recording: per fused instant (``t_s (T,)``) the joint angles, their
    sigma and flag codes (:data:`JOINT_FLAGS`), the base attitude and its sigma, the gyro
    bias, magnetic flags (bit 1: disturbance, bit 2: recovery), sensor status codes
    (:data:`SENSOR_STATUS`); with truth, the errors and the NEES (joints, roll, pitch, yaw)."""

    joint_names: tuple[str, ...]
    sensor_names: tuple[str, ...]
    t_s: np.ndarray
    q_rad: np.ndarray
    sigma_rad: np.ndarray
    flags: np.ndarray
    rpy_rad: np.ndarray
    rpy_sigma_rad: np.ndarray
    gyro_bias_rad_s: np.ndarray
    magnetic: np.ndarray
    sensor_status: np.ndarray
    elapsed_s: float
    counters: dict
    nis: dict
    q_error_rad: np.ndarray | None = None
    yaw_error_rad: np.ndarray | None = None
    nees: np.ndarray | None = None
    nees_dof: int = 0
    heading_status: np.ndarray | None = None
    """Per instant, the heading's status (codes of :data:`armfusion.fusion.tracking.estimate.HEADING_STATUS`)."""
    true_north: bool = False
    combinations: dict | None = None
    """What gravity reads where it cannot read single joints: per combination's name (e.g.
    ``"shoulder + elbow"``), its coefficients (name, coefficient pairs over the joints and
    ``base roll``/``base pitch``) and its value and sigma (rad) per instant, NaN where it
    was not reported (:mod:`armfusion.fusion.startup.combinations`)."""

    @property
    def steps(self) -> int:
        return int(len(self.t_s))

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.elapsed_s if self.elapsed_s > 0 else float("nan")

    def flags_seen(self) -> dict:
        """How many instants each joint showed each flag, and each sensor each status."""
        joints = {nm: _tally(self.flags[:, j], JOINT_FLAGS) for j, nm in enumerate(self.joint_names)}
        sensors = {nm: _tally(self.sensor_status[:, i], SENSOR_STATUS)
                   for i, nm in enumerate(self.sensor_names)}
        mag = {"magnetic_disturbance": int(np.sum(self.magnetic & 1 > 0)),
               "magnetic_recovery": int(np.sum(self.magnetic & 2 > 0))}
        return {"joints": joints, "sensors": sensors, "heading": mag}

    def summary(self, after_s: float = 60.0, t0_s: float | None = None) -> dict:
        """The JSON summary (see docs/reference/track-output.md): steps, speed, rejections, flags seen, and
        with truth the RMS errors after ``after_s`` (from ``t0_s``, default the first
        instant), NEES and NIS means with their 95 % chi-square bounds."""
        t0 = (float(self.t_s[0]) if len(self.t_s) else 0.0) if t0_s is None else t0_s
        d: dict = {
            "steps": self.steps,
            "duration_s": float(self.t_s[-1] - self.t_s[0]) if self.steps > 1 else 0.0,
            "elapsed_s": self.elapsed_s,
            "steps_per_s": self.steps_per_s,
            "rejections": {s: c["rejected"] for s, c in self.counters.items()},
            "skipped": {s: {k: c[k] for k in ("nan", "saturated", "implausible", "stuck", "out_of_order")}
                        for s, c in self.counters.items()},
            "reacquisitions": {s: c["reacquisitions"] for s, c in self.counters.items()
                               if c["reacquisitions"]},
            "flags_seen": self.flags_seen(),
        }
        nis = {}
        for s, (mean, count, dof) in self.nis.items():
            if count:
                lo, hi = chi2.ppf([0.025, 0.975], count * dof) / count
                nis[s] = {"mean": mean, "dof": dof, "count": count, "bounds_95": [float(lo), float(hi)],
                          "inside": bool(lo <= mean <= hi)}
        d["nis"] = nis
        d["combinations"] = self.combinations_summary(self.t_s >= t0 + after_s)
        d.update(truth_summary(self, self.t_s >= t0 + after_s, after_s))
        return d

    def combinations_summary(self, scored: np.ndarray | None = None) -> list[dict]:
        """Each combination reported in the run: its name, coefficients, CSV columns
        (:func:`combination_column`), the share of instants it was reported at, its last
        value and sigma; with truth (joint terms only), its RMS error (deg) and share within
        3 sigma over the ``scored`` instants it was reported at."""
        out = []
        for name, (coef, vals, sigs) in (self.combinations or {}).items():
            have = np.isfinite(vals)
            last = int(np.flatnonzero(have)[-1]) if have.any() else None
            e = {"name": name, "coefficients": dict(coef), "column": combination_column(name),
                 "reported_share": float(have.mean()) if len(have) else 0.0,
                 "last_angle_rad": None if last is None else float(vals[last]),
                 "last_sigma_rad": None if last is None else float(sigs[last])}
            joints_only = all(k in self.joint_names for k, _ in coef)
            if self.q_error_rad is not None and joints_only:
                c = np.array([dict(coef).get(nm, 0.0) for nm in self.joint_names])
                err = self.q_error_rad @ c
                m = have & np.isfinite(err) & (np.ones_like(have) if scored is None else scored)
                if m.any():
                    e["rms_error_deg"] = float(np.degrees(np.sqrt(np.mean(err[m] ** 2))))
                    e["within_3_sigma"] = float(np.mean(np.abs(err[m]) <= 3.0 * sigs[m]))
            out.append(e)
        return out


def combination_column(name: str) -> str:
    """A combination's value column in the estimates CSV (its sigma's is ``sigma_`` before it):
    ``shoulder + elbow`` is ``combo_shoulder_plus_elbow``, ``0.5 a - b`` ``combo_0p5_a_minus_b``
    (letters, digits and underscores only: a column name every CSV reader keeps)."""
    slug = name.replace(" + ", "_plus_").replace(" - ", "_minus_").replace("-", "minus_").replace(".", "p")
    return "combo_" + re.sub(r"[^0-9A-Za-z_]", "_", slug)


def _tally(codes: np.ndarray, names: tuple[str, ...]) -> dict[str, int]:
    vals, counts = np.unique(codes, return_counts=True)
    return {names[int(c)]: int(k) for c, k in zip(vals, counts, strict=True)}
