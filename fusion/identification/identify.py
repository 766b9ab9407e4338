"""Sensor and model identification: the arm calibrates its own sensors.

From a recording in which the arm moves through many orientations, estimate the
parameters of the model's effects (``armfusion.models.effects``: biases, scales, axis directions,
mounts, joint zeros, sag, the IMU's gyro and compass errors…) and the base attitude (the
gravity and Earth-field directions in the base frame, as the sensor-calibration article's
φ, ψ; one per parked stance of the chair, :func:`~armfusion.fusion.identification.stances.parked_stances`,
optionally with an inclinometer's reading of the first stance's tilt), by weighted nonlinear
least squares:

* residuals: every reading's prediction minus the measurement, divided by its noise
  (window means of ``window`` samples: the noise of a mean; :mod:`~armfusion.fusion.identification.data`);
* priors as pseudo-measurements ``(x - x0) / σ0`` (each block's prior, from the config or
  the effect's datasheet-typical magnitude);
* analytic Jacobians from :meth:`Model.predict_with_jacobian`; the base attitude's three
  columns by forward differences of the model (the only numerical ones;
  :mod:`~armfusion.fusion.identification.problem`);
* identifiability first (:mod:`~armfusion.fusion.identification.identifiability`): what the data know
  no better than their priors is held there, its σ carried into the others' as a consider
  covariance;
* Levenberg-Marquardt with geodesic acceleration (:mod:`~armfusion.fusion.identification.solver`),
  a long recording's solves started on a quarter of its points, then each stream weighted
  by its own residual's size and correlation and fitted again.

This module is the fit itself (:func:`identify`, :func:`identify_recentred`,
:func:`identify_separately`). Its neighbours hold the rest: ``settings``, ``data``,
``problem``, ``identifiability``, ``solver``, ``result`` (:class:`Identification`),
``truth``, ``calibrated_config`` (:func:`config_with_estimates`) and ``correction``
(:class:`StartupCorrection`, what the startup applies for a calibrated config). The names
other modules import from here are re-exported (``__all__``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
from armfusion.fusion.identification.calibrated_config import (
    config_with_estimates,
    correction_covariance,
    joint_zero_conventions,
)
from armfusion.fusion.identification.correction import (
    COMPASS_MAP_EFFECTS,
    StartupCorrection,
    startup_correction,
)
from armfusion.fusion.identification.data import (
    ENCODER_ZERO_SIGMA_RAD,
    FIT_STREAMS_EXCLUDED,
    REFERENCE_SIGMA_RAD,
    FitData,
    JointReference,
    data_from_recording,
    fit_streams,
    joint_references,
    with_encoder_zeros,
)
from armfusion.fusion.identification.identifiability import (
    Hold,
    analyse_identifiability,
    analyse_information,
    suggestion_for,
)
from armfusion.fusion.identification.problem import (
    ATTITUDE,
    ATTITUDE_LABELS,
    ATTITUDE_SIGMA_RAD,
    FitProblem,
    attitude_names,
)
from armfusion.fusion.identification.result import (
    REFERENCE_CONTRADICTION_SIGMA,
    Identification,
    ReferenceCheck,
    StreamFit,
)
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.identification.solver import coarse_points, solve, stream_scales
from armfusion.fusion.identification.stances import parked_stances
from armfusion.fusion.identification.starts import start_pose
from armfusion.fusion.identification.truth import compare_with_truth, truth_values
from armfusion.models.effects import Model
from armfusion.models.effects.library import JointOffset

__all__ = [
    "ATTITUDE", "ATTITUDE_LABELS", "ATTITUDE_SIGMA_RAD", "COMPASS_MAP_EFFECTS", "ENCODER_ZERO_SIGMA_RAD",
    "FIT_STREAMS_EXCLUDED", "REFERENCE_CONTRADICTION_SIGMA", "REFERENCE_SIGMA_RAD", "FitData", "FitProblem",
    "Hold", "Identification", "IdentifySettings", "JointReference", "ReferenceCheck", "StartupCorrection",
    "StreamFit", "analyse_identifiability", "analyse_information", "attitude_names", "compare_with_truth",
    "config_with_estimates", "correction_covariance", "data_from_recording", "fit_streams",
    "identify", "identify_recentred", "identify_separately", "joint_references",
    "joint_zero_conventions", "parked_stances", "start_pose", "startup_correction", "suggestion_for",
    "truth_values", "with_encoder_zeros",
]


class _JacobianCounter:
    """Counts the Jacobians of every solve of one fit, passing each to the caller's
    ``progress(k, cost)`` numbered over the whole fit."""

    def __init__(self, progress: Callable[[int, float], None] | None):
        self.n = 0
        self._progress = progress

    def __call__(self, k: int, cost: float) -> None:
        self.n += 1
        if self._progress is not None:
            self._progress(self.n, cost)


class _Solution(NamedTuple):
    """Where a fit's solves ended: the estimate, which elements were free, what the
    identifiability analysis holds, each stream's weight and scale (the scale empty when
    nothing was free), whether the last solve converged (None: nothing to solve), and the
    Jacobians the coarse starts took."""

    z: np.ndarray
    free: np.ndarray
    holds: list[Hold]
    w_stream: dict[str, float]
    scale: dict[str, float]
    converged: bool | None
    coarse_iterations: int


def _problems(model: Model, data: FitData, streams: list[str], st: IdentifySettings,
              attitude0_rad: np.ndarray) -> tuple[FitProblem, FitProblem | None]:
    """The fit's problem, its start the compass's coarse headings where it has them, and, for a
    long recording, the same problem on a subset of the points (:func:`~.solver.coarse_points`)
    with the same priors, which each solve starts on (:func:`~.solver.solve`)."""
    pb = FitProblem(model, data, streams, st.estimate_attitude, attitude0_rad, encoder_scale=st.encoder_scale)
    if pb.attitude and "imu_mag" in pb.streams:
        _coarse_headings(pb, data)
    idx = coarse_points(data.n, data.stance, data.used)
    if idx is None:
        return pb, None
    coarse = FitProblem(model, data.subset(idx), streams, st.estimate_attitude, attitude0_rad,
                        encoder_scale=st.encoder_scale)
    coarse.x0 = pb.x0  # the same priors (the coarse headings included)
    return pb, coarse


def _not_held(names: Sequence[str], hold: set[str]) -> np.ndarray:
    """Per element, whether the caller leaves it free (``hold`` names elements or whole blocks)."""
    return np.array([not (n in hold or n.split("[")[0] in hold) for n in names], bool)


def _freed_at_estimate(pb: FitProblem, z: np.ndarray, hold: set[str], holds: list[Hold],
                       st: IdentifySettings) -> tuple[np.ndarray, list[Hold]] | None:
    """The free elements and holds of the identifiability analysed again at the estimate ``z``,
    or None when it holds the same. Bilinear effects (a compass dipole's field and the IMU's
    position, a soft-iron matrix on that field) are invisible at the prior, where the other
    factor is zero: the data may see them at the estimate. A held element is freed only when
    the data know it well (to half its prior σ): one barely above the line makes a long flat
    valley the solver creeps along."""
    H1, _, _ = pb.normal_equations(z, np.arange(pb.size))
    free = _not_held(pb.names, hold)
    holds1 = analyse_information(H1, pb.sigma0, pb.names, free, replace(st, hold_ratio=0.5 * st.hold_ratio))
    before = {h.element for h in holds}
    holds1 = [h for h in holds1 if h.element in before]
    if {h.element for h in holds1} == before:
        return None
    for h in holds1:
        free[pb.names.index(h.element)] = False
    return free, holds1


def _solve(pb: FitProblem, coarse: FitProblem | None, hold: set[str], st: IdentifySettings,
           counter: _JacobianCounter) -> _Solution:
    """Hold what the data cannot see at the prior, solve, free what the data see at the
    estimate and solve again, then weight each stream by its own scale (:func:`_reweighted`)."""
    z0 = pb.x0.copy()
    free = _not_held(pb.names, hold)
    H0, _, _ = pb.normal_equations(z0, np.arange(pb.size))
    holds = analyse_information(H0, pb.sigma0, pb.names, free, st)
    for h in holds:
        free[pb.names.index(h.element)] = False
    w_stream = {s_: 1.0 for s_ in pb.streams}
    if not free.any():
        return _Solution(z0.copy(), free, holds, w_stream, {}, None, 0)
    z, converged, n_coarse = solve(pb, coarse, z0, np.flatnonzero(free), w_stream, st.max_nfev, counter)
    freed = _freed_at_estimate(pb, z, hold, holds, st)
    if freed is not None:
        free, holds = freed
        z[~free] = z0[~free]
        z, converged, nc = solve(pb, coarse, z, np.flatnonzero(free), w_stream, st.max_nfev, counter)
        n_coarse += nc
    z, converged, scale = _reweighted(pb, z, np.flatnonzero(free), st, counter, converged)
    return _Solution(z, free, holds, {s_: 1.0 / scale[s_] for s_ in pb.streams}, scale, converged, n_coarse)


def _reweighted(pb: FitProblem, z: np.ndarray, fcols: np.ndarray, st: IdentifySettings,
                counter: _JacobianCounter, converged: bool) -> tuple[np.ndarray, bool, dict[str, float]]:
    """Each stream at its own scale (:func:`~.solver.stream_scales`): a stream the model fits
    worse than its noise (or with smooth, correlated residuals) counts for fewer independent
    readings; weight it so and fit again (one pass, from the optimum at the first weights:
    no coarse start, it would walk away), so its errors neither pull the others' estimates
    nor shrink their σ. Returns the estimate, whether its solve converged, and the scales."""
    scale = stream_scales(pb, z)
    if any(v > 1.05 for v in scale.values()):
        w_stream = {s_: 1.0 / scale[s_] for s_ in pb.streams}
        z, converged, _ = solve(pb, None, z, fcols, w_stream, st.max_nfev, counter)
        scale = stream_scales(pb, z)
    return z, converged, scale


def identify(model: Model, data: FitData, streams: Sequence[str] | None = None,
             settings: IdentifySettings | None = None, hold: Iterable[str] = (),
             attitude0_rad: np.ndarray | None = None,
             progress: Callable[[int, float], None] | None = None,
             mode: str = "simultaneous") -> Identification:
    """Estimate every parameter of ``model`` (and the base attitude) from ``data``.

    ``hold`` names elements or whole blocks to keep at their priors (besides those the
    identifiability analysis holds). ``progress(k, cost)`` is called at every Jacobian.
    """
    st = settings or IdentifySettings()
    t0 = time.perf_counter()
    streams = [s for s in (data.counts if streams is None else streams) if s not in FIT_STREAMS_EXCLUDED]
    att0 = np.zeros(3) if attitude0_rad is None else np.asarray(attitude0_rad, float)
    pb, coarse = _problems(model, data, streams, st, att0)
    counter = _JacobianCounter(progress)
    sol = _solve(pb, coarse, set(hold), st, counter)
    z, free = sol.z, sol.free
    notes = []
    if sol.converged is not None and not sol.converged:
        notes.append(f"the solver stopped before converging (after {counter.n} Jacobians)")
    H, grad, rr = pb.normal_equations(z, np.arange(pb.size), sol.w_stream)
    r = pb.residual(z)
    m_res = int(np.count_nonzero(pb.w))
    dof = max(m_res - int(free.sum()), 1)
    chi2 = float(np.sum(r**2) / dof)
    worse = {s_: v for s_, v in sol.scale.items() if v > 1.05}
    if worse:
        notes.append("σ scaled per stream by its residual's size and correlation (some effect is not "
                     "modelled, or the noise is larger than the datasheet's): "
                     + ", ".join(f"{s_} {v:.2f}x" for s_, v in worse.items()))
    C = _consider_covariance(pb, H, free)
    sigma = np.sqrt(np.clip(np.diag(C), 0, None))
    checks = _reference_checks(pb, z, H, grad, C)
    notes += [c.message() for c in checks]
    fits = _stream_fits(pb, model, data, z)
    return Identification(
        model=model, names=pb.names, x=z, x0=pb.x0.copy(), sigma=sigma, prior_sigma=pb.sigma0.copy(),
        covariance=C, held=~free, holds=tuple(sol.holds), fits=tuple(fits), chi2_red=chi2,
        n_samples=data.n if data.used is None else int(data.used.sum()), n_residuals=m_res,
        iterations=counter.n, seconds=time.perf_counter() - t0,
        attitude_rad=z[pb.P:pb.P + 3] if pb.attitude else None, q_ref_rad=data.q_ref_rad, mode=mode,
        notes=tuple(notes), attitudes_rad=z[pb.P:].reshape(-1, 3) if pb.attitude else None,
        reference_checks=checks, coarse_iterations=sol.coarse_iterations)


def _coarse_headings(pb: FitProblem, data: FitData) -> None:
    """The heading of each stance, before the fit: a coarse search over twelve headings (the
    compass decides), written into the problem's starting point ``pb.x0``."""
    point_stance = np.zeros(data.n, int) if data.stance is None else data.stance
    rows_stance = np.concatenate([np.repeat(point_stance, data.counts[s].shape[1])
                                  for s in pb.streams])
    yaws = np.linspace(-np.pi, np.pi, 12, endpoint=False)
    cost = np.zeros((len(yaws), pb.K))
    for i, yaw in enumerate(yaws):
        z = pb.x0.copy()
        z[pb.P + 2::3] = yaw
        cost[i] = np.bincount(rows_stance, pb.residual(z) ** 2, minlength=pb.K)
    pb.x0[pb.P + 2::3] = yaws[np.argmin(cost, 0)]


