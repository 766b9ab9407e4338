"""How well a planned maneuver's parameters will be known, before it is played.

:func:`predicted_identification`: the maneuver played noise-free by the simulator at the
priors, turned into the fit's data as a recording would be
(:func:`~armfusion.fusion.identification.data.data_from_recording`: the moves count too), the
identifiability analysis and the consider covariance of the fit
(:func:`~armfusion.fusion.identification.identify.identify`'s). :func:`startup_sigmas`: the
startup's σ of each joint after it, from the calibrated config such a fit would write and
the startup solved on it at random still poses. :func:`predict_maneuver`: both. The plan
itself is :mod:`~armfusion.fusion.identification.planner`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.fusion.identification.calibrated_config import config_with_estimates
from armfusion.fusion.identification.correction import startup_correction
from armfusion.fusion.identification.data import FitData, data_from_recording, fit_streams
from armfusion.fusion.identification.identifiability import analyse_information
from armfusion.fusion.identification.identify import _consider_covariance
from armfusion.fusion.identification.problem import FitProblem
from armfusion.fusion.identification.result import Identification, StreamFit
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.startup.prior import StartupPrior
from armfusion.fusion.startup.readings import readings_from_counts
from armfusion.fusion.startup.solve import solve_still
from armfusion.models.arm_config import build_arm
from armfusion.models.effects import Model, model_from_arm
from armfusion.models.motion import MotionState
from armfusion.models.rotations import DEG
from armfusion.models.sensor_models import stream_models
from armfusion.models.simulator import SimulationOptions, simulate
from armfusion.models.trajectories.planned import PlannedManeuver, planned_scenario
from armfusion.models.trajectories.scenario import Scenario, margin_limits


@dataclass(frozen=True)
class Prediction:
    """What a fit on the maneuver will know: every element's σ (the held ones at their prior
    σ), what it will hold, the startup's σ of each joint after it."""

    identification: Identification
    """The fit's σ as :func:`identify` would report them, at the priors (``x = x0``)."""
    joint_sigma_rad: np.ndarray
    """Per joint: the median σ of the startup's ``ok`` answers at random still poses on the
    calibrated config (nan where none is ok)."""
    joint_ok_share: np.ndarray


def predicted_identification(model: Model, maneuver: PlannedManeuver | Scenario, window: int = 25,
                             rate_hz: float = 100.0) -> Identification:
    """The σ a fit of ``model`` on ``maneuver`` (a plan, or any scenario) will report: the
    maneuver simulated without noise on the priors' arm, its data and problem as the fit
    builds them, the identifiability analysis and the consider covariance at the priors.
    (The fit analyses again at its
    estimate and may free a bilinear element held here; it also scales a stream whose residual
    exceeds its noise: neither can be known before the recording.)"""
    arm = model.arm
    sc = (planned_scenario(arm, maneuver, np.random.default_rng(0), tilt_sigma_rad=0.0)
          if isinstance(maneuver, PlannedManeuver) else maneuver)
    rec, _ = simulate(arm, sc, rate_hz=rate_hz, options=SimulationOptions(noise=False))
    data = data_from_recording(arm, rec, window, nodes=2, stances=True)
    return _predicted(model, data)


def _predicted(model: Model, data: FitData) -> Identification:
    """The fit's σ on ``data`` at the priors: the identifiability analysis there and the
    consider covariance of what it leaves free."""
    st = IdentifySettings(encoder_scale=True)
    streams = [s for s in data.counts if s in fit_streams(model.arm)]
    pb = FitProblem(model, data, streams, True, np.zeros(3), encoder_scale=True)
    H, _, _ = pb.normal_equations(pb.x0, np.arange(pb.size))
    holds = analyse_information(H, pb.sigma0, pb.names, np.ones(pb.size, bool), st)
    free = np.ones(pb.size, bool)
    for h in holds:
        free[pb.names.index(h.element)] = False
    C = _consider_covariance(pb, H, free)
    sm = model.stream_models()
    fits = tuple(StreamFit(s, sm[s].unit, data.sigma_counts[s] / np.abs(sm[s].gain),
                           data.sigma_counts[s] / np.abs(sm[s].gain)) for s in pb.streams)
    return Identification(
        model=model, names=pb.names, x=pb.x0.copy(), x0=pb.x0.copy(),
        sigma=np.sqrt(np.clip(np.diag(C), 0, None)), prior_sigma=pb.sigma0.copy(), covariance=C,
        held=~free, holds=tuple(holds), fits=fits, chi2_red=1.0, n_samples=data.n,
        n_residuals=int(np.count_nonzero(pb.w)), iterations=0, seconds=0.0,
        attitude_rad=pb.x0[pb.P:pb.P + 3], q_ref_rad=data.q_ref_rad, mode="predicted",
        notes=("predicted at the priors, before any recording",),
        attitudes_rad=pb.x0[pb.P:].reshape(-1, 3))


def startup_sigmas(config_data: dict, result: Identification, poses: int = 64, seed: int = 0,
                   temperature_c: float = 25.0, tilt_sigma_deg: float = 3.0,
                   prior_sigma_deg: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """The startup after a calibration ``result`` (its config written as ``calibrate sensors
    --write`` writes it, over ``config_data``): the still solve at ``poses`` random poses
    inside the limits, the chair tilted N(0, ``tilt_sigma_deg``) per axis, 1 s of readings at
    the prior's values, the pose saved at the last shutdown ``prior_sigma_deg`` from the truth
    as its prior (the startup benchmark's draw); per joint the median σ of the ``ok`` answers
    (nan where none) and the share of poses it is ok."""
    cal = build_arm(config_with_estimates(config_data, result), "(predicted calibrated config)")
    corr = startup_correction(cal, temperature_c)
    model = model_from_arm(cal)
    rng = np.random.default_rng([seed, 0x57A])
    lo, hi = margin_limits(cal)
    Q = rng.uniform(lo, hi, (poses, cal.n_joints))
    tilt = rng.normal(0.0, tilt_sigma_deg * DEG, (poses, 2))
    saved = Q + rng.normal(0.0, prior_sigma_deg * DEG, Q.shape)
    streams = [s.name for s in cal.link_accelerometers] + (["imu_acc"] if cal.imu is not None else [])
    phys = model.predict(MotionState.static(Q, tilt[:, 0], tilt[:, 1], temperature_c=temperature_c),
                         model.x0, streams, units="physical")
    sm = stream_models(cal)
    means = {s: sm[s].to_counts(phys[s]) for s in streams}
    sig = np.full((poses, cal.n_joints), np.nan)
    for k in range(poses):
        r = readings_from_counts(cal, {s: m[k] for s, m in means.items()}, n_samples=100)
        prior = StartupPrior.saved_pose(saved[k], sigma_deg=prior_sigma_deg)
        res = corr.controller_result(solve_still(cal, corr.readings(r), prior=prior, propose_unlock=False))
        for j, je in enumerate(res.joints):
            if je.flag == "ok" and je.sigma_rad is not None:
                sig[k, j] = je.sigma_rad
    ok = np.isfinite(sig)
    med = np.array([np.median(sig[ok[:, j], j]) if ok[:, j].any() else np.nan for j in range(cal.n_joints)])
    return med, ok.mean(0)


def predict_maneuver(model: Model, maneuver: PlannedManeuver | Scenario, config_data: dict, poses: int = 64,
                     window: int = 25) -> Prediction:
    """:func:`predicted_identification` and :func:`startup_sigmas` of ``maneuver``."""
    ident = predicted_identification(model, maneuver, window)
    sig, share = startup_sigmas(config_data, ident, poses)
    return Prediction(ident, sig, share)
