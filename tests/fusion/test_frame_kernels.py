"""The live path's compiled kinematic frame and causal fits equal their batch forms.

:func:`armfusion.fusion.tracking.frame_kernels.frame_one` (through :class:`FrameConstants`) against
:func:`armfusion.fusion.tracking.tracker.make_frames` for one instant, field by field and to the bit
(both call the compiled equations of :mod:`armfusion.models.chain_kernels`), at seeded random
states: motion on and off, a calibrated config's joint effects, and joint axes that are
not z (the chain's general path). The compiled differentiator against
:func:`armfusion.fusion.tracking.tracker.causal_poly_fit`. Then the tracker's live path
(:meth:`Tracker.update_instant`, the one filter path) with both compiled against the same
tracker given the NumPy frame and the NumPy differentiator, instant by instant.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.tracking.frame_kernels import FrameConstants, extrapolate_fit, poly_fit_one, push_fit
from armfusion.fusion.tracking.tracker import (
    BaseTurn,
    CausalDifferentiator,
    Frames,
    JointMotion,
    Tracker,
    causal_poly_fit,
    make_frames,
    start_from_recording,
)
from armfusion.models.simulator import simulate
from armfusion.models.trajectories import DrivingChair, Scenario, StepsBuilder, WaypointPath

POSE = np.radians([45.0, 60.0, 30.0, -50.0, 40.0, 30.0, 20.0])
JOINT_EFFECTS = ("joint_offset", "link_compliance", "backlash")


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


@pytest.fixture(scope="module")
def effects(arm):
    """A realistic draw of every joint effect (zero offsets, sag, play) on every joint."""
    _, truth = simulate(arm, "startup", 1.0, seed=11, realistic=True)
    return tuple(e for e in truth["effects"] if e["effect"] in JOINT_EFFECTS)


def random_states(arm, rng, count):
    """Encoder fits ``(3, n)`` (angles within the limits, rates, accelerations), offsets,
    base rates and accelerations: brisker than the arm moves, so every term counts."""
    for _ in range(count):
        fit = np.stack([rng.uniform(arm.min_rad, arm.max_rad), rng.normal(0, 1.0, arm.n_joints),
                        rng.normal(0, 3.0, arm.n_joints)])
        yield fit, rng.normal(0, 0.1, arm.n_joints), rng.normal(0, 0.5, 3), rng.normal(0, 2.0, 3)


def assert_frames_equal(got: tuple, ref: Frames) -> None:
    """Every field the same number: the live frame and make_frames run the same compiled
    equations (armfusion.models.chain_kernels), so not even round-off may differ."""
    assert len(got) == len(Frames.FIELDS)
    for name, a, b in zip(Frames.FIELDS, got, ref, strict=True):
        if b is None:
            assert a is None, name
            continue
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape, (name, a.shape, b.shape)
        np.testing.assert_array_equal(a, b, err_msg=name)


def check_against_make_frames(tr: Tracker, rng, motion: bool, count: int = 25) -> None:
    fc = FrameConstants(tr.arm, tr.accel_names, tr._joint_effects)
    for fit, offset, w, wd in random_states(tr.arm, rng, count):
        ref = make_frames(tr.arm, tr.accel_names, JointMotion(fit[0][None], fit[1][None], fit[2][None]),
                          offset[None], BaseTurn(w[None], wd[None]), motion, tr._joint_effects).take(0)
        assert_frames_equal(fc.fields(fit, offset, w, wd, motion), ref)


# --------------------------------------------------------------------------------------
# the frame
@pytest.mark.parametrize("motion", [True, False])
def test_the_compiled_frame_equals_make_frames(arm, motion):
    tr = Tracker(arm)
    assert not tr._joint_effects
    check_against_make_frames(tr, np.random.default_rng(101), motion)


def test_no_gyro_yet_is_a_base_at_rest(arm):
    """``omega_B``/``omega_dot_B`` None (no gyro sample yet) is the base not turning."""
    tr = Tracker(arm)
    fc = FrameConstants(tr.arm, tr.accel_names)
    fit, offset, _, _ = next(random_states(arm, np.random.default_rng(102), 1))
    z = np.zeros((1, 3))
    ref = make_frames(arm, tr.accel_names, JointMotion(fit[0][None], fit[1][None], fit[2][None]),
                      offset[None], BaseTurn(z, z)).take(0)
    assert_frames_equal(fc.fields(fit, offset, None, None), ref)


@pytest.mark.parametrize("motion", [True, False])
def test_the_compiled_frame_applies_a_calibrated_config_s_joint_effects(arm, effects, motion):
    """Zero offsets (added in the kernel), sag and play (their gravity torques in NumPy, as
    make_frames evaluates them): several effects on every joint, in the config's order."""
    tr = Tracker(replace(arm, effects=effects))
    kinds = {type(e).__name__ for e, _ in tr._joint_effects}
    assert kinds == {"JointOffset", "LinkCompliance", "Backlash"}
    check_against_make_frames(tr, np.random.default_rng(103), motion)