def _consider_covariance(pb: FitProblem, H: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The covariance of every element: the free ones from the data's information ``H`` and
    their priors, the held ones as consider parameters (at their prior σ, carried into the
    free ones they trade with)."""
    fcols = np.flatnonzero(free)
    hcols = np.flatnonzero(~free)
    # in prior units the priors make A the identity plus the data's information: a plain
    # inverse there. (A pseudo-inverse of A itself cuts every direction whose information is
    # below 1e-15 of the largest, i.e. exactly the ones the data barely see, and reports
    # them known perfectly: a heading and the hard iron it trades with came out 10x too sure.)
    D = pb.sigma0[fcols]
    A = H[np.ix_(fcols, fcols)] * np.outer(D, D) + np.eye(len(fcols))
    Sff = np.linalg.inv(A) * np.outer(D, D)
    S = -Sff @ H[np.ix_(fcols, hcols)]
    Shh = np.diag(pb.sigma0[hcols] ** 2)
    C = np.zeros((pb.size, pb.size))
    C[np.ix_(fcols, fcols)] = Sff + S @ Shh @ S.T
    C[np.ix_(fcols, hcols)] = S @ Shh
    C[np.ix_(hcols, fcols)] = (S @ Shh).T
    C[np.ix_(hcols, hcols)] = Shh
    return 0.5 * (C + C.T)


def _stream_fits(pb: FitProblem, model: Model, data: FitData, z: np.ndarray) -> list[StreamFit]:
    """The fit's quality per stream at ``z``: residual RMS and noise per axis, physical units."""
    sm = model.stream_models()
    fits = []
    pred = pb.predict(z)
    i = 0
    for s in pb.streams:
        k = data.counts[s].shape
        d = (pred[i:i + data.counts[s].size] - pb.meas[i:i + data.counts[s].size]).reshape(k)
        i += data.counts[s].size
        if data.used is not None:
            d = d[data.used]
        g = np.abs(sm[s].gain)
        fast = data.sample_excess_counts.get(s)
        fits.append(StreamFit(s, sm[s].unit, np.sqrt(np.mean(d**2, 0)) / g,
                              data.sigma_counts[s] / g, None if fast is None else fast / g))
    return fits


def _reference_checks(pb: FitProblem, z: np.ndarray, H: np.ndarray, grad: np.ndarray, C: np.ndarray
                      ) -> tuple[ReferenceCheck, ...]:
    """Each reference against the rest of the fit, leave-one-out: ``H`` and ``grad`` are the
    information and the cost's data gradient (the references' rows included) over every
    element at the fit ``z``, with the fit's weights. Without reference k, every prior
    counted (held elements' too, as if free), one Gauss-Newton step from ``z`` reaches the
    rest's own optimum: ``δ = -A⁻¹ ∇``; the joint's geometric angle there is
    ``Y = q + g δ`` (``g`` its gradient), known to ``S² = g A⁻¹ gᵀ``; ``z = (Y - v) / √(S² + σ²)``.
    A step, not the posterior's algebra: the fit stops on a flat valley (a gauge) before its
    last hundredth of a σ, and a reference 100× sharper than the rest would magnify that.
    The fitted angle's σ is the fit's own (``C``: held elements as consider parameters)."""
    if not pb.refs:
        return ()
    r, J = pb.reference_rows(z, np.arange(pb.size))
    D = pb.sigma0
    prior_grad = (z - pb.x0) / D**2
    out = []
    for k, ref in enumerate(pb.refs):
        s_r = ref.sigma_rad
        g = J[k] * s_r  # d q_geom / d z
        A = (H - np.outer(J[k], J[k])) * np.outer(D, D) + np.eye(pb.size)  # prior units
        rest = (grad - J[k] * r[k] + prior_grad) * D
        gd = g * D
        S2 = float(gd @ np.linalg.solve(A, gd))
        d = float(r[k]) * s_r  # fitted minus the reference
        P = float(g @ C @ g)
        if S2 > (10.0 * np.pi) ** 2:  # nothing but the reference knows it
            out.append(ReferenceCheck(ref, ref.angle_rad + d, np.sqrt(P), np.nan, np.inf, 0.0))
            continue
        dy = d - float(gd @ np.linalg.solve(A, rest))
        out.append(ReferenceCheck(ref, ref.angle_rad + d, np.sqrt(P), ref.angle_rad + dy, np.sqrt(S2),
                                  dy / np.sqrt(S2 + s_r**2)))
    return tuple(out)


def identify_recentred(model: Model, data: FitData, streams: Sequence[str] | None = None,
                       settings: IdentifySettings | None = None, progress=None,
                       passes: int = 3) -> tuple[Identification, FitData]:
    """:func:`identify`, then, while a joint offset (the recording's encoder zero) ends near
    its bound, fold the offsets into ``q_ref`` and fit again. Returns the last fit and data."""
    res = identify(model, data, streams, settings, progress=progress)
    for _ in range(passes - 1):
        jo = [b for b in model.blocks if b.effect == JointOffset.name]
        near = [b for b in jo if abs(res.model_x[model.index[b.name]][0]) > 0.5 * b.upper[0]]
        if not near:
            break
        dq = np.zeros(model.arm.n_joints)
        for b in jo:
            dq[model.arm.joint_names.index(b.target)] = res.model_x[model.index[b.name]][0]
        data = data.shifted(dq)
        res = identify(model, data, streams, settings, progress=progress,
                       attitude0_rad=res.attitudes_rad)
        res = replace(res, notes=res.notes + (
            "encoder zeros re-centred on the previous fit (the start pose was "
            f"{np.degrees(np.max(np.abs(dq))):.1f}° off)",))
    return res, data


def identify_separately(model: Model, data: FitData, settings: IdentifySettings | None = None,
                        progress=None) -> dict[str, Identification]:
    """The article's "separate" calibration: each accelerometer (and the IMU) alone, each with
    its own base attitude (gravity direction), with only the blocks that reach it. If the
    gravity directions disagree by more than their σ, the model or a sensor is wrong."""
    out = {}
    arm = model.arm
    groups = [[s.name] for s in arm.link_accelerometers]
    if arm.imu is not None:
        groups.append([s for s in ("imu_acc", "imu_gyro", "imu_mag") if s in data.counts])
    for g in groups:
        g = [s for s in g if s in data.counts]
        if not g:
            continue
        _, jac = model.predict_with_jacobian(data.subset(slice(0, 2)).state, None, g)
        reach = {b for s in g for b in jac.get(s, {})}
        sub = model.without([b.name for b in model.blocks if b.name not in reach])
        key = arm.imu.name if g[0].startswith("imu") else g[0]
        # a joint reference pins a joint's zero in the one fit of every sensor; each sensor
        # alone compares gravity directions, which the reference does not touch
        out[key] = identify(sub, replace(data, joint_references=()), g, settings, progress=progress,
                            mode=f"separate ({key})")
    return out
