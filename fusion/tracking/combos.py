"""What gravity reads together where it cannot read single joints (:class:`JointTiltCombinations`):
the combinations of the joints and the base's roll and pitch that the filter knows well, from
the joint and tilt block of its covariance with the calibration's own share, found again when
the joints' flags change and every ``observability_window_s``, their values and sigmas now in
between."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from armfusion.fusion.startup.combinations import Combination, observable_combinations
from armfusion.fusion.startup.solve import TILT_NAMES
from armfusion.fusion.tracking.observability import Observability
from armfusion.fusion.tracking.settings import (
    F_AMBIGUOUS,
    F_GIMBAL,
    F_UNOBSERVED,
    StateLayout,
    TrackerSettings,
)
from armfusion.fusion.tracking.ukf import BatchedUKF
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG


class JointTiltCombinations:
    """The combinations of a tracker's joints and tilt, with the last found kept."""

    def __init__(self, arm: ArmModel, layout: StateLayout, settings: TrackerSettings,
                 observability: Observability):
        self.arm, self.layout, self.settings, self.observability = arm, layout, settings, observability
        self.found = (None, -np.inf, (), None, None)
        """(the flags, the time, the combinations, their coefficients, the state indices) as
        last found."""

    def vectors(self, ukf: BatchedUKF, q_enc: np.ndarray, flags: np.ndarray,
                ) -> tuple[tuple[Combination, ...], np.ndarray, np.ndarray]:
        """What gravity reads where it cannot read single joints, now: the combinations of
        the joints not ``ok`` (nor ``ambiguous``, nor flagged as read by no sensor:
        ``gimbal_lock``, ``unobserved``) and of the base's roll and pitch (where
        their sigma is above ``sigma_limit_deg``) that the filter knows within
        ``mean_state_held_sigma_deg`` and better than any of their terms
        (:func:`armfusion.fusion.startup.combinations.observable_combinations`), from the joint and
        tilt block of its covariance with the calibration's own share (the consider
        sensitivity and an unread joint's cover: what the reported sigmas hold). Returns the
        combinations, their coefficients ``(k, n + 2)`` over the joints, roll and pitch,
        and the state indices of those ``(n + 2,)``."""
        L, n, st = self.layout, self.arm.n_joints, self.settings
        ix = np.r_[np.arange(n), L.roll, L.pitch]
        values, P = self.block(ukf, q_enc, ix)
        cand = np.r_[(flags != 0) & (flags != F_AMBIGUOUS) & (flags != F_GIMBAL) & (flags != F_UNOBSERVED),
                     np.sqrt(np.clip(np.diag(P)[n:], 0.0, None)) > st.sigma_limit_deg * DEG]
        names = (*self.arm.joint_names, *TILT_NAMES)
        found = observable_combinations(P, values, names, st.mean_state_held_sigma_deg * DEG, cand)
        C = np.array([c.vector(names) for c in found]).reshape(len(found), n + 2)
        return found, C, ix

    def block(self, ukf: BatchedUKF, q_enc: np.ndarray, ix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joints' angles (as reported), roll and pitch, and their covariance with the
        calibration's own share (see :meth:`vectors`)."""
        n, L = self.arm.n_joints, self.layout
        P = ukf.covariance[np.ix_(ix, ix)].copy()
        obs = self.observability
        P[:n, :n] += obs.consider @ obs.consider.T + np.diag(obs.unread_var)
        P[n, n] += obs.tilt_var[0]  # (the accelerometers' floor in the tilt)
        P[n + 1, n + 1] += obs.tilt_var[1]
        x = ukf.x
        values = np.r_[self.arm.angles_in_range(q_enc + x[:n], q_enc), x[L.roll], x[L.pitch]]
        return values, P

    def values(self, ukf: BatchedUKF, q_enc: np.ndarray, C: np.ndarray,
               ix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The combinations of coefficients ``C`` (from :meth:`vectors`) now: their values
        and sigmas (rad)."""
        values, P = self.block(ukf, q_enc, ix)
        return C @ values, np.sqrt(np.clip(np.einsum("ki,ij,kj->k", C, P, C), 0.0, None))

    def now(self, ukf: BatchedUKF, q_enc: np.ndarray, flags: np.ndarray, t: float) -> tuple[Combination, ...]:
        """:meth:`vectors`' combinations at ``t``: which ones, found again when the flags
        change (``flags`` is replaced, never written into, when they do) and every
        ``observability_window_s``; their values and sigmas now (an estimate a sample
        carries no eigen-decomposition)."""
        last_flags, t_found, found, C, ix = self.found
        if flags is not last_flags or t - t_found >= self.settings.observability_window_s:
            found, C, ix = self.vectors(ukf, q_enc, flags)
            self.found = (flags, t, found, C, ix)
            return found
        if not found:
            return ()
        v, sg = self.values(ukf, q_enc, C, ix)
        return tuple(replace(c, angle_rad=float(a), sigma_rad=float(b))
                     for c, a, b in zip(found, v, sg, strict=True))