def test_the_compiled_frame_turns_about_axes_that_are_not_z(arm):
    """Joint axes tilted off z: the chain's Rodrigues path (armfusion.models.chain_kernels.pose_one)."""
    rng = np.random.default_rng(104)
    axes = [np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.3, 3) for _ in arm.joints]
    tilted = replace(arm, joints=tuple(replace(j, axis=a / np.linalg.norm(a))
                                       for j, a in zip(arm.joints, axes, strict=True)))
    assert not tilted.chain.axis_is_z
    check_against_make_frames(Tracker(tilted), rng, True)


@pytest.mark.parametrize("motion", [True, False])
def test_a_block_s_frames_are_each_instant_s_frame(arm, effects, motion):
    """A run makes a block's frames in one call (FrameConstants.fields_block, then the noise
    for the block, then Frames.split): each instant's is the one-instant frame to the bit, joint effects and
    measurement variances included; an instant without a frame is left zero."""
    tr = Tracker(replace(arm, effects=effects))
    rng = np.random.default_rng(108)
    states = list(random_states(arm, rng, 12))
    fit = np.stack([s[0] for s in states])
    offset = states[0][1]
    w, wd = np.stack([s[2] for s in states]), np.stack([s[3] for s in states])
    have = np.ones(len(states), dtype=bool)
    have[[0, 5]] = False
    fc = tr.frame_constants
    noise = tr.measurements.with_noise
    block = noise(Frames.of(fc.fields_block(fit, have, offset, w, wd, motion)))
    split = block.split()
    assert len(split) == len(states)
    for b in range(len(states)):
        got = split[b]
        assert_frames_equal(got, block.take(b))
        if not have[b]:
            assert not np.any(got.R_0S) and not np.any(got.q_ref)
            continue
        one = noise(Frames.of(fc.fields(fit[b], offset, w[b], wd[b], motion)))
        assert_frames_equal(got, one)


def test_one_instant_s_noise_is_a_block_s_to_the_bit(arm):
    """The measurement variances of one instant's frame (scalar |omega_dot|, live) and of a
    block's (an array of them, a run) are the same numbers: the squares are products, not
    a scalar's pow, which differs in the last bit for about one value in 1,500."""
    tr = Tracker(arm)
    rng = np.random.default_rng(110)
    B, S = 3000, len(tr.accel_names)
    fields = dict.fromkeys(Frames.FIELDS)
    fields.update(motion_g=rng.uniform(0, 0.3, (B, S)), dist2_m2=rng.uniform(0, 1.5, (B, S)),
                  omega_dot_norm=rng.uniform(0, 20.0, B))
    block = tr.measurements.with_noise(Frames(**fields)).accel_var_g2
    one = [tr.measurements.with_noise(Frames(**{k: None if v is None else v[b] for k, v in fields.items()}))
           for b in range(B)]
    np.testing.assert_array_equal(np.stack([f.accel_var_g2 for f in one]), block)


# --------------------------------------------------------------------------------------
# the differentiators
@pytest.mark.parametrize("window, order, dim", [(9, 3, 7), (15, 2, 3), (4, 3, 2), (2, 1, 1), (5, 0, 2)])
def test_one_window_s_fit_equals_causal_poly_fit(window, order, dim):
    rng = np.random.default_rng(105)
    for start in (0.0, 1.7e9):  # a recording's clock and a wall clock
        for _ in range(20):
            t = start + np.cumsum(rng.uniform(0.005, 0.015, window))
            y = rng.normal(0, 1, (window, dim)) + np.sin(3.0 * t - start)[:, None]
            ref = causal_poly_fit(t[None], y[None], t[-1:], order)[0]
            got = poly_fit_one(t, y, float(t[-1]), order)
            scale = np.abs(ref).max(axis=1, keepdims=True) + 1.0  # per row: value, rate, acceleration
            assert np.max(np.abs(got - ref) / scale) < 1e-11


