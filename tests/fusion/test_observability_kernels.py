"""The offsets' observability compiled in :mod:`armfusion.fusion.tracking.observability_kernels` says
what the equations say: which axes are gimbal-locked, how much the link accelerometers read
each offset, and which directions the filter must hold (its gain zero along them). A wrong
held span lets a gimbal-locked joint wander on noise, or freezes one gravity reads; a wrong
achievable sigma flags a joint ill-conditioned that is not, or misses one that is."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.tracking.observability_kernels import offsets_observability
from armfusion.models.rotations import DEG


def _skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _random_rotation(rng):
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def _case(rng, n=7, S=4, vertical=()):
    axes = rng.normal(size=(n, 3))
    for j in vertical:  # this axis is (nearly) along gravity
        axes[j] = [0.0, 0.0, 1.0] + rng.normal(0.0, 1e-3, 3)
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    K = np.array([_skew(a) for a in axes])
    R_0S = np.array([_random_rotation(rng) for _ in range(S)])
    motion = rng.normal(0.0, 0.5, (S, 3))
    base = np.array([0.1, -0.2, 9.81])
    A = rng.normal(size=(n, n))
    P = (A @ A.T) * (2 * DEG) ** 2 + np.eye(n) * (0.1 * DEG) ** 2
    return axes, K, R_0S, motion, base, P


def _numpy_form(axes, up, lock_deg, motion, base, K, R_0S, sel, coef, P, weak_info, wide_var, blind):
    """The same quantities as NumPy writes them (the form the kernel replaced)."""
    n = axes.shape[0]
    axis_deg = np.degrees(np.arccos(np.minimum(np.abs(axes @ up), 1.0)))
    locked = (axis_deg < lock_deg) | blind
    v = motion[sel] + base
    Kv = (K.reshape(3 * n, 3) @ v.T).reshape(n, 3, -1).transpose(2, 1, 0)
    W = ((R_0S[sel].transpose(0, 2, 1) @ Kv) * coef).reshape(-1, n)
    lam, V = np.linalg.eigh(W.T @ W)
    readable = lam > 1e-12 * max(lam[-1], 0.0)
    achievable = np.sqrt((V[:, readable] ** 2) @ (1.0 / lam[readable]))
    achievable[((V[:, ~readable] ** 2) > 1e-12).any(axis=1)] = np.inf
    weak = lam < weak_info
    weak &= lam * (V * (P @ V)).sum(axis=0) < 1.0
    B = np.concatenate([V[:, weak], np.eye(n)[:, locked]], axis=1)
    held = np.zeros((n, n))
    if B.shape[1]:
        w, U = np.linalg.eigh(B @ B.T)
        held = U[:, w > 1e-6] @ U[:, w > 1e-6].T
    wide = locked & (np.diag(P) > wide_var)
    return axis_deg, locked, W, achievable, held, wide


@pytest.mark.parametrize("vertical, sel, blind", [((), [0, 1, 2, 3], ()), ((0,), [0, 1, 2, 3], ()),
                                                  ((), [3], ()), ((0, 2), [2, 3], ()), ((0,), [], ()),
                                                  ((0,), [0, 1, 2, 3], (4,)), ((), [1, 2], (1, 5))])
def test_the_compiled_observability_says_what_the_equations_say(vertical, sel, blind):
    """(``blind``: joints another test found gravity-blind, whatever their axis says: locked
    and held as a vertical axis is.)"""
    rng = np.random.default_rng(11 + len(sel) + 10 * len(vertical))
    n, S = 7, 4
    axes, K, R_0S, motion, base, P = _case(rng, n, S, vertical)
    sel = np.array(sel, dtype=np.int64)
    coef = rng.uniform(50.0, 500.0, (len(sel), 3, n)) * (rng.uniform(size=(len(sel), 1, n)) > 0.3)
    up = np.array([0.0, 0.0, 1.0])
    weak_info, wide_var = 1.0 / (2.0 * DEG) ** 2, (3.0 * DEG) ** 2
    axis_deg, locked = np.empty(n), np.empty(n, np.bool_)
    wide, achievable = np.empty(n, np.bool_), np.empty(n)
    blind_mask = np.zeros(n, np.bool_)
    blind_mask[list(blind)] = True
    W, U = offsets_observability(axes, up, 1.0, motion, base, K, R_0S, sel, coef, P, weak_info, wide_var,
                                 blind_mask, axis_deg, locked, wide, achievable)
    ref = _numpy_form(axes, up, 1.0, motion, base, K, R_0S, sel, coef, P, weak_info, wide_var, blind_mask)
    np.testing.assert_allclose(axis_deg, ref[0], rtol=0, atol=1e-9)
    assert np.array_equal(locked, ref[1])
    assert locked[list(vertical) + list(blind)].all() and locked.sum() == len(set(vertical) | set(blind))
    np.testing.assert_allclose(W, ref[2], rtol=1e-12, atol=1e-9)
    finite = np.isfinite(ref[3])
    assert np.array_equal(np.isfinite(achievable), finite)
    np.testing.assert_allclose(achievable[finite], ref[3][finite], rtol=1e-7)
    np.testing.assert_allclose(U @ U.T, ref[4], atol=1e-9)  # the same held span
    np.testing.assert_allclose(U.T @ U, np.eye(U.shape[1]), atol=1e-9)  # orthonormal
    assert np.array_equal(wide, ref[5])
    if not len(sel):  # nothing read: every direction held, no sigma achievable
        assert U.shape[1] == n and not np.isfinite(achievable).any()
