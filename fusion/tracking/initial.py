"""The filter's first state, from the startup calibration (:func:`initial_state`), what the
IMU said in the same still window (:class:`ImuStill`), and :class:`Ambiguity`: the joints
the startup left with rival branches, carried until a move tells them apart."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.fusion.startup.solve import StartupResult
from armfusion.fusion.tracking.heading import FieldReference
from armfusion.fusion.tracking.settings import StateLayout, TrackerSettings
from armfusion.models.rotations import DEG, wrap_angle


@dataclass(frozen=True)
class ImuStill:
    """What the IMU said during the still startup window: the gyro's zero-rate offset, the
    heading (tilt-compensated, from the startup's roll and pitch) and the field reference."""

    gyro_bias_rad_s: np.ndarray
    gyro_bias_sigma_rad_s: float
    yaw_rad: float | None
    yaw_sigma_rad: float | None
    field: FieldReference | None


def initial_state(startup: StartupResult, imu: ImuStill, layout: StateLayout, settings: TrackerSettings,
                  prior_q_rad: np.ndarray, imu_bias_var_g2: np.ndarray, gyro_scale_var: float = 0.0,
                  prior_sigma_rad: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x, P, q0)``: the state and covariance (offsets zero: the first encoder sample sets
    them to ``q0 - q_enc``) and the joint angles ``q0`` the filter starts from. Where the
    layout holds the gyro's scale about z, it starts at zero (the config's scale is applied to
    the readings) with ``gyro_scale_var`` (fraction²).

    A joint the startup could not read starts at ``prior_q_rad`` with
    ``unknown_joint_sigma_deg`` (or, where ``prior_sigma_rad`` gives a finite one below it, that
    sigma: a pose a running tracker knew, the arm unmoved since); joints with rival branches
    start on the one nearest the prior (with that branch's covariance; the sigma reported
    covers them all)."""
    st, L = settings, layout
    n = L.n_joints
    x = np.zeros(L.size)
    P = np.zeros((L.size, L.size))
    prior = np.asarray(prior_q_rad, float)
    q0, cov, known = _start_pose(startup, prior)
    tgt = np.r_[np.arange(n), L.roll, L.pitch]
    P[np.ix_(tgt, tgt)] = _joints_and_tilt_covariance(startup, cov, known, prior_sigma_rad, st)
    x[L.roll], x[L.pitch] = startup.roll_rad, startup.pitch_rad
    _base_and_imu_prior(x, P, L, st, imu, imu_bias_var_g2, gyro_scale_var)
    return x, _as_rotation_vector(x, P, L), q0


def _start_pose(startup: StartupResult, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The joint angles the filter starts from ``(n,)``, the startup covariance they come
    with, and which joints the startup read (or left between rival branches): a joint not
    read starts at ``prior``. With rival branches the filter runs on one of them, the one
    nearest the prior pose (where the search started: no evidence, so the flag stays
    ``ambiguous`` and the sigma covers every candidate), each one a real minimum with its
    own covariance."""
    cov = np.array(startup.covariance, dtype=float)
    q0 = np.array(startup.q_rad, dtype=float)
    known = read_by_startup(startup)
    amb = np.array([j.flag == "ambiguous" for j in startup.joints], dtype=bool)
    cands = startup.candidates_rad
    if amb.any() and cands is not None and len(cands) > 1:
        d = np.abs(wrap_angle(np.asarray(cands) - prior))[:, amb].sum(1)
        c = int(np.argmin(d))
        q0 = np.array(cands[c], dtype=float)
        if startup.candidates_covariance is not None:
            cov = np.array(startup.candidates_covariance[c], dtype=float)
        known = known | amb
    return np.where(known, q0, prior), cov, known


def _joints_and_tilt_covariance(startup: StartupResult, cov: np.ndarray, known: np.ndarray,
                                prior_sigma_rad: np.ndarray | None, st: TrackerSettings) -> np.ndarray:
    """The joints' and the base tilt's covariance ``(n + 2, n + 2)``: the startup's (its
    sigmas where it gives no covariance), a joint it did not read uncorrelated with
    ``unknown_joint_sigma_deg`` (or a finite carried sigma below it), plus a small floor."""
    n = len(startup.joints)
    jb = np.r_[np.arange(n), n, n + 1]  # joints, roll, pitch in the startup covariance
    if cov.shape == (n + 2, n + 2):
        block = cov[np.ix_(jb, jb)].copy()
    else:
        block = np.diag(np.r_[[j.sigma_rad or 0.0 for j in startup.joints], startup.roll_sigma_rad,
                              startup.pitch_sigma_rad] ** 2)
    block = np.where(np.isfinite(block), block, 0.0)
    wide = (st.unknown_joint_sigma_deg * DEG) ** 2
    carried = (np.full(n, np.inf) if prior_sigma_rad is None
               else np.where(np.isfinite(prior_sigma_rad), np.asarray(prior_sigma_rad, float), np.inf))
    for j in np.flatnonzero(~known):
        block[j, :] = 0.0
        block[:, j] = 0.0
        block[j, j] = min(wide, float(carried[j]) ** 2)
    # a floor: the startup's sigma is for a still average; the tracker's model adds a little
    block[np.diag_indices(n + 2)] += (0.005 * DEG) ** 2
    return block