class NumpyDifferentiator(CausalDifferentiator):
    """The differentiator as it was in NumPy (``np.roll``, :func:`causal_poly_fit`)."""

    def push(self, t, y):
        self._t = np.roll(self._t, -1)
        self._y = np.roll(self._y, -1, axis=0)
        self._t[-1] = t
        self._y[-1] = y
        self._n = min(self._n + 1, self.window)
        w = self._n
        if w < 2:
            self._fit = np.stack([np.asarray(y, float), np.zeros(self.dim), np.zeros(self.dim)])
        else:
            order = self.order if w > self.order else w - 1
            self._fit = causal_poly_fit(self._t[None, -w:], self._y[None, -w:], np.array([t]), order)[0]
        self._t_last = t

    def at(self, t):
        if self._fit is None:
            return None
        dt = t - self._t_last
        v, d1, d2 = self._fit
        return np.stack([v + d1 * dt + 0.5 * d2 * dt * dt, d1 + d2 * dt, d2])


def test_the_differentiator_sample_by_sample_equals_its_numpy_form():
    """Through the first, partial windows and on; extrapolated between samples; restored
    from a snapshot it goes on the same."""
    rng = np.random.default_rng(106)
    t = np.cumsum(rng.uniform(0.008, 0.012, 60))
    y = np.stack([np.sin(2 * t), t**2, np.cos(5 * t)], 1) + rng.normal(0, 1e-3, (60, 3))
    a, b = CausalDifferentiator(3, 9, 3), NumpyDifferentiator(3, 9, 3)
    assert a.at(0.0) is None
    for k in range(len(t)):
        a.push(float(t[k]), y[k])
        b.push(float(t[k]), y[k])
        np.testing.assert_array_equal(a._t, b._t)
        np.testing.assert_array_equal(a._y, b._y)
        for dt in (0.0, 0.004):
            got, ref = a.at(t[k] + dt), b.at(t[k] + dt)
            np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9 * (1 + np.abs(ref).max()))
        if k == 30:
            c = CausalDifferentiator(3, 9, 3)
            c.restore(a.snapshot())
            np.testing.assert_array_equal(c.at(t[k] + 0.004), a.at(t[k] + 0.004))


def test_a_block_through_the_differentiator_equals_sample_by_sample():
    """push_block (a run's block of instants, some without a sample) gives at every instant
    what push, at and latest give one by one, to the bit, and leaves the same state; no
    fit before the first sample; a block with no sample changes nothing."""
    rng = np.random.default_rng(109)
    t = np.cumsum(rng.uniform(0.008, 0.012, 40))
    y = np.stack([np.sin(2 * t), t**2, np.cos(5 * t)], 1)
    pushed = rng.uniform(size=len(t)) < 0.7
    pushed[:3] = False
    one, many = CausalDifferentiator(3, 9, 2), CausalDifferentiator(3, 9, 2)
    ats, latests, haves = [], [], []
    for a, b in ((0, 17), (17, 17), (17, 40)):  # the middle block is empty
        at, latest, have = many.push_block(t[a:b], y[a:b], pushed[a:b])
        ats.append(at), latests.append(latest), haves.append(have)
    at, latest, have = (np.concatenate(v) for v in (ats, latests, haves))
    assert not have[:3].any() and have[3:].all()
    for k in range(len(t)):
        if pushed[k]:
            one.push(float(t[k]), y[k])
        if not have[k]:
            assert one.at(t[k]) is None
            continue
        np.testing.assert_array_equal(at[k], one.at(float(t[k])))
        np.testing.assert_array_equal(latest[k], one.latest)
    np.testing.assert_array_equal(many._t, one._t)
    np.testing.assert_array_equal(many._y, one._y)
    assert (many._n, many._t_last) == (one._n, one._t_last)
    np.testing.assert_array_equal(many.at(t[-1] + 0.004), one.at(t[-1] + 0.004))


