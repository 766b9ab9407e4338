"""The gravity chain's compiled core: world-up carried from the base through every joint,
with its derivatives, written once.

Only rotations matter to what a still accelerometer reads. With the constant frame changes
of :class:`armfusion.models.kinematics.GravityChain` (``C_i``: the previous joint's axis frame to
joint i's, before its turn; its axis is z there), going through joint i is ``v <- Rz(q_i +
offset_i)^T C_i v``, and turning joint i changes ``v`` by ``v x z = [v_y, -v_x, 0]``. Every
later step is linear in ``v``, so derivative columns are carried by the same steps as ``v``.

A state's columns ``V (3, n + E)``: ``[up, d/dq_0 .. d/dq_{n-1}, d/d outer_1 ..
d/d outer_{E-1}]`` (the outer parameters move up itself: the base roll and pitch in the
startup solve). :func:`seed_up_and_tilt` starts it from the base tilt, :func:`turn_joint`
carries it through one joint, and :func:`propagate` runs every joint for a batch of poses.

Called by :class:`armfusion.models.kinematics.GravityChain` (batched, for NumPy callers) and by the
startup solve's compiled Levenberg-Marquardt (:mod:`armfusion.fusion.startup.kernels`), so the two
are one arithmetic. Compiled once per machine and cached next to this file.
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.models.rotations import up_and_tilt_derivatives_into
from numba import njit

# armfusion.models.rotations.up_and_tilt_derivatives_into compiled: the one definition of up's tilt
# Jacobian, for NumPy and compiled callers alike
_up_and_tilt_into = njit(cache=True, nogil=True)(up_and_tilt_derivatives_into)


@njit(cache=True, nogil=True)
def seed_up_and_tilt(roll_rad, pitch_rad, V):  # pragma: no cover - compiled
    """``V (3, n + 3)`` before the first joint, for a base at (roll, pitch): column 0 up
    (:func:`armfusion.models.rotations.up_from_tilt`), the last two its derivatives by roll and by
    pitch, every other column zero."""
    w = V.shape[1]
    for a in range(3):
        for j in range(w):
            V[a, j] = 0.0
    _up_and_tilt_into(roll_rad, pitch_rad, V, 0, w - 2, w - 1)


@njit(cache=True, nogil=True)
def turn_joint(V, C, theta_rad, i, n):  # pragma: no cover - compiled
    """Carry ``V (3, n + E)`` through joint ``i`` of ``n`` in place: ``V <- Rz(theta)^T C
    V`` (``C``: the joint's ``step_in``; ``theta``: its angle plus offset), then its own
    column ``1 + i`` set to ``v x z``. The columns of later joints are zero and left as
    they are."""
    w = V.shape[1]
    k = i + 1
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    # Rz^T C: rows c C0 + s C1, -s C0 + c C1, C2
    s00 = c * C[0, 0] + s * C[1, 0]
    s01 = c * C[0, 1] + s * C[1, 1]
    s02 = c * C[0, 2] + s * C[1, 2]
    s10 = c * C[1, 0] - s * C[0, 0]
    s11 = c * C[1, 1] - s * C[0, 1]
    s12 = c * C[1, 2] - s * C[0, 2]
    s20, s21, s22 = C[2, 0], C[2, 1], C[2, 2]
    for j in range(w):
        if j > k and j <= n:  # a later joint's column: still zero
            continue
        v0, v1, v2 = V[0, j], V[1, j], V[2, j]
        V[0, j] = s00 * v0 + s01 * v1 + s02 * v2
        V[1, j] = s10 * v0 + s11 * v1 + s12 * v2
        V[2, j] = s20 * v0 + s21 * v1 + s22 * v2
    V[0, k] = V[1, 0]  # d v / d q_i = v x z
    V[1, k] = -V[0, 0]
    V[2, k] = 0.0


@njit(cache=True, nogil=True)
def propagate(Q, seed, step_in, offset, last):  # pragma: no cover - compiled
    """Every pose ``Q (N, n)`` from ``seed (N, 3, E)`` (up in the base frame, then its
    derivatives by E - 1 outer parameters) through joints 0..``last``: ``V`` before joint
    0 and after each, ``(last + 2, N, 3, n + E)``."""
    N, n = Q.shape
    E = seed.shape[2]
    w = n + E
    out = np.zeros((last + 2, N, 3, w))
    V = np.zeros((3, w))
    for b in range(N):
        for a in range(3):
            for j in range(w):
                V[a, j] = 0.0
            V[a, 0] = seed[b, a, 0]
            for e in range(1, E):
                V[a, n + e] = seed[b, a, e]
        out[0, b] = V
        for i in range(last + 1):
            turn_joint(V, step_in[i], Q[b, i] + offset[i], i, n)
            out[i + 1, b] = V
    return out
