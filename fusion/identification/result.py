"""What a fit reports (:class:`Identification`): every element's estimate, σ, prior and
whether it was held; the covariance; the holds in words; each stream's residual against its
noise; the base attitude of every stance; and each one-time joint reference checked against
the rest of the fit (:class:`ReferenceCheck`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from armfusion.fusion.identification.data import JointReference
from armfusion.fusion.identification.identifiability import Hold
from armfusion.models.effects import Model

REFERENCE_CONTRADICTION_SIGMA = 4.0
"""A reference farther than this many σ from where the rest of the fit (data and priors) puts
the joint contradicts it."""


@dataclass(frozen=True)
class ReferenceCheck:
    """A reference against the rest of the fit: where the data and the priors alone put the
    joint's geometric angle at the reference (leave-one-out, ``without_rad ± without_sigma_rad``;
    an infinite σ when nothing but the reference knows it) and the reference's distance from
    it in σ of their difference."""

    reference: JointReference
    fitted_rad: float
    fitted_sigma_rad: float
    without_rad: float
    without_sigma_rad: float
    z: float

    @property
    def contradicted(self) -> bool:
        return bool(abs(self.z) > REFERENCE_CONTRADICTION_SIGMA)

    def message(self) -> str:
        r = self.reference
        head = (f"reference {r.joint} = {np.degrees(r.angle_rad):.3f}° ± {np.degrees(r.sigma_rad):.3g}° "
                f"({r.where}, t {r.t_start_s:.1f}-{r.t_end_s:.1f} s)")
        if not np.isfinite(self.without_sigma_rad):
            return (f"{head}: nothing else in the fit knows {r.joint} there, so nothing can check "
                    "the reference; the calibration rests on it")
        rest = (f"the data and the priors alone put {r.joint} at {np.degrees(self.without_rad):.3f}° "
                f"± {np.degrees(self.without_sigma_rad):.3g}° there")
        if self.contradicted:
            return (f"{head} contradicts the calibration: {rest} ({self.z:+.1f} σ of their difference); "
                    f"check that {r.joint} stood at that angle then (the index, the pose confirmed, the "
                    "sign and the time)")
        blind_deg = REFERENCE_CONTRADICTION_SIGMA * np.degrees(np.hypot(self.without_sigma_rad, r.sigma_rad))
        return (f"{head}: {rest} ({self.z:+.1f} σ), consistent; a reference wrong by less than about "
                f"{blind_deg:.2g}° would not be detected")

    def as_dict(self) -> dict[str, Any]:
        fin = np.isfinite(self.without_sigma_rad)
        return {**self.reference.as_dict(),
                "fitted_deg": float(np.degrees(self.fitted_rad)),
                "fitted_sigma_deg": float(np.degrees(self.fitted_sigma_rad)),
                "without_reference_deg": float(np.degrees(self.without_rad)) if fin else None,
                "without_reference_sigma_deg": float(np.degrees(self.without_sigma_rad)) if fin else None,
                "z": float(self.z) if fin else None, "contradicted": self.contradicted,
                "message": self.message()}


@dataclass(frozen=True)
class StreamFit:
    stream: str
    unit: str
    rms: np.ndarray
    noise: np.ndarray
    sample_excess: np.ndarray | None = None
    """Per axis, the fast error one sample carries beyond its noise (vibration…), which the
    window means do not show (:func:`armfusion.fusion.identification.data.sample_excess`); None: none."""

    def lasting(self) -> np.ndarray:
        """RMS beyond the noise of the window means, per axis (0 where the fit is at the
        noise): the misfit a window's mean keeps, an error averaging does not lower."""
        return np.sqrt(np.maximum(self.rms**2 - self.noise**2, 0.0))

    def fast(self) -> np.ndarray:
        """One sample's fast excess beyond its noise, per axis (0 where none was measured):
        an error that averages away as noise does."""
        return np.zeros_like(self.rms) if self.sample_excess is None else np.asarray(self.sample_excess)

    def excess(self) -> np.ndarray:
        """RMS beyond the noise, per axis: the window means' misfit (:meth:`lasting`) and one
        sample's fast excess (:meth:`fast`) together."""
        return np.hypot(self.lasting(), self.fast())


