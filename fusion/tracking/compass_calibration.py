"""The compass calibrated by driving: the hard and soft iron the config leaves unknown,
estimated online, with their sigma, from the turns the chair makes anyway
(:class:`IronEstimator`).

A chair parked for its sensor calibration never turns, so its fit cannot tell the
compass's hard iron (a field that turns with the chair) from Earth's (a field that does
not): the config's ``mag_hard_iron`` keeps a sigma of many µT, and a compass read through
it would be tens of degrees off. Turning, the readings trace a circle about the iron's
offset; no heading is needed to find that circle. With the tilt the tracker knows from
gravity, each (averaged) reading ``m`` (µT, compass axes, the config's iron and the arm's
steel already undone) is de-tilted, ``h = T (M m - c)`` with ``T`` the world-up frame's
rotation from the compass's axes, and must have

* a horizontal part of Earth's horizontal field, ``|h_xy| = H``, and
* a vertical part of Earth's vertical field, ``h_z = -V``,

whatever the chair's heading. The unknowns are the residual hard iron ``c`` (µT, 3), the
residual soft iron as the symmetric ``M = I - S(e)`` (6, the config's ``mag_soft_iron``
labels) and Earth's ``H`` and ``V`` (µT). A Gauss-Newton fit with the config's sigmas as
the prior finds them and their covariance; the heading's sigma at any reading follows
(:meth:`IronEstimator.heading_sigma_rad`).

Memory and time are bounded: readings are kept as running means in bins of the de-tilted
field's direction (``iron_bin_deg`` wide); each bin counts as at most
``iron_bin_max_count`` independent readings (the model's own errors do not average away
by sitting at one heading), its weight fades with time (``iron_forget_s``: a slow change of
the chair's iron is followed), and the fit runs at most once per ``iron_refit_period_s``.
Once calibrated, a reading whose field is off Earth's by more than the guard's tolerances
is a disturbance and is not binned.
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.models.effects.library import MagHardIron, MagSoftIron

N_PARAMS = 11
"""c (3), e (6: xx, yy, zz, xy, xz, yz), H, V."""
SOFT_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
"""The soft iron's six entries (the ``mag_soft_iron`` effect's labels)."""
SLICE_HARD, SLICE_SOFT, I_H, I_V = slice(0, 3), slice(3, 9), 9, 10
HUBER_K = 2.5
"""Bins whose residual is beyond this many sigma count with Huber's weight."""


def soft_matrix(e: np.ndarray) -> np.ndarray:
    """``M = I - S(e)``: the map that undoes a small residual soft iron ``e``."""
    M = np.eye(3)
    for (a, b), v in zip(SOFT_PAIRS, e, strict=True):
        M[a, b] -= v
        if a != b:
            M[b, a] -= v
    return M


def detilt(roll_rad: float, pitch_rad: float, R_0I: np.ndarray) -> np.ndarray:
    """``T``: a vector in the compass's axes into the frame of world up and the base's
    heading (``Ry(pitch) Rx(roll) R_0I``: :func:`armfusion.models.rotations.R_from_rpy` at zero yaw,
    written out for one attitude, ten times faster)."""
    sr, cr, sp, cp = math.sin(roll_rad), math.cos(roll_rad), math.sin(pitch_rad), math.cos(pitch_rad)
    return np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]]) @ R_0I