def _base_and_imu_prior(x: np.ndarray, P: np.ndarray, L: StateLayout, st: TrackerSettings, imu: ImuStill,
                        imu_bias_var_g2: np.ndarray, gyro_scale_var: float) -> None:
    """The base's motion states (still in the startup window), the heading, the gyro's bias
    and scale and the IMU accelerometer's bias, into ``x`` and ``P`` in place."""
    # the startup window was still: the chair's acceleration is zero there
    P[L.accel, L.accel] = np.eye(3) * (0.01**2 if st.motion_compensation and not st.base_fixed else 1e-16)
    if L.vel is not None:  # and so is its velocity
        P[L.vel, L.vel] = np.eye(3) * 0.01**2
    if L.jerk_B is not None:  # and its acceleration's change
        P[L.jerk_B, L.jerk_B] = np.eye(3) * 0.01**2
    if L.pivot_B is not None:  # where the base will turn about: not known before it turns
        P[L.pivot_B, L.pivot_B] = np.eye(3) * st.base_pivot_sigma_m**2
    if imu.yaw_rad is not None:
        x[L.yaw] = imu.yaw_rad
        P[L.yaw, L.yaw] = imu.yaw_sigma_rad**2
    else:
        P[L.yaw, L.yaw] = np.pi**2
    x[L.bias] = imu.gyro_bias_rad_s
    P[L.bias, L.bias] = np.eye(3) * imu.gyro_bias_sigma_rad_s**2
    P[L.imu_bias, L.imu_bias] = np.diag(imu_bias_var_g2)
    if L.scale >= 0:
        P[L.scale, L.scale] = gyro_scale_var


def _as_rotation_vector(x: np.ndarray, P: np.ndarray, L: StateLayout) -> np.ndarray:
    """``P`` with the attitude's covariance as the filter holds it, a world-axis rotation
    vector's: the startup's (and the yaw's) are of Euler-angle increments, so they (and
    their correlations with the joints) are turned through d(delta)/d(roll, pitch, yaw) at
    the start."""
    pch, y = x[L.pitch], x[L.yaw]
    cy, sy, cp, sp = np.cos(y), np.sin(y), np.cos(pch), np.sin(pch)
    T = np.array([[cy * cp, -sy, 0.0], [sy * cp, cy, 0.0], [-sp, 0.0, 1.0]])  # columns: roll, pitch, yaw
    att = np.array([L.roll, L.pitch, L.yaw])
    M = np.eye(L.size)
    M[np.ix_(att, att)] = T
    return M @ P @ M.T


def read_by_startup(startup: StartupResult) -> np.ndarray:
    """Per joint: did the startup read it (an angle and a sigma, neither gimbal-locked nor
    left between rival branches)?"""
    return np.array([j.flag not in ("gimbal_lock", "ambiguous") and j.sigma_rad is not None
                     for j in startup.joints], dtype=bool)


def limits_cover_var(q0_rad: np.ndarray, lo_rad: np.ndarray, hi_rad: np.ndarray) -> np.ndarray:
    """Per joint, the mean square distance from ``q0`` to an angle anywhere inside the limits
    (uniform over ``[lo, hi]``): the variance of a joint known only to lie within them."""
    a, b = np.asarray(hi_rad, float) - q0_rad, q0_rad - np.asarray(lo_rad, float)
    return (a**3 + b**3) / (3.0 * (a + b))


class Ambiguity:
    """The joints the startup left ``ambiguous`` (rival branches that fit the still data
    equally): their candidates, and the encoders' angles when those held."""

    def __init__(self, startup: StartupResult):
        self.joints = np.array([j.flag == "ambiguous" for j in startup.joints], dtype=bool)
        self._candidates = tuple(tuple(j.alternatives_rad) for j in startup.joints)
        self.q_enc = None  # the encoders' angles when the candidates held
        self.half_gap = np.array([
            (max(a) - min(a)) / 2.0 if j.flag == "ambiguous" and len(a) > 1 else 0.0
            for j, a in ((j, j.alternatives_rad) for j in startup.joints)])
        """Per joint, half the spread of its candidates (rad): its sigma covers them."""

    def at(self, joint_names: tuple[str, ...], q_enc: np.ndarray) -> dict[str, tuple[float, ...]]:
        """Per ambiguous joint, its candidates moved by what the encoders counted since."""
        if not self.joints.any():
            return {}
        moved = np.zeros(len(joint_names)) if self.q_enc is None else q_enc - self.q_enc
        return {joint_names[j]: tuple(float(a + moved[j]) for a in self._candidates[j])
                for j in np.flatnonzero(self.joints)}

    def snapshot(self) -> dict:
        return {"joints": self.joints.tolist(), "candidates_rad": [list(c) for c in self._candidates],
                "q_enc": None if self.q_enc is None else self.q_enc.tolist()}

    def restore(self, snap: dict | None, n: int) -> bool:
        """Rival branches still open in ``snap``: taken (True)."""
        if snap is None or len(snap.get("joints", ())) != n:
            return False
        self.joints = np.array(snap["joints"], dtype=bool)
        self._candidates = tuple(tuple(float(a) for a in c) for c in snap["candidates_rad"])
        self.q_enc = None if snap.get("q_enc") is None else np.array(snap["q_enc"], float)
        self.half_gap = np.array([(max(c) - min(c)) / 2.0 if len(c) > 1 else 0.0 for c in self._candidates])
        return True


@dataclass(frozen=True)
class _JointStub:
    name: str
    flag: str = "ok"
    sigma_rad: float = 0.0
    alternatives_rad: tuple[float, ...] = ()


def restored_startup(arm) -> StartupResult:
    """A placeholder startup for a tracker resumed from a snapshot (which then replaces
    every state it seeds)."""
    n = arm.n_joints
    return StartupResult(
        joints=tuple(_JointStub(nm) for nm in arm.joint_names), roll_rad=0.0, pitch_rad=0.0,
        roll_sigma_rad=0.0, pitch_sigma_rad=0.0, residual_rms_g=0.0, chi2_per_dof=0.0,
        q_rad=np.zeros(n), covariance=np.eye(n + 2), branches_rad=np.zeros((1, n)), method="restore")