@dataclass(frozen=True)
class Identification:
    """The result of a fit. ``x``/``sigma`` over ``names`` (model elements, then the base
    attitude if estimated); held elements sit at their prior with their prior σ."""

    model: Model
    names: tuple[str, ...]
    x: np.ndarray
    x0: np.ndarray
    sigma: np.ndarray
    prior_sigma: np.ndarray
    covariance: np.ndarray
    held: np.ndarray
    holds: tuple[Hold, ...]
    fits: tuple[StreamFit, ...]
    chi2_red: float
    n_samples: int
    n_residuals: int
    iterations: int
    seconds: float
    attitude_rad: np.ndarray | None
    q_ref_rad: np.ndarray
    mode: str = "simultaneous"
    notes: tuple[str, ...] = ()
    attitudes_rad: np.ndarray | None = None
    """Roll, pitch, yaw of every parked stance ``(K, 3)`` (``attitude_rad`` is the first)."""
    reference_checks: tuple[ReferenceCheck, ...] = ()
    """Each one-time joint reference of the data against the rest of the fit."""
    coarse_iterations: int = 0
    """Of ``iterations``, the Jacobians of the coarse starts (a subset of the points,
    :func:`armfusion.fusion.identification.solver.solve`)."""

    @property
    def references_contradicted(self) -> list[ReferenceCheck]:
        return [c for c in self.reference_checks if c.contradicted]

    @property
    def model_x(self) -> np.ndarray:
        return self.x[: self.model.size]

    def correlation(self) -> np.ndarray:
        d = np.sqrt(np.clip(np.diag(self.covariance), 1e-300, None))
        return self.covariance / np.outer(d, d)

    def correlated_pairs(self, limit: float = 0.9) -> list[tuple[str, str, float]]:
        C = self.correlation()
        free = ~self.held
        out = []
        idx = np.flatnonzero(free)
        for a in range(len(idx)):
            for b in range(a + 1, len(idx)):
                i, j = idx[a], idx[b]
                if abs(C[i, j]) > limit:
                    out.append((self.names[i], self.names[j], float(C[i, j])))
        return sorted(out, key=lambda p: -abs(p[2]))

    def calibrated_model(self) -> Model:
        """The model with the estimates as values and their σ as the new priors."""
        m = self.model
        sig = {b.name: np.maximum(self.sigma[m.index[b.name]], 1e-12) for b in m.blocks}
        return Model(m.arm, m.effects, m.unpack(self.model_x), sig, m.earth_field_W_ut, m.masses)

    def value(self, element: str) -> tuple[float, float]:
        i = self.names.index(element)
        return float(self.x[i]), float(self.sigma[i])

    def unmodelled_g(self, part: str = "all") -> dict[str, float]:
        """Per accelerometer (by sensor name): what the fit leaves beyond the noise (the worst
        axis), in g; ``part``: ``"all"``, ``"lasting"`` (:meth:`StreamFit.lasting`: what
        stays) or ``"fast"`` (:meth:`StreamFit.fast`: what averages away)."""
        of = {"all": StreamFit.excess, "lasting": StreamFit.lasting, "fast": StreamFit.fast}[part]
        out = {}
        for f in self.fits:
            if f.unit == "g":
                name = self.model.arm.imu.name if f.stream == "imu_acc" else f.stream
                out[name] = float(np.max(of(f)))
        return out

    def as_dict(self) -> dict[str, Any]:
        params = []
        for i, n in enumerate(self.names):
            params.append({"name": n, "value": float(self.x[i]), "sigma": float(self.sigma[i]),
                           "prior": float(self.x0[i]), "prior_sigma": float(self.prior_sigma[i]),
                           "held": bool(self.held[i])})
        return {
            "mode": self.mode, "parameters": params,
            "holds": [{"element": h.element, "partners": [p for p, _ in h.partners],
                       "message": h.message, "suggestion": h.suggestion} for h in self.holds],
            "correlated_pairs": [{"a": a, "b": b, "rho": r} for a, b, r in self.correlated_pairs()],
            "fit": [{"stream": f.stream, "unit": f.unit, "rms": f.rms.tolist(), "noise": f.noise.tolist()}
                    for f in self.fits],
            "chi2_red": self.chi2_red, "n_samples": self.n_samples, "n_residuals": self.n_residuals,
            "iterations": self.iterations, "coarse_iterations": self.coarse_iterations,
            "seconds": round(self.seconds, 3),
            "attitude_deg": None if self.attitude_rad is None else np.degrees(self.attitude_rad).tolist(),
            "stance_attitudes_deg": None if self.attitudes_rad is None
            else np.degrees(self.attitudes_rad).tolist(),
            "q_ref_rad": self.q_ref_rad.tolist(), "notes": list(self.notes),
            "references": [c.as_dict() for c in self.reference_checks],
            "unmodelled_g": self.unmodelled_g(),
        }

    def summary(self) -> str:
        nf = int((~self.held).sum())
        return (f"{self.mode} fit: {nf} parameters estimated, {int(self.held.sum())} held at their "
                f"priors; {self.n_samples:,} samples, reduced chi-square {self.chi2_red:.2f}, "
                f"{self.iterations} Jacobians, {self.seconds:.1f} s")