class IronEstimator:
    """Online residual hard and soft iron, with covariance, from readings while turning.

    ``prior_sigma``: the prior sigma of ``c`` (µT, 3: the config's hard iron sigma, or
    the datasheet-typical one) and of ``e`` (6); ``H_ut``, ``V_ut``: Earth's horizontal and
    vertical field as first guessed (the startup's still window), ``field_sigma_ut`` their
    sigma. ``noise_ut``: one averaged reading's noise per axis (the sensor's, averaged,
    plus the model floor the settings give)."""

    def __init__(self, prior_sigma: np.ndarray, H_ut: float, V_ut: float, field_sigma_ut: float,
                 settings, t_s: float = 0.0):
        st = settings
        self.bin_rad = math.radians(st.iron_bin_deg)
        self.n_bins = int(round(2 * math.pi / self.bin_rad))
        self.max_count = float(st.iron_bin_max_count)
        self.forget_s = float(st.iron_forget_s)
        self.refit_period_s = float(st.iron_refit_period_s)
        self.floor_ut = float(st.iron_model_floor_ut)
        s0 = np.concatenate([np.asarray(prior_sigma, float), [field_sigma_ut, field_sigma_ut]])
        if s0.shape != (N_PARAMS,) or not np.all(np.isfinite(s0)) or np.any(s0 <= 0):
            raise ValueError(f"IronEstimator: prior sigmas must be {N_PARAMS - 2} positive numbers "
                             f"(hard iron 3, soft iron 6)")
        self.theta0 = np.zeros(N_PARAMS)
        self.theta0[I_H], self.theta0[I_V] = H_ut, V_ut
        self.info0 = np.diag(1.0 / s0**2)
        self.theta = self.theta0.copy()
        self._M = None
        self.P = np.diag(s0**2)
        nb = self.n_bins
        self.w = np.zeros(nb)            # each bin's weight (independent readings it counts as)
        self.var = np.zeros(nb)          # one reading's variance in it, µT²
        self.mT = np.zeros((nb, 3, 3))   # mean of T
        self.mTm = np.zeros((nb, 3, 3, 3))  # mean of T_ik m_l
        self.mTa = np.zeros((nb, 3))     # mean of T b_arm
        self.t_last = np.full(nb, -np.inf)
        self._t_fit = -np.inf
        self._t_faded = float(t_s)
        self._dirty = False
        self.readings = 0
        """Readings binned so far."""
        self.chi2_reduced = 1.0
        """The last fit's reduced chi-square (its covariance is widened by it when above 1)."""

    # -- the readings -------------------------------------------------------------------
    def corrected(self, m_ut: np.ndarray, b_arm_ut: np.ndarray | None = None) -> np.ndarray:
        """The reading with the estimated residual iron (and the arm's field) undone, µT,
        compass axes: ``M m - c - b_arm``."""
        out = self.M @ m_ut - self.theta[SLICE_HARD]
        return out if b_arm_ut is None else out - b_arm_ut

    @property
    def M(self) -> np.ndarray:
        """``I - S(e)`` at the present estimate (made once per estimate)."""
        if self._M is None:
            self._M = soft_matrix(self.theta[SLICE_SOFT])
        return self._M

    def add(self, t_s: float, m_ut: np.ndarray, T: np.ndarray, noise_var_ut2: float,
            b_arm_ut: np.ndarray | None = None, disturbed: bool = False) -> bool:
        """Bin one averaged reading ``m_ut`` (compass axes) taken at de-tilt ``T``; the field
        of the arm's steel ``b_arm_ut`` (compass axes) is the model's. Returns whether it was
        binned (a ``disturbed`` reading is not, once the estimate is good enough to say so)."""
        if disturbed:
            return False
        m = np.asarray(m_ut, float)
        a = np.zeros(3) if b_arm_ut is None else np.asarray(b_arm_ut, float)
        h = T @ (self.corrected(m) - a)
        k = int(math.floor((math.atan2(h[1], h[0]) + math.pi) / self.bin_rad)) % self.n_bins
        w = self.w[k]
        f = 1.0 / (w + 1.0)
        if w == 0.0:
            self.mT[k], self.mTm[k], self.mTa[k] = T, np.einsum("ik,l->ikl", T, m), T @ a
            self.var[k] = noise_var_ut2
        else:
            self.mT[k] += f * (T - self.mT[k])
            self.mTm[k] += f * (np.einsum("ik,l->ikl", T, m) - self.mTm[k])
            self.mTa[k] += f * (T @ a - self.mTa[k])
            self.var[k] += f * (noise_var_ut2 - self.var[k])
        self.w[k] = min(w + 1.0, self.max_count)
        self.t_last[k] = t_s
        self.readings += 1
        self._dirty = True
        return True

    def fade(self, t_s: float) -> None:
        """Every bin's weight fades with ``exp(-dt / iron_forget_s)``."""
        dt = t_s - self._t_faded
        if dt > 0 and self.forget_s > 0:
            self.w *= math.exp(-dt / self.forget_s)
            self._t_faded = t_s

    # -- the fit ------------------------------------------------------------------------
    def _bin_field(self, th: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The bins' mean de-tilted field ``h (K, 3)`` and ``dh/dθ (K, 3, 11)``."""
        M = soft_matrix(th[SLICE_SOFT])
        mTm, mT = self.mTm[k], self.mT[k]
        h = np.einsum("nikl,kl->ni", mTm, M) - mT @ th[SLICE_HARD] - self.mTa[k]
        J = np.zeros((len(k), 3, N_PARAMS))
        J[:, :, SLICE_HARD] = -mT
        for c, (a, b) in enumerate(SOFT_PAIRS):
            col = -mTm[:, :, a, b] if a == b else -(mTm[:, :, a, b] + mTm[:, :, b, a])
            J[:, :, 3 + c] = col
        return h, J

    def _residuals(self, th: np.ndarray, k: np.ndarray):
        h, Jh = self._bin_field(th, k)
        hxy = np.maximum(np.hypot(h[:, 0], h[:, 1]), 1e-9)
        r = np.concatenate([hxy - th[I_H], h[:, 2] + th[I_V]])
        J1 = (h[:, 0, None] * Jh[:, 0] + h[:, 1, None] * Jh[:, 1]) / hxy[:, None]
        J1[:, I_H] -= 1.0
        J2 = Jh[:, 2].copy()
        J2[:, I_V] += 1.0
        return r, np.vstack([J1, J2])

    def refit(self, t_s: float, force: bool = False) -> bool:
        """Fit again from the bins if anything new arrived and ``iron_refit_period_s`` has
        passed (or ``force``). Returns whether it did."""
        if not self._dirty or (not force and t_s - self._t_fit < self.refit_period_s):
            return False
        self.fade(t_s)
        self._t_fit = t_s
        self._dirty = False
        k = np.flatnonzero(self.w > 1e-6)
        if len(k) == 0:
            return False
        wk = self.w[k] / (self.var[k] + self.floor_ut**2)
        W0 = np.concatenate([wk, wk])
        W = W0
        th = self.theta.copy()
        for _ in range(8):
            r, J = self._residuals(th, k)
            # Huber's weights: a bin far off the circle (a disturbance binned before the
            # estimate could tell it) pulls as one at HUBER_K sigma, not with all its weight
            z = np.abs(r) * np.sqrt(W0)
            W = W0 * np.minimum(1.0, HUBER_K / np.maximum(z, 1e-12))
            A = self.info0 + J.T @ (W[:, None] * J)
            g = J.T @ (W * r) + self.info0 @ (th - self.theta0)
            step = np.linalg.solve(A, g)
            th -= step
            if np.max(np.abs(step[:9])) < 1e-4:
                break
        r, J = self._residuals(th, k)
        A = self.info0 + J.T @ (W[:, None] * J)
        self.theta, self._M = th, None
        P = np.linalg.inv(A)
        # readings that scatter about the circle more than their noise says (a field that is
        # not Earth's plus a constant iron: disturbances, a tilt gone wrong) widen the
        # estimate's doubt by their reduced chi-square
        dof = 2 * len(k) - N_PARAMS
        self.chi2_reduced = float(np.sum(W * r * r) / dof) if dof >= 5 else 1.0
        self.P = 0.5 * (P + P.T) * max(1.0, self.chi2_reduced)
        return True

    # -- what it says about the heading ---------------------------------------------------
    def heading_sigma_rad(self, m_ut: np.ndarray, T: np.ndarray, b_arm_ut: np.ndarray | None = None) -> float:
        """The heading's sigma (rad) that the estimate's uncertainty leaves at a reading
        ``m_ut`` (compass axes) taken at de-tilt ``T``."""
        m = np.asarray(m_ut, float)
        a = np.zeros(3) if b_arm_ut is None else np.asarray(b_arm_ut, float)
        h = T @ (self.corrected(m) - a)
        # dh/dθ for this one reading
        Jh = np.zeros((3, N_PARAMS))
        Jh[:, SLICE_HARD] = -T
        for c, (i, j) in enumerate(SOFT_PAIRS):
            col = -T[:, i] * m[j] if i == j else -(T[:, i] * m[j] + T[:, j] * m[i])
            Jh[:, 3 + c] = col
        n2 = max(h[0] ** 2 + h[1] ** 2, 1e-12)
        g = (h[1] * Jh[0] - h[0] * Jh[1]) / n2  # psi = atan2(-h_y, h_x)
        return float(math.sqrt(max(g @ self.P @ g, 0.0)))

    @property
    def field_ut(self) -> tuple[float, float]:
        """Earth's horizontal and vertical field as estimated, µT."""
        return float(self.theta[I_H]), float(self.theta[I_V])

    @property
    def coverage_deg(self) -> float:
        """How much of the circle of headings the bins cover, deg."""
        return float(np.count_nonzero(self.w > 0.5) * math.degrees(self.bin_rad))

    def hard_iron_sigma_ut(self) -> np.ndarray:
        return np.sqrt(np.diag(self.P)[SLICE_HARD])

    # -- saved between runs ------------------------------------------------------------------
    def snapshot(self) -> dict:
        """The estimate and its covariance (what the next start reuses), and the bins."""
        return {"theta": self.theta.tolist(), "P": self.P.tolist(), "readings": self.readings}

    def restore(self, snap: dict) -> None:
        """Start from a saved estimate: it becomes the prior (its covariance the prior's)."""
        th = np.asarray(snap["theta"], float)
        P = np.asarray(snap["P"], float)
        if th.shape != (N_PARAMS,) or P.shape != (N_PARAMS, N_PARAMS) or not (
                np.all(np.isfinite(th)) and np.all(np.isfinite(P))):
            raise ValueError(f"compass calibration: a saved estimate needs theta ({N_PARAMS}) and "
                             f"P ({N_PARAMS}x{N_PARAMS}), finite")
        P = 0.5 * (P + P.T)
        self.theta0, self.theta, self._M = th.copy(), th.copy(), None
        self.P = P
        self.info0 = np.linalg.inv(P + 1e-12 * np.eye(N_PARAMS))
        self.readings = int(snap.get("readings", 0))


# -- what a drive tells the config -----------------------------------------------------------
def drive_compass_entries(correction_map: tuple[np.ndarray, np.ndarray] | None, estimator: IronEstimator,
                          target: str, source: str) -> list[dict]:
    """The config's ``mag_hard_iron`` and ``mag_soft_iron`` entries that a drive's estimate
    makes: the config's own map (``correction_map``, ``(A, c0)`` as
    :func:`armfusion.fusion.tracking.calibrated.undo_map` gives it; None: none) composed with the
    estimate, with the estimate's sigmas (its covariance is the whole doubt: the config's
    was its prior).

    The reading is ``y = L ideal + c0`` (``L = A^-T``); the estimate undoes ``M m - c`` of
    ``m = L^-1 (y - c0)``, so ``y = S ideal + c_new`` with ``S = L M^-1`` (symmetrised: the
    effect's matrix is) and ``c_new = c0 + S c``."""
    A, c0 = correction_map if correction_map is not None else (np.eye(3), np.zeros(3))
    L = np.linalg.inv(np.asarray(A, float).T)
    th, P = estimator.theta, estimator.P
    S = L @ np.linalg.inv(soft_matrix(th[SLICE_SOFT]))
    S = 0.5 * (S + S.T)
    c_new = np.asarray(c0, float) + S @ th[SLICE_HARD]
    sig_c = np.sqrt(np.diag(S @ P[SLICE_HARD, SLICE_HARD] @ S.T))
    sig_e = np.sqrt(np.diag(P[SLICE_SOFT, SLICE_SOFT]))
    e_new = [S[a, b] - (1.0 if a == b else 0.0) for a, b in SOFT_PAIRS]
    note = f"from the chair's turns in {source} (the tracker's online compass calibration)"
    return [
        {"effect": MagHardIron.name, "target": target,
         "params": {"offset_ut": [float(v) for v in c_new]},
         "sigma": {"offset_ut": [float(v) for v in sig_c]}, "note": note},
        {"effect": MagSoftIron.name, "target": target,
         "params": {"matrix_error": [float(v) for v in e_new]},
         "sigma": {"matrix_error": [float(v) for v in sig_e]}, "note": note},
    ]

