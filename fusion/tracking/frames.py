"""The kinematic frame of an instant: the mean pose's sensor rotations, joint axes and
motion accelerations, which the filter's measurement model turns into every sigma
point's prediction by the product of exponentials (see docs/tracking.md).

:class:`Frames` is the record (K instants, or one). The filter makes one per fused instant
with the compiled :class:`armfusion.fusion.tracking.frame_kernels.FrameConstants`, live and over a
recording alike; :func:`make_frames` is the same frame from the models' batched functions
(:func:`armfusion.models.motion.link_motion`, :func:`armfusion.models.motion.sensor_motion`), the reference
the compiled frame is held to and the benchmark baseline's frames.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.settings import G
from armfusion.models.arm import ArmModel
from armfusion.models.motion import MotionState, link_motion, sensor_motion
from armfusion.models.rotations import skew


class _FrameFields(NamedTuple):
    q_ref: np.ndarray
    offset_ref: np.ndarray
    R_0S: np.ndarray
    motion_mps2: np.ndarray
    axes: np.ndarray
    p_0S_m: np.ndarray
    omega_dot_B: np.ndarray
    K: np.ndarray
    motion_g: np.ndarray
    dist2_m2: np.ndarray
    omega_dot_norm: np.ndarray
    accel_var_g2: np.ndarray | None = None
    omega_S_rad_s: np.ndarray | None = None


class Frames(_FrameFields):
    """The kinematics at the reference poses of K instants (batched).

    ``q_ref (K, n)`` the reference joint angles (encoder angles plus the offsets the frame
    was made with, ``offset_ref (K, n)``); ``R_0S (K, S, 3, 3)`` and ``motion_mps2 (K, S, 3)``
    (each sensor's acceleration from the joints' motion and the base's rotation, base
    axes, without gravity or the base's own linear acceleration) for the accelerometers
    (link accelerometers then the IMU); ``axes (K, n, 3)`` the joint axes in base axes.
    ``K (., n, 3, 3)``: the axes' skew matrices; ``motion_g (., S)``:
    |motion| in g; ``dist2_m2 (., S)``: each sensor's squared distance from the base origin;
    ``accel_var_g2 (., S, 3)``: the accelerometers' measurement variances at these
    instants, when a tracker has added them; ``omega_S_rad_s (., S, 3)``: each
    accelerometer's angular velocity in its own axes. Read-only (a named tuple).
    """

    __slots__ = ()
    FIELDS = _FrameFields._fields

    @classmethod
    def of(cls, fields) -> Frames:
        """The record of ``fields`` in :attr:`FIELDS` order (all of them, as
        :meth:`armfusion.fusion.tracking.frame_kernels.FrameConstants.fields` gives them: no
        per-field checks, the cheapest construction)."""
        return tuple.__new__(cls, fields)

    def take(self, k: int) -> Frames:
        """The frame of instant ``k`` (a plain read-only record; one per fused instant)."""
        return tuple.__new__(Frames, [None if a is None else a[k] for a in self])

    def split(self) -> list[Frames]:
        """Every instant's frame, in order: ``[self.take(k) for k in range(K)]`` at half the
        cost (a run takes a block's frames apart this way)."""
        K = len(self.q_ref)
        cols = [[None] * K if a is None else list(a) for a in self]
        new = tuple.__new__
        return [new(Frames, f) for f in zip(*cols, strict=True)]


class JointMotion(NamedTuple):
    """The joints at K instants, as the encoders' causal fit gives them."""

    q_enc_rad: np.ndarray
    """The encoders' angles ``(K, n)``."""
    qd_rad_s: np.ndarray
    """Their rates ``(K, n)``."""
    qdd_rad_s2: np.ndarray
    """Their accelerations ``(K, n)``."""


class BaseTurn(NamedTuple):
    """The base's turn at K instants, base axes."""

    omega_rad_s: np.ndarray
    """Its rate ``(K, 3)``."""
    omega_dot_rad_s2: np.ndarray
    """Its rate's change ``(K, 3)``."""


def make_frames(arm: ArmModel, names: tuple[str, ...], joints: JointMotion, offset: np.ndarray,
                base: BaseTurn, motion: bool = True, joint_effects=()) -> Frames:
    """Kinematic frames for K instants: the ``joints``' encoder angles, rates and
    accelerations, the offsets ``offset (n,)`` or ``(K, n)``, the ``base``'s turn. ``motion``
    False: as if nothing moved (no motion compensation). ``joint_effects`` (effect,
    parameters) pairs turn the controller's angles into the geometric ones. The base origin
    turns about the chair's turning centre where the arm states one
    (:attr:`armfusion.models.arm.ArmModel.base_from_turning_centre_m`, ``ρ``): its acceleration
    ``ω̇ x ρ + ω x (ω x ρ)`` is in every sensor's motion, and ``dist2_m2`` is measured from there."""
    q_enc, qd, qdd = joints
    omega_B, omega_dot_B = base
    q = q_enc + offset
    K = q.shape[0]
    if not motion:
        qd = qdd = np.zeros_like(q)
        omega_B = omega_dot_B = np.zeros((K, 3))
    eye = np.broadcast_to(np.eye(3), (K, 3, 3))
    lever = arm.base_from_turning_centre_m
    rho = np.zeros(3) if lever is None else np.asarray(lever, float)
    w_B, wd_B = np.asarray(omega_B, float), np.asarray(omega_dot_B, float)
    a_B = np.cross(wd_B, rho) + np.cross(w_B, np.cross(w_B, rho))
    st = MotionState(np.zeros(K), q, qd, qdd, eye, omega_B, omega_dot_B, a_B, 25.0)
    if joint_effects:
        from armfusion.models.effects import Context

        ctx = Context(arm, st)
        qg = np.array(q, dtype=float, copy=True)
        for e, th in joint_effects:
            qg[:, e.j] += e.delta(q, th, ctx)
        st = st.replace(q_rad=qg)
    lm = link_motion(arm, st)
    sm = sensor_motion(arm, st, list(names), lm=lm)
    Ks = skew(lm.axis_0)
    wd = np.asarray(omega_dot_B, float)
    return Frames(q, np.broadcast_to(offset, q.shape), sm.R_0S, sm.acc_0_mps2, lm.axis_0, sm.p_0S_m,
                  wd, Ks, np.linalg.norm(sm.acc_0_mps2, axis=-1) / G,
                  np.sum((sm.p_0S_m + rho) ** 2, axis=-1), np.linalg.norm(wd, axis=-1),
                  omega_S_rad_s=sm.omega_S_rad_s)

