"""The correction of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`'s state by an innovation
``nu`` with covariance ``S`` and cross covariance ``Pxz``: the gain (held by ``hold``, masked
by ``gain_mask``), the covariance by the optimal form when the gain is, else by the general
(Joseph-equivalent) one, the angle states wrapped, ``P`` repaired if round-off made a
variance not positive. Through the compiled kernel in the common case
(:func:`correct_compiled`), else in NumPy (:func:`correct_numpy`), which takes any gain,
any angles and an ``S`` that is not positive definite."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.ukf_kernels import (
    DIAGONAL_NOT_POSITIVE,
    NOT_POSITIVE_DEFINITE,
    kalman_update_into,
)
from armfusion.fusion.tracking.unscented import repair_covariance
from armfusion.models.rotations import wrap_angle
from scipy.linalg import lapack

_NONE_2D = np.zeros((0, 0))  # "no hold / no gain mask" for the compiled update


def correct_compiled(x: np.ndarray, P: np.ndarray, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray,
                     hold: np.ndarray | None, gain_mask: np.ndarray | None,
                     angle_index: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The corrected ``(x, P)`` through the compiled kernel (``angle_index``: the one angle
    state, -1 for none); None, with nothing done, when ``S`` is not positive definite or a
    shape is not the common case's (``hold (n, n)``, ``gain_mask (n, m)``)."""
    n, m = Pxz.shape
    hold_c = _NONE_2D if hold is None else np.ascontiguousarray(hold, dtype=np.float64)
    mask_c = _NONE_2D if gain_mask is None else np.ascontiguousarray(gain_mask, dtype=np.float64)
    if not (m > 0 and nu.shape == (m,) and S.shape == (m, m) and n == x.shape[0]
            and (hold is None or hold_c.shape == (n, n))
            and (gain_mask is None or mask_c.shape == (n, m))):
        return None
    x_new, P_new = np.empty(n), np.empty((n, n))
    status = kalman_update_into(x, P, np.ascontiguousarray(nu, dtype=np.float64),
                                np.ascontiguousarray(S, dtype=np.float64),
                                np.ascontiguousarray(Pxz, dtype=np.float64), hold_c, mask_c,
                                angle_index, x_new, P_new)
    if status == NOT_POSITIVE_DEFINITE:
        return None
    if status == DIAGONAL_NOT_POSITIVE:
        P_new = repair_covariance(P_new, 1e-18)
    return x_new, P_new


def correct_numpy(x: np.ndarray, P: np.ndarray, nu: np.ndarray, S: np.ndarray, Pxz: np.ndarray,
                  hold: np.ndarray | None, gain_mask: np.ndarray | None,
                  angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The corrected ``(x, P)`` in NumPy (``angles``: the angle states' indices)."""
    _, Kt, info = lapack.dposv(S, Pxz.T)  # S is symmetric positive definite
    if info != 0:
        Kt = np.linalg.lstsq(S, Pxz.T, rcond=None)[0]
    K = Kt.T
    if hold is None and gain_mask is None:
        # the optimal gain: P - K S K^T = P - K Pxz^T
        P_new = P - K @ Pxz.T
    else:
        # a held gain is not optimal: the general (Joseph-equivalent) form stays exact
        if hold is not None:
            K = hold @ K
        if gain_mask is not None:
            K = K * gain_mask
        # P - K Pxz^T - Pxz K^T + K S K^T = P + B + B^T with B = (K S / 2 - Pxz) K^T:
        # exactly symmetric as it is summed
        B = K @ S
        B *= 0.5
        B -= Pxz
        B = B @ K.T
        B += B.T
        P_new = P + B
    x_new = x + K @ nu
    if len(angles) == 1:
        a = int(angles[0])
        x_new[a] = wrap_angle(float(x_new[a]))
    elif len(angles):
        x_new[angles] = wrap_angle(x_new[angles])
    if hold is None and gain_mask is None:
        P_new += P_new.T
        P_new *= 0.5
    if not P_new.diagonal().min() > 0.0:  # (NaN too)
        P_new = repair_covariance(P_new, 1e-18)
    return x_new, P_new