def test_push_fit_shifts_the_window_in_place():
    t_buf, y_buf = np.full(4, np.nan), np.zeros((4, 2))
    for k, v in enumerate((1.0, 2.0, 4.0)):
        fit = push_fit(t_buf, y_buf, float(k), np.array([v, -v]), k + 1, 2)
    np.testing.assert_array_equal(t_buf[1:], [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(y_buf[1:, 0], [1.0, 2.0, 4.0])
    np.testing.assert_allclose(fit[:, 0], [4.0, 2.5, 1.0], atol=1e-12)  # 1 + t/2 + t²/2 at t = 2
    fit, dt = np.random.default_rng(107).normal(0, 1, (3, 2)), 0.25
    np.testing.assert_array_equal(extrapolate_fit(fit, dt), np.stack(
        [fit[0] + fit[1] * dt + 0.5 * fit[2] * dt * dt, fit[1] + fit[2] * dt, fit[2]]))


# --------------------------------------------------------------------------------------
# the live path
def moving_on_a_turning_chair(arm, duration_s: float) -> Scenario:
    """Still for the startup, then the arm reaching while the chair drives and turns."""
    q2 = POSE + np.radians([10, -15, 20, 15, -20, 25, 30])
    b = StepsBuilder(POSE).hold(3.0).move(q2, 2.0).hold(0.5).move(POSE, 2.0)
    while b.t < duration_s:
        b.hold(0.2).move(q2, 1.5).move(POSE, 1.5)
    speed = StepsBuilder(0.0).hold(3.5).move([0.8], 1.5).hold(1.0).move([0.0], 1.5).build()
    yaw_rate = StepsBuilder(0.0).hold(3.5).move([0.5], 1.0).hold(1.0).move([-0.3], 1.0).build()
    flat = StepsBuilder(0.0).build()
    chair = DrivingChair(speed, yaw_rate, flat, flat)
    return Scenario("live", arm, duration_s, WaypointPath(b.build()), chair,
                    lambda t: 25.0 + 0.0 * np.asarray(t, float))


class NumpyFrame:
    """The one-instant frame from :func:`make_frames` (the NumPy form of
    :meth:`FrameConstants.fields`), for a tracker's filter path."""

    def __init__(self, tr: Tracker):
        self.tr = tr

    def fields(self, fit, offset, omega_B, omega_dot_B, motion):
        z = np.zeros(3)
        base = BaseTurn((z if omega_B is None else omega_B)[None],
                        (z if omega_dot_B is None else omega_dot_B)[None])
        return tuple(make_frames(self.tr.arm, self.tr.accel_names,
                                 JointMotion(fit[0][None], fit[1][None], fit[2][None]), offset[None], base,
                                 motion, self.tr._joint_effects).take(0))


@pytest.mark.parametrize("calibrated", [False, True])
def test_update_instant_gives_the_same_estimates_as_the_numpy_path(arm, effects, calibrated, monkeypatch):
    """Instant by instant, the compiled frame and differentiators against make_frames and
    the NumPy differentiator (the filter path before they were compiled)."""
    arm = replace(arm, effects=effects) if calibrated else arm
    rec, _ = simulate(arm, moving_on_a_turning_chair(arm, 9.0), seed=21,
                      effects=effects if calibrated else None)
    a, _ = start_from_recording(arm, rec)
    with monkeypatch.context() as m:
        m.setattr("armfusion.fusion.tracking.setup.CausalDifferentiator", NumpyDifferentiator)
        b, _ = start_from_recording(arm, rec)
    assert isinstance(b.enc_rates, NumpyDifferentiator) and not isinstance(a.enc_rates, NumpyDifferentiator)
    b.frame_constants = NumpyFrame(b)
    assert a.t_s < 4.0
    names = a.sensor_names
    enc = rec.get("enc")
    streams = {s: rec.get(s) for s in names}
    fused = 0
    for i in np.flatnonzero(enc.t_s > a.t_s + 1e-9):
        samples = {s: streams[s].values[i] for s in names}
        ea, eb = a.update_instant(enc.t_s[i], samples), b.update_instant(enc.t_s[i], samples)
        assert ea.t_s == eb.t_s
        np.testing.assert_allclose(ea.q_rad, eb.q_rad, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ea.sigma_rad, eb.sigma_rad, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose([ea.roll_rad, ea.pitch_rad, ea.yaw_rad],
                                   [eb.roll_rad, eb.pitch_rad, eb.yaw_rad], rtol=0, atol=1e-9)
        np.testing.assert_allclose(ea.gyro_bias_rad_s, eb.gyro_bias_rad_s, rtol=0, atol=1e-9)
        assert ea.flags == eb.flags and ea.sensors == eb.sensors
        fused += 1
    assert fused > 400
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-9, atol=1e-15)
    fa, fb = a._frame_cache[1], b._frame_cache[1]
    assert np.max(np.abs(fa.motion_mps2)) > 0.05  # the arm and the chair were moving
    for name, x, y in zip(Frames.FIELDS, fa, fb, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9, err_msg=name)
