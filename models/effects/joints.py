"""The joints' errors: a zero off, the link and gearbox sagging under gravity, gearbox
play, and an encoder's counts per revolution off.
"""

from __future__ import annotations

import numpy as np
from armfusion.models.effects.base import JointEffect, SensorEffect
from armfusion.models.effects.shapes import diag_batch
from armfusion.models.rotations import DEG


class JointOffset(JointEffect):
    name = "joint_offset"
    rank = 10
    key = "offset_rad"
    shape = (1,)
    units = "rad"
    labels = ("offset",)
    bound = 0.35
    summary = "joint's zero not where the config puts it"
    description = (
        "The joint's real zero is a little off the zero in the arm's description (an "
        "encoder index or a part assembled a tooth off): the link really stands at the "
        "controller's angle plus this offset.")
    seen_in = "encoder index / assembly error, about a degree"

    def default_sigma(self):
        return np.array([1.0 * DEG])

    def delta(self, q, theta, ctx):
        return np.full(q.shape[0], theta[0])

    def delta_jac_params(self, q, theta, ctx):
        return np.ones((q.shape[0], 1))


class LinkCompliance(JointEffect):
    name = "link_compliance"
    rank = 20
    key = "compliance_rad_per_nm"
    shape = (1,)
    units = "rad/(N·m)"
    labels = ("compliance",)
    bound = 5e-3
    nonnegative = True
    summary = "link and gearbox sag under gravity"
    description = (
        "The gearbox and the link are not perfectly stiff: gravity's pull on everything "
        "beyond the joint bends it a little, more when the arm is stretched out "
        "horizontally than when it hangs down. The joint really stands at the controller's "
        "angle plus compliance times the gravity torque (from a nominal mass model).")
    seen_in = "harmonic drives and long aluminium links: tenths of a degree at full reach"

    def default_sigma(self):
        return np.array([2e-4])

    def delta(self, q, theta, ctx):
        return theta[0] * ctx.gravity_torque()[:, self.j]

    def delta_jac_params(self, q, theta, ctx):
        return ctx.gravity_torque()[:, self.j, None]

    def delta_jac_q(self, q, theta, ctx):
        return theta[0] * ctx.gravity_torque_jacobian()[:, self.j, :]


class Backlash(JointEffect):
    name = "backlash"
    rank = 30
    key = "play_rad"
    shape = (1,)
    units = "rad"
    labels = ("play",)
    bound = 0.05
    nonnegative = True
    TORQUE_SCALE_NM = 1.0
    summary = "gearbox play, taken up by gravity"
    description = (
        "The gears have a little play. Gravity pushes the link against one side of it, so "
        "the link sits half the play away from where the motor's encoder says, on the side "
        "gravity pulls; where the gravity torque is near zero (the joint's load balanced) it "
        "floats in the middle. Modelled as play/2 · tanh(torque / 1 N·m).")
    seen_in = "gearbox backlash, about 0.1°"

    def default_sigma(self):
        return np.array([0.1 * DEG])

    def delta(self, q, theta, ctx):
        return 0.5 * theta[0] * np.tanh(ctx.gravity_torque()[:, self.j] / self.TORQUE_SCALE_NM)

    def delta_jac_params(self, q, theta, ctx):
        return 0.5 * np.tanh(ctx.gravity_torque()[:, self.j, None] / self.TORQUE_SCALE_NM)

    def delta_jac_q(self, q, theta, ctx):
        u = ctx.gravity_torque()[:, self.j] / self.TORQUE_SCALE_NM
        sech2 = 1.0 / np.cosh(u) ** 2
        return (0.5 * theta[0] * sech2 / self.TORQUE_SCALE_NM)[:, None] * \
            ctx.gravity_torque_jacobian()[:, self.j, :]


class EncoderScale(SensorEffect):
    input_is_diagonal = True
    name = "encoder_scale"
    rank = 30
    key = "scale_error"
    shape = (1,)
    units = "1 (fraction)"
    labels = ("scale",)
    bound = 0.1
    target_kind = "geared_joint"
    summary = "encoder counts per joint revolution off"
    description = (
        "The joint's encoder gives a few more (or fewer) counts per joint revolution than "
        "the config says (a wrong gear ratio, a slipping belt): angles measured from "
        "power-up grow too fast by this fraction.")
    seen_in = "wrong gear ratio or counts per rev"

    def __init__(self, arm, target=None):
        super().__init__(arm, target)
        self.j = arm.joint_names.index(self.target)

    @property
    def streams(self):
        return ("enc",)

    def default_sigma(self):
        return np.array([1e-3])

    def apply(self, y, theta, ctx, stream):
        out = np.array(y, dtype=float, copy=True)
        out[:, self.j] *= 1.0 + theta[0]
        return out

    def jac_params(self, y, theta, ctx, stream):
        J = np.zeros(y.shape + (1,))
        J[:, self.j, 0] = y[:, self.j]
        return J

    def jac_input(self, y, theta, ctx, stream):
        d = np.ones(y.shape)
        d[:, self.j] = 1.0 + theta[0]
        return diag_batch(d)
