"""The sensor-calibration article's own model and fits (Renk et al., seed 003).

Each axis k of a triaxial accelerometer (or magnetometer) reads a voltage

    V_k = m S_k ĝᵀ P_k + δ_k                                        (eqs. 11, 13, 19)

with ``m`` the field's magnitude (9.8 m/s² for gravity, 1 G for the Earth's field), ``S_k``
the sensitivity, ``δ_k`` the offset, ``P_k = R_0E(θ) Rz(γ_k) Ry(β_k) î`` the axis in the
robot base frame (eqs. 4-8: β about the end effector's ĵ, then γ about its k̂) and
``ĝ = Rz(ψ) Ry(φ) î`` the field's direction in the base frame (eq. 12: φ = 90° is straight
down). ``R_0E`` comes from the arm config's DH table (``config/crs_a465.yaml``, the
article's Table 1).

* **separate** (eq. 14, 20): each axis alone, six parameters (β, γ, S, δ, φ_k, ψ_k);
* **simultaneous** (eq. 15, 21): the three axes with one field direction, 14 parameters.

Least squares with analytic Jacobians (the article used MATLAB's fminunc with numerical
gradients), weighted by each axis's noise; σ from the Jacobian. The start is linear, not
the article's "every axis along î, S = 1, δ = 2.5 V": for each of 64 trial field
directions the model is linear in ``(m S_k P_k, δ_k)``, the best one starts the fit.
Where the field points along the base's k̂ (φ = ±90°), ψ does not change the prediction:
the identifiability analysis of :mod:`armfusion.fusion.identification.identifiability` says so
and the fit reports ψ as undefined (the article's Table 3 and 7 notice the same: ψ spread by
100°, σ 88.8°).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from armfusion.fusion.identification.identifiability import analyse_identifiability
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.models.arm import ArmModel
from armfusion.models.kinematics import forward_kinematics
from armfusion.models.rotations import wrap_angle
from scipy.optimize import least_squares

GRAVITY_ARTICLE_MPS2 = 9.8
ARTICLE_JOINTS = ("j1", "j5", "j6")
ARTICLE_SAMPLES = 166_400
ARTICLE_EVERY = 25
"""The article analyses every 25th of its 166,400 samples: 6,656 orientations at 4 Hz."""

# the article's Table 2 (simulated accelerometer), gravity along -k
TABLE2 = {"beta_deg": [-89.0, 1.0, -3.75], "gamma_deg": [2.0, 93.5, -2.0],
          "S": [0.1, 0.15, 0.095], "delta_v": [2.45, 2.55, 2.3], "phi_deg": 90.0, "psi_deg": 0.0}
ACCEL_NOISE_V = (0.0134, 0.0136, 0.0146)
# its Table 10 (simultaneous magnetometer estimates), used as the magnetometer's truth
TABLE10 = {"beta_deg": [0.96237, -85.6307, -4.0172], "gamma_deg": [270.2059, 185.8359, 1.2153],
           "S": [1.3006, 1.3283, 1.3342], "delta_v": [2.4216, 2.3967, 2.7643],
           "phi_deg": 59.4127, "psi_deg": 81.402}
MAG_NOISE_V = (0.0085, 0.0068, 0.0117)


def axis_in_ee(beta: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Eq. 6: ``Rz(γ) Ry(β) î`` for each axis, ``(..., 3)``."""
    cb, sb, cg, sg = np.cos(beta), np.sin(beta), np.cos(gamma), np.sin(gamma)
    return np.stack([cb * cg, cb * sg, -sb], -1)


