"""The correction of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`'s state by an innovation
``nu`` with covariance ``S`` and cross covariance ``Pxz``, through the compiled kernel
(:func:`armfusion.fusion.tracking.ukf_kernels.kalman_update_into`): the gain (held by
``hold``, masked by ``gain_mask``), the covariance by the optimal form when the gain is,
else by the general (Joseph-equivalent) one, the angle states wrapped, ``P`` repaired if
round-off made a variance not positive."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.ukf_kernels import DIAGONAL_NOT_POSITIVE, kalman_update_into
from armfusion.fusion.tracking.unscented import repair_covariance

_NONE_2D = np.zeros((0, 0))  # "no hold / no gain mask" for the compiled update


def correct(x: np.ndarray, P: np.ndarray, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray,
            hold: np.ndarray | None, gain_mask: np.ndarray | None,
            angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The corrected ``(x, P)`` (``angles (int64)``: the angle states' indices); ``hold``
    ``(n, n)`` and ``gain_mask (n, m)`` or None."""
    n, m = Pxz.shape
    hold_c = _NONE_2D if hold is None else np.ascontiguousarray(hold, dtype=np.float64)
    mask_c = _NONE_2D if gain_mask is None else np.ascontiguousarray(gain_mask, dtype=np.float64)
    if not (nu.shape == (m,) and S.shape == (m, m) and n == x.shape[0]):
        raise ValueError(f"correct: an innovation of {nu.shape}, S {S.shape} and Pxz {Pxz.shape} "
                         f"do not fit a state of size {x.shape[0]}")
    if hold is not None and hold_c.shape != (n, n):
        raise ValueError(f"hold must be ({n}, {n}), got {hold_c.shape}")
    if gain_mask is not None and mask_c.shape != (n, m):
        raise ValueError(f"gain_mask must be ({n}, {m}), got {mask_c.shape}")
    x_new, P_new = np.empty(n), np.empty((n, n))
    status = kalman_update_into(x, P, np.ascontiguousarray(nu, dtype=np.float64),
                                np.ascontiguousarray(S, dtype=np.float64),
                                np.ascontiguousarray(Pxz, dtype=np.float64), hold_c, mask_c,
                                angles, x_new, P_new)
    if status == DIAGONAL_NOT_POSITIVE:
        P_new = repair_covariance(P_new, 1e-18)
    return x_new, P_new
