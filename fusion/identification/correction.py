"""The startup correction a calibrated config implies (:class:`StartupCorrection`, made by
:func:`startup_correction`): the config's sensor-stage effects undone on averaged still
readings (σ grown by the correction's own uncertainty), and its joint-stage effects undone
on the startup's geometric joint angles."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from armfusion.fusion.calibration import COMPASS_MAP_EFFECTS, GYRO_MAP_EFFECTS, Calibration
from armfusion.models.arm import ArmModel
from armfusion.models.effects import Model, model_from_arm
from armfusion.models.effects.base import Context, JointEffect, SensorEffect
from armfusion.models.effects.library import JointOffset, TemperatureDrift
from armfusion.models.motion import MotionState
from armfusion.models.rotations import DEG


@dataclass(frozen=True)
class StartupCorrection(Calibration):
    """A calibrated config's effects, as the startup calibration needs them: a
    :class:`armfusion.fusion.calibration.Calibration` (per stream, the affine map of its
    sensor-stage effects, its temperature slope and its spread, applied by ``ideal``) with
    the startup's own uses of it.

    * ``readings(r)``: averaged still readings (g, sensor axes) back to what an ideal sensor
      on its nominal mount would read: every sensor-stage effect of an accelerometer
      (mount, axes, scale, bias, temperature drift) is affine, ``y' = L y + c``; this
      inverts it, σ mapped through ``L⁻¹``;
    * ``maps``: per stream, that affine map ``(L, c)``; besides the accelerometers', the
      compass's (its soft and hard iron) and the IMU gyro's (its scale and bias), which
      the tracker undoes on every reading (:class:`armfusion.fusion.tracking.calibrated.Readings`);
    * ``controller_angles(q_geom)``: the startup solves the geometric joint angles; the
      joint-stage effects (offsets, sag, play) map the controller's angles to them, and
      this inverts that map (fixed point, three passes).
    """

    def given_conventions(self) -> StartupCorrection:
        """This correction with its doubt taken relative to the calibration's joint-zero
        conventions (:attr:`spread_given_conventions` as :attr:`spread`): what a tracker
        built on it reports is the σ of its angles against the calibration's own zeros,
        without the absolute zero's doubt that a reference aligned by the same calibration
        shares."""
        return replace(self, spread=dict(self.spread_given_conventions))

    def readings(self, r):
        from armfusion.fusion.startup.solve import StillReadings

        means, sigmas = {}, {}
        for name, m in r.accel_mean_g.items():
            means[name], sigmas[name] = self._undo(name, m, r.accel_sigma_g[name])
        imu_m, imu_s = r.imu_mean_g, r.imu_sigma_g
        if imu_m is not None and "imu_acc" in self.maps:
            imu_m, imu_s = self._undo("imu_acc", imu_m, imu_s)
        return StillReadings(means, sigmas, imu_m, imu_s, r.t_start_s, r.t_end_s)

    def readings_one(self, stream: str, mean_g: np.ndarray) -> np.ndarray:
        """One still reading of ``stream`` (g, sensor axes) corrected, as :meth:`readings`
        (the map solved for this one reading rather than its inverse applied)."""
        if stream not in self.maps:
            return np.asarray(mean_g, float)
        L, c = self.maps[stream]
        return np.linalg.solve(L, np.asarray(mean_g, float) - c)

    def _undo(self, stream, mean, sigma):
        if stream not in self.maps:
            return mean, sigma
        m = np.asarray(mean, float)
        y = self.ideal(stream, m)
        var = (self.undo_map(stream)[0].T ** 2) @ (np.asarray(sigma, float) ** 2)
        for L1, c1 in self.spread.get(stream, ()):
            var = var + (np.linalg.solve(L1, m - c1) - y) ** 2
        return y, np.sqrt(var)

    def controller_result(self, res, sigma_limit_rad: float | None = None):
        """A startup result (geometric angles, from ``solve_still``) on the controller's side:
        the config's joint effects (offsets, sag, play) undone at the chosen branch.

        Sag and play follow the gravity torque, which depends on where every joint stands.
        Where the startup cannot say (a rival branch it could not rule out, a gimbal-locked
        joint at any angle of its range), each numbered joint's σ grows to cover, at 2 σ,
        what its correction would be there; one pushed past ``sigma_limit_rad`` (default:
        the startup's limit) becomes ``ill_conditioned``."""
        from armfusion.fusion.startup.solve import StartupSettings

        limit = (StartupSettings().sigma_limit_deg * DEG if sigma_limit_rad is None
                 else sigma_limit_rad)
        q = np.asarray(res.q_rad, float)
        delta = q - self.controller_angles(q)
        if not np.any(delta):
            return res
        n = len(q)
        variants = []
        rivals = res.candidates_rad if res.candidates_rad is not None else res.branches_rad
        if any(j.flag == "ambiguous" for j in res.joints):
            variants += [b for b in np.asarray(rivals, float).reshape(-1, n)
                         if np.any(np.abs(b - q) > 1e-6)]
        arm = self.model.arm
        for i, j in enumerate(res.joints):
            if j.flag == "gimbal_lock":
                for v in np.linspace(arm.min_rad[i], arm.max_rad[i], 9):
                    qv = q.copy()
                    qv[i] = v
                    variants.append(qv)
        spread = np.zeros(n)
        if variants:
            V = np.array(variants)
            spread = np.max(np.abs((V - self.controller_angles(V)) - delta), axis=0)
        joints, cov = [], np.array(res.covariance, float, copy=True)
        for i, j in enumerate(res.joints):
            sig, flag = j.sigma_rad, j.flag
            if sig is not None and spread[i] / 2.0 > sig:
                grow = spread[i] / 2.0 / sig
                sig = sig * grow
                cov[i, :] *= grow
                cov[:, i] *= grow
                if flag == "ok" and sig > limit:
                    flag = "ill_conditioned"
            joints.append(replace(j, angle_rad=None if j.angle_rad is None else j.angle_rad - delta[i],
                                  sigma_rad=sig, flag=flag,
                                  alternatives_rad=tuple(a - delta[i] for a in j.alternatives_rad),
                                  turns_rad=tuple(a - delta[i] for a in j.turns_rad)))
        cands = (None if res.candidates_rad is None
                 else np.atleast_2d(self.controller_angles(np.asarray(res.candidates_rad, float))))
        return replace(res, joints=tuple(joints), q_rad=q - delta, covariance=cov, candidates_rad=cands)

    def controller_angles(self, q_geom_rad: np.ndarray) -> np.ndarray:
        joint = [e for e in self.model.effects if isinstance(e, JointEffect)]
        qg = np.atleast_2d(np.asarray(q_geom_rad, float))
        if not joint:
            return qg.reshape(np.shape(q_geom_rad))
        th = self.model.unpack()
        q = qg.copy()
        for _ in range(3):
            st = MotionState.static(q)
            ctx = Context(self.model.arm, st, self.model.masses)
            d = np.zeros_like(q)
            for e in joint:
                d[:, e.j] += e.delta(q, th[e.block_name], ctx)
            q = qg - d
        return q.reshape(np.shape(q_geom_rad))


def startup_correction(arm: ArmModel, temperature_c: float = 25.0,
                       include_joint_offsets: bool = False) -> StartupCorrection:
    """The correction the startup calibration applies for ``arm``'s config effects.

    Call once after loading the config; then ``corr.readings(readings)`` before
    ``solve_still`` and ``corr.controller_angles(q)`` on its joint angles. Joint offsets are
    skipped unless asked (relative encoders: the startup defines the zero).
    """
    model = model_from_arm(arm)
    if not include_joint_offsets:
        model = model.without([e.block_name for e in model.effects if e.name == JointOffset.name])
    accel = [s.name for s in arm.link_accelerometers] + (["imu_acc"] if arm.imu is not None else [])
    th = model.unpack()
    cov = arm.calibration.correction_covariance
    maps, spread, given, per_c = {}, {}, {}, {}
    conventions = set(arm.calibration.joint_zero_conventions)
    imu_parts = [] if arm.imu is None else ["imu_mag", "imu_gyro"]
    for s in accel + imu_parts:
        # the compass's own map is its soft and hard iron; the arm's steel (mag_arm_disturbance)
        # turns with the joints and is no fixed map. The gyro's is its scale and bias: the IMU's
        # mount on the base, as a parked calibration fits it, is gravity's (it trades against
        # the base's attitude), not a rotation of the gyro's axes
        effs = sorted((e for e in model.effects if isinstance(e, SensorEffect) and s in e.streams
                       and (s != "imu_mag" or e.name in COMPASS_MAP_EFFECTS)
                       and (s != "imu_gyro" or e.name in GYRO_MAP_EFFECTS)), key=lambda e: e.rank)
        if not effs:
            continue
        st = MotionState.static(np.zeros((4, arm.n_joints)), temperature_c=temperature_c)
        ctx = Context(arm, st, model.masses)

        def affine(theta, effs=effs, ctx=ctx, s=s):
            y = np.vstack([np.zeros(3), np.eye(3)])
            for e in effs:
                y = e.apply(y, theta[e.block_name], ctx, s)
            return (y[1:] - y[0]).T, y[0]

        maps[s] = affine(th)
        drift = next((e for e in effs if e.name == TemperatureDrift.name), None)
        if drift is not None:  # the offset's slope: the drift through what comes after it
            after = effs[effs.index(drift) + 1:]
            slope = affine(th, effs=after)[0] @ np.asarray(th[drift.block_name], float)
            if np.any(slope):
                per_c[s] = slope
        c = cov.get(s)
        if c:  # a calibrated config: the fit's covariance of this sensor's correction
            names = model.element_names()
            els = [n for n in c.elements if n in names]
            keep = [c.elements.index(n) for n in els]
            C = c.matrix[np.ix_(keep, keep)]
            spread[s] = _spread_maps(model, th, els, C, affine)
            held = [i for i, n in enumerate(els) if n in conventions]
            if held:  # the others given the held ones (the Schur complement)
                free = [i for i in range(len(els)) if i not in held]
                C_fh = C[np.ix_(free, held)]
                C_g = C[np.ix_(free, free)] - C_fh @ np.linalg.pinv(C[np.ix_(held, held)]) @ C_fh.T
                given[s] = _spread_maps(model, th, [els[i] for i in free], C_g, affine)
            else:
                given[s] = spread[s]
    return StartupCorrection(model, temperature_c, maps, spread, given, per_c)


def _spread_maps(model: Model, th, els: list[str], C: np.ndarray, affine) -> list:
    """The correction's map with the elements ``els`` moved by their covariance ``C`` along
    each principal direction in turn (by its σ)."""
    names = model.element_names()
    lam, V = np.linalg.eigh(0.5 * (C + C.T))
    x0 = model.pack(th)
    out = []
    for k in np.flatnonzero(lam > 0):
        x1 = x0.copy()
        for i, n in enumerate(els):
            x1[names.index(n)] += np.sqrt(lam[k]) * V[i, k]
        out.append(affine(model.unpack(x1)))
    return out