def field_direction(phi: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Eq. 12: ``Rz(ψ) Ry(φ) î``."""
    return axis_in_ee(phi, psi)


def angles_between_deg(beta: np.ndarray, gamma: np.ndarray) -> dict[str, float]:
    """The angles between axes 1-2, 1-3, 2-3 (the article's Tables 4, 6, 9, 11)."""
    P = axis_in_ee(np.asarray(beta), np.asarray(gamma))
    out = {}
    for a, b in ((0, 1), (0, 2), (1, 2)):
        out[f"{a + 1} and {b + 1}"] = float(np.degrees(np.arccos(np.clip(P[a] @ P[b], -1, 1))))
    return out


def end_effector_rotations(arm: ArmModel, q_rad: np.ndarray) -> np.ndarray:
    """``R_0E (N, 3, 3)`` of the arm's last link from the DH table (eq. 8)."""
    return forward_kinematics(arm, np.asarray(q_rad, float))[0]


@dataclass(frozen=True)
class TriaxParams:
    """β, γ [rad], S, δ [V] per axis; the field's φ, ψ [rad] (3 values each when separate)."""

    beta: np.ndarray
    gamma: np.ndarray
    S: np.ndarray
    delta: np.ndarray
    phi: np.ndarray
    psi: np.ndarray

    @classmethod
    def from_table(cls, t: dict) -> TriaxParams:
        return cls(np.radians(t["beta_deg"]), np.radians(t["gamma_deg"]), np.asarray(t["S"], float),
                   np.asarray(t["delta_v"], float), np.full(3, np.radians(t["phi_deg"])),
                   np.full(3, np.radians(t["psi_deg"])))


def predict_voltages(R_0E: np.ndarray, p: TriaxParams, magnitude: float) -> np.ndarray:
    """Eq. 11/19 for every sample and axis, ``(N, 3)`` volts."""
    g = field_direction(np.broadcast_to(p.phi, (3,)), np.broadcast_to(p.psi, (3,)))  # (3 axes, 3)
    P = axis_in_ee(p.beta, p.gamma)  # (3, 3)
    u = np.einsum("nji,kj->nki", R_0E, g)  # R_0Eᵀ ĝ_k
    return magnitude * p.S * np.einsum("nki,ki->nk", u, P) + p.delta


def simulate_article(arm: ArmModel, truth: TriaxParams, noise_v=ACCEL_NOISE_V, noise_scale: float = 1.0,
                     magnitude: float = GRAVITY_ARTICLE_MPS2, seed: int = 0,
                     samples: int = ARTICLE_SAMPLES, every: int = ARTICLE_EVERY):
    """The article's simulated experiment: its maneuver (joints 1, 5, 6; 166,400 samples at
    100 Hz, every ``every``-th kept), voltages from ``truth``, white noise N(0, σ_k·scale).
    Returns ``(q_rad (n, 6), R_0E (n, 3, 3), V (n, 3))``."""
    from armfusion.models.trajectories import make_scenario

    sc = make_scenario(arm, "renk-maneuver", samples / 100.0, seed, joints=list(ARTICLE_JOINTS))
    t = np.arange(0, samples, every) / 100.0
    q = sc.state(t).q_rad
    R = end_effector_rotations(arm, q)
    V = predict_voltages(R, truth, magnitude)
    rng = np.random.default_rng([seed, 0x3E4C])
    V = V + rng.standard_normal(V.shape) * np.asarray(noise_v, float) * noise_scale
    return q, R, V


@dataclass(frozen=True)
class TriaxFit:
    mode: str
    params: TriaxParams
    sigma: TriaxParams
    rms_v: np.ndarray
    cost_rms_v: float
    n: int
    seconds: float
    nfev: int
    undefined: tuple[str, ...] = ()
    messages: tuple[str, ...] = field(default=())

    def angles_between_deg(self) -> dict[str, float]:
        return angles_between_deg(self.params.beta, self.params.gamma)

    def gravity_directions(self) -> np.ndarray:
        """The field's unit direction(s) in the base frame, ``(3, 3)`` (one row per axis)."""
        return field_direction(np.broadcast_to(self.params.phi, (3,)), np.broadcast_to(self.params.psi, (3,)))


def _axis_fun(R, V, w, magnitude):
    """Residual and Jacobian of one axis: params (β, γ, S, δ, φ, ψ)."""
    def res_jac(x, jac=False):
        b, g, S, d, ph, ps = x
        P = axis_in_ee(b, g)
        gd = field_direction(ph, ps)
        RP = R @ P  # (N, 3) axis in base
        dot = RP @ gd
        r = (magnitude * S * dot + d - V) * w
        if not jac:
            return r
        cb, sb, cg, sg = np.cos(b), np.sin(b), np.cos(g), np.sin(g)
        cp, sp, cs, ss = np.cos(ph), np.sin(ph), np.cos(ps), np.sin(ps)
        dPb = np.array([-sb * cg, -sb * sg, -cb])
        dPg = np.array([-cb * sg, cb * cg, 0.0])
        dgp = np.array([-sp * cs, -sp * ss, -cp])
        dgs = np.array([-cp * ss, cp * cs, 0.0])
        u = R.transpose(0, 2, 1) @ gd  # R_0Eᵀ ĝ
        J = np.empty((len(V), 6))
        m = magnitude * S
        J[:, 0] = m * (u @ dPb)
        J[:, 1] = m * (u @ dPg)
        J[:, 2] = magnitude * dot
        J[:, 3] = 1.0
        J[:, 4] = m * (RP @ dgp)
        J[:, 5] = m * (RP @ dgs)
        return r, J * w
    return res_jac


class _Start(NamedTuple):
    """A fit's start: β, γ [rad], S, δ [V] per axis, ``(3,)`` each, and the one field
    direction φ, ψ [rad]."""

    beta: np.ndarray
    gamma: np.ndarray
    S: np.ndarray
    delta: np.ndarray
    phi: float
    psi: float


class _Solved(NamedTuple):
    """A least-squares fit's values and σ [per :class:`TriaxParams` field, 3 values each; σ NaN
    where undefined], the elements the identifiability analysis calls undefined, and the
    function evaluations it took."""

    values: dict[str, np.ndarray]
    sigma: dict[str, np.ndarray]
    undefined: list[str]
    nfev: int


AXIS_PARAMS = ("beta", "gamma", "S", "delta", "phi", "psi")
"""One axis's parameters, in the order of its Jacobian's columns (:func:`_axis_fun`)."""


def _linear_start(R, V, magnitude, dirs) -> _Start:
    """For each trial direction, the linear fit of every axis; the best direction's values."""
    best = None
    for gd in dirs:
        u = R.transpose(0, 2, 1) @ gd  # (N, 3)
        A = np.hstack([u, np.ones((len(u), 1))])
        sol, res, *_ = np.linalg.lstsq(A, V, rcond=None)
        cost = float(np.sum((A @ sol - V) ** 2))
        if best is None or cost < best[0]:
            best = (cost, gd, sol)
    _, gd, sol = best
    w = sol[:3].T  # (3 axes, 3)
    S = np.linalg.norm(w, axis=1) / magnitude
    P = w / np.linalg.norm(w, axis=1, keepdims=True)
    beta = -np.arcsin(np.clip(P[:, 2], -1, 1))
    gamma = np.arctan2(P[:, 1], P[:, 0])
    phi = -np.arcsin(np.clip(gd[2], -1, 1))
    psi = np.arctan2(gd[1], gd[0])
    return _Start(beta, gamma, S, sol[3], phi, psi)


def _sphere(n: int = 64) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z**2)
    a = np.pi * (1 + 5**0.5) * k
    return np.stack([r * np.cos(a), r * np.sin(a), z], 1)


def _psi_identifiable(J, x, names) -> list[str]:
    """Ask the identifiability analysis; the scale: 0.1 rad (6°) for the angles, 10 % of S,
    1 V: an angle the data know no better than 6° is reported as undefined."""
    scale = np.array([0.1 if n.startswith(("beta", "gamma", "phi", "psi")) else
                      (0.1 * abs(x[i]) if n.startswith("S") else 1.0) for i, n in enumerate(names)])
    holds = analyse_identifiability(J, scale, names, np.ones(len(names), bool),
                                    IdentifySettings(hold_ratio=1.0))
    return [h.element for h in holds]


def _fit_separate(R: np.ndarray, V: np.ndarray, w: np.ndarray, magnitude: float, start: _Start) -> _Solved:
    """Eq. 14, 20: each axis alone, with its own field direction (six parameters each)."""
    out = {k: np.zeros(3) for k in AXIS_PARAMS}
    sig = {k: np.zeros(3) for k in out}
    undefined: list[str] = []
    nfev = 0
    for k in range(3):
        f = _axis_fun(R, V[:, k], w[k], magnitude)
        x0 = np.array([start.beta[k], start.gamma[k], start.S[k], start.delta[k], start.phi, start.psi])
        sol = least_squares(f, x0, jac=lambda x, f=f: f(x, True)[1], method="lm",
                            xtol=1e-12, ftol=1e-12)
        nfev += sol.nfev
        x = sol.x
        r, J = f(x, True)
        C = np.linalg.pinv(J.T @ J)
        names = [f"{n}{k + 1}" for n in AXIS_PARAMS]
        held = _psi_identifiable(J, x, names)
        undefined += held
        for i, key in enumerate(AXIS_PARAMS):
            out[key][k] = x[i]
            sig[key][k] = np.nan if names[i] in held else np.sqrt(C[i, i])
    return _Solved(out, sig, undefined, nfev)


def _fit_simultaneous(R: np.ndarray, V: np.ndarray, w: np.ndarray, magnitude: float,
                      start: _Start) -> _Solved:
    """Eq. 15, 21: the three axes with one field direction (14 parameters: β, γ, S, δ of
    each axis, then φ, ψ)."""
    fs = [_axis_fun(R, V[:, k], w[k], magnitude) for k in range(3)]
    N = len(V)

    def unpack(x):
        return [np.array([x[4 * k], x[4 * k + 1], x[4 * k + 2], x[4 * k + 3], x[12], x[13]])
                for k in range(3)]

    def fun(x):
        return np.concatenate([fs[k](xk) for k, xk in enumerate(unpack(x))])

    def jac(x):
        J = np.zeros((3 * N, 14))
        for k, xk in enumerate(unpack(x)):
            _, Jk = fs[k](xk, True)
            J[k * N:(k + 1) * N, 4 * k:4 * k + 4] = Jk[:, :4]
            J[k * N:(k + 1) * N, 12:14] = Jk[:, 4:6]
        return J

    x0 = np.concatenate([np.stack([start.beta, start.gamma, start.S, start.delta], 1).ravel(),
                         [start.phi, start.psi]])
    sol = least_squares(fun, x0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12)
    x = sol.x
    J = jac(x)
    C = np.linalg.pinv(J.T @ J)
    names = [f"{n}{k + 1}" for k in range(3) for n in AXIS_PARAMS[:4]] + ["phi", "psi"]
    held = _psi_identifiable(J, x, names)
    out = {k: np.zeros(3) for k in AXIS_PARAMS}
    sig = {k: np.zeros(3) for k in out}
    for k in range(3):
        for i, key in enumerate(AXIS_PARAMS[:4]):
            j = 4 * k + i
            out[key][k] = x[j]
            sig[key][k] = np.nan if names[j] in held else np.sqrt(C[j, j])
    for key, j in (("phi", 12), ("psi", 13)):
        out[key][:] = x[j]
        sig[key][:] = np.nan if names[j] in held else np.sqrt(C[j, j])
    return _Solved(out, sig, list(held), sol.nfev)


def _undefined_messages(undefined: list[str], phi_deg: float) -> tuple[str, ...]:
    """One sentence per element the fit reports as undefined."""
    return tuple(f"{u}: undefined: the field points along the base's k̂ axis (φ = {phi_deg:.2f}°), "
                 "so a turn ψ about k̂ does not change it; reported, not estimated" if u.startswith("psi")
                 else f"{u}: the data cannot tell it" for u in undefined)


def fit_triax(R_0E: np.ndarray, V: np.ndarray, mode: str = "simultaneous", noise_v=ACCEL_NOISE_V,
              magnitude: float = GRAVITY_ARTICLE_MPS2) -> TriaxFit:
    """Fit the article's model to voltages ``V (N, 3)`` at end-effector rotations ``R_0E``:
    ``separate`` (:func:`_fit_separate`) or ``simultaneous`` (:func:`_fit_simultaneous`),
    both from the linear start (:func:`_linear_start`), the result in its canonical form
    (:func:`_canonical`)."""
    if mode not in ("separate", "simultaneous"):
        raise ValueError(f"mode must be 'separate' or 'simultaneous', not {mode!r}")
    t0 = time.perf_counter()
    R = np.asarray(R_0E, float)
    V = np.asarray(V, float)
    noise = np.broadcast_to(np.asarray(noise_v, float), (3,))
    w = 1.0 / noise
    sub = slice(None, None, max(1, len(V) // 7000))  # the start needs no more than ~7,000 points
    start = _linear_start(R[sub], V[sub], magnitude, _sphere())
    fit = _fit_separate if mode == "separate" else _fit_simultaneous
    solved = fit(R, V, w, magnitude, start)
    p = _canonical(TriaxParams(**solved.values))
    resid = predict_voltages(R, p, magnitude) - V
    rms = np.sqrt(np.mean(resid**2, 0))
    msgs = _undefined_messages(solved.undefined, np.degrees(p.phi[0]))
    return TriaxFit(mode, p, TriaxParams(**solved.sigma), rms, float(np.sqrt(np.mean(resid**2))), len(V),
                    time.perf_counter() - t0, int(solved.nfev), tuple(solved.undefined), msgs)


def _canonical(p: TriaxParams) -> TriaxParams:
    """S > 0 (a negative S is the same axis reversed), the field's φ ≥ 0 (the field and
    every axis reversed together fit the same), angles wrapped: β in [-90°, 90°], γ and ψ
    in [0°, 360°) as the article prints them."""
    beta, gamma, S = p.beta.copy(), p.gamma.copy(), p.S.copy()
    neg = S < 0
    # -P: β -> -β, γ -> γ + π
    beta[neg], gamma[neg], S[neg] = -beta[neg], gamma[neg] + np.pi, -S[neg]
    beta = wrap_angle(beta)
    flip = np.abs(beta) > np.pi / 2  # (β, γ) and (π - β, γ + π) give the same axis
    beta[flip] = np.sign(beta[flip]) * np.pi - beta[flip]
    gamma[flip] += np.pi
    phi, psi = p.phi.copy(), p.psi.copy()
    phi = wrap_angle(phi)
    f2 = np.abs(phi) > np.pi / 2
    phi[f2] = np.sign(phi[f2]) * np.pi - phi[f2]
    psi[f2] += np.pi
    # (ĝ, P_k) and (-ĝ, -P_k) predict the same voltages: the data cannot tell a field
    # pointing down seen by these axes from one pointing up seen by the reversed axes. Report
    # the field with no upward component (φ ≥ 0: gravity; the Earth's field north of the
    # magnetic equator, as in the article's Tables 8, 10), reversing the axes with it.
    up = np.broadcast_to(phi < 0, (3,))
    phi, psi = np.where(phi < 0, -phi, phi), np.where(phi < 0, psi + np.pi, psi)
    beta[up], gamma[up] = -beta[up], gamma[up] + np.pi
    return TriaxParams(beta, gamma % (2 * np.pi), S, p.delta.copy(), phi, psi % (2 * np.pi))
