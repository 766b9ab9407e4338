"""What a tracker's run over a whole recording keeps (:class:`RunArrays`, filled instant by
instant by :func:`armfusion.fusion.tracking.run.run_recording`) and gives (:class:`TrackRun`:
every instant's estimate, the sensors' counters and, with truth, the errors and NEES)."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.tracking.process import attitude_sigma_rad
from armfusion.fusion.tracking.scoring import errors, truth_summary
from armfusion.fusion.tracking.settings import JOINT_FLAGS, SENSOR_STATUS
from armfusion.fusion.tracking.tracker_kernels import state_row_into
from scipy.stats import chi2


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
