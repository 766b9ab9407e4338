"""The effects library: one contract for every effect, then the model and its config entries.

The contract, run over every effect in ``EFFECTS``:
- identity parameters (zero) change nothing;
- shapes are kept (values in, values out; Jacobians ``(N, k, p)``);
- analytic Jacobians agree with central differences, the effect's own (w.r.t. its
  parameters and its input) and the whole model's (through every later stage);
- data simulated with known parameters (noise on) gives them back, by a small weighted
  least-squares fit, within 4 σ of the fit's own uncertainty.
"""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.models.arm_config import ConfigError, build_arm
from armfusion.models.effects import (
    EFFECTS,
    JointEffect,
    Model,
    MountEffect,
    SensorEffect,
    TimeEffect,
    all_effects,
    build_effect,
    describe_effects,
    entries_from_model,
    model_from_arm,
    model_from_entries,
    parse_effect_option,
    realistic_values,
)
from armfusion.models.motion import MotionState
from armfusion.models.simulator import simulate
from armfusion.models.trajectories import make_scenario
from scipy.optimize import least_squares

# where each effect is checked: a target with something to see (a joint with gravity torque,
# the wrist accelerometer for lever arms, …); None = its only possible target
TARGETS = {
    "accel_bias": "acc3", "accel_scale": "acc3", "accel_axes": "acc3", "mount_rotation": "acc3",
    "joint_offset": "j2", "base_mount": None, "link_compliance": "j2", "motion_acceleration": "acc4",
    "time_offset": "acc3", "encoder_scale": "j3", "backlash": "j4", "gyro_bias": None,
    "gyro_scale": None, "mag_hard_iron": None, "mag_soft_iron": None, "mag_arm_disturbance": "j2",
    "temperature_drift": "acc3", "time_drift": "acc3",
}
# the same contract on the IMU's accelerometer, for effects that also apply there
IMU_CASES = ["accel_bias", "accel_scale", "accel_axes", "temperature_drift", "motion_acceleration"]
CASES = [(name, TARGETS[name]) for name in EFFECTS] + [(name, "imu") for name in IMU_CASES]
IDS = [f"{n}:{t}" if t else n for n, t in CASES]


def test_the_contract_covers_every_effect_of_the_library():
    assert set(TARGETS) == set(EFFECTS)
    assert len(EFFECTS) >= 17


@pytest.fixture(scope="module")
def scene(wmra):
    """An excitation scenario: every joint, the chair and the temperature move."""
    sc = make_scenario(wmra, "excitation", duration_s=40.0, seed=11)
    t = np.arange(4000) / 100.0
    return sc, sc.state(t)


@pytest.fixture(scope="module")
def short(scene):
    sc, state = scene
    return state.take(slice(1200, 1400))  # 2 s while everything moves


def _draw(effect, rng, scale=1.0):
    return (effect.draw(rng) * scale).reshape(effect.shape)


# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(("name", "target"), CASES, ids=IDS)
def test_identity_parameters_change_nothing(wmra, short, name, target):
    e = build_effect(wmra, name, target)
    with_e = Model(wmra, [e]).predict(short)
    without = Model(wmra).predict(short)
    for s in without:
        np.testing.assert_allclose(with_e[s], without[s], rtol=0, atol=1e-9, err_msg=s)


@pytest.mark.parametrize(("name", "target"), CASES, ids=IDS)
def test_shapes_are_kept(wmra, short, name, target, rng):
    e = build_effect(wmra, name, target)
    model = Model(wmra, [e])
    theta = _draw(e, rng)
    x = model.pack({e.block_name: theta})
    N, n = short.N, wmra.n_joints
    ctx = model.context(short, x)
    if isinstance(e, SensorEffect):
        for s in e.streams:
            k = len(model.stream_models()[s].channels)
            y = rng.normal(0, 1, (N, k))
            assert e.apply(y, theta, ctx, s).shape == (N, k)
            assert e.jac_params(y, theta, ctx, s).shape == (N, k, e.size)
            A = e.jac_input(y, theta, ctx, s)
            assert A is None or A.shape == (N, k, k)
    elif isinstance(e, JointEffect):
        assert e.apply(short.q_rad, theta, ctx).shape == (N, n)
        assert e.jac_params(short.q_rad, theta, ctx).shape == (N, n, e.size)
    elif isinstance(e, MountEffect):
        R, p = e.apply_mount(np.eye(3), np.zeros(3), theta)
        assert R.shape == (3, 3) and p.shape == (3,)
    else:
        assert isinstance(e, TimeEffect)
    pred, jac = model.predict_with_jacobian(short, x)
    ref = Model(wmra).predict(short)
    for s in ref:
        assert pred[s].shape == ref[s].shape
        for b, J in jac[s].items():
            assert J.shape == ref[s].shape + (model.block(b).size,)
    assert any(e.block_name in jac[s] for s in e.streams)


def _numeric_model_jacobian(model, state, x, block, h):
    sl = model.index[block]
    cols = []
    for i in range(sl.start, sl.stop):
        xp, xm = x.copy(), x.copy()
        xp[i] += h[i - sl.start]
        xm[i] -= h[i - sl.start]
        p, m = model.predict(state, xp, units="physical"), model.predict(state, xm, units="physical")
        cols.append({s: (p[s] - m[s]) / (2 * h[i - sl.start]) for s in p})
    return {s: np.stack([c[s] for c in cols], -1) for s in cols[0]}


@pytest.mark.parametrize(("name", "target"), CASES, ids=IDS)
def test_model_jacobian_matches_central_differences(wmra, short, name, target, rng):
    """Through every stage after the effect, with the effect well away from identity and
    other effects on the same streams so that the chain rule is exercised."""
    e = build_effect(wmra, name, target)
    others = [x for x in all_effects(wmra) if x.block_name != e.block_name
              and set(x.streams) & set(e.streams)]
    model = Model(wmra, [e] + others)
    x = model.pack(realistic_values(model, rng))
    x[model.index[e.block_name]] = _draw(e, rng, 3.0).reshape(-1)
    pred, jac = model.predict_with_jacobian(short, x, units="physical")
    h = np.maximum(e.default_sigma() * 1e-4, 1e-10)
    num = _numeric_model_jacobian(model, short, x, e.block_name, h)
    for s in pred:
        J = jac[s].get(e.block_name, np.zeros_like(num[s]))
        scale = max(np.abs(num[s]).max(), 1e-12)
        np.testing.assert_allclose(J, num[s], rtol=1e-5, atol=1e-6 * scale, err_msg=f"{s}")


@pytest.mark.parametrize(("name", "target"), CASES, ids=IDS)
def test_effect_jacobians_match_central_differences(wmra, short, name, target, rng):
    """The effect on its own: d out / d params and d out / d input."""
    e = build_effect(wmra, name, target)
    model = Model(wmra, [e])
    theta = _draw(e, rng, 3.0)
    ctx = model.context(short, model.pack({e.block_name: theta}))
    hp = np.maximum(e.default_sigma() * 1e-4, 1e-10)
    if isinstance(e, SensorEffect):
        for s in e.streams:
            k = len(model.stream_models()[s].channels)
            y = rng.normal(0, 1, (short.N, k))
            Jp = e.jac_params(y, theta, ctx, s)
            for i in range(e.size):
                d = np.zeros(e.size)
                d[i] = hp[i]
                num = (e.apply(y, theta + d.reshape(e.shape), ctx, s)
                       - e.apply(y, theta - d.reshape(e.shape), ctx, s)) / (2 * hp[i])
                np.testing.assert_allclose(Jp[..., i], num, rtol=1e-6, atol=1e-9)
            A = e.jac_input(y, theta, ctx, s)
            A = np.broadcast_to(np.eye(k), (short.N, k, k)) if A is None else A
            if e.input_is_diagonal:  # the model's fast path relies on it
                assert np.all(A * (1 - np.eye(k)) == 0)
            for c in range(k):
                dy = np.zeros(k)
                dy[c] = 1e-6
                num = (e.apply(y + dy, theta, ctx, s) - e.apply(y - dy, theta, ctx, s)) / 2e-6
                np.testing.assert_allclose(A[..., c], num, rtol=1e-6, atol=1e-9)
    elif isinstance(e, JointEffect):
        q = short.q_rad
        Jp = e.jac_params(q, theta, ctx)
        for i in range(e.size):
            d = np.zeros(e.size)
            d[i] = hp[i]
            num = (e.apply(q, theta + d, ctx) - e.apply(q, theta - d, ctx)) / (2 * hp[i])
            np.testing.assert_allclose(Jp[..., i], num, rtol=1e-6, atol=1e-12)
        A = e.jac_input(q, theta, ctx)
        A = np.broadcast_to(np.eye(q.shape[1]), q.shape + (q.shape[1],)) if A is None else A
        for j in range(q.shape[1]):
            dq = np.zeros(q.shape[1])
            dq[j] = 1e-6
            cp = model.context(short.replace(q_rad=q + dq))
            cm = model.context(short.replace(q_rad=q - dq))
            num = (e.apply(q + dq, theta, cp) - e.apply(q - dq, theta, cm)) / 2e-6
            np.testing.assert_allclose(A[..., j], num, rtol=1e-6, atol=1e-9)
    # mount and time effects act inside the model: the model-level test covers them


def test_exact_time_offset_jacobian(wmra, scene):
    """With a state function, a time offset re-evaluates the state at t - offset; its
    Jacobian is -dy/dt there."""
    sc, _ = scene
    state = sc.state(np.arange(1200, 1400) / 100.0)
    e = build_effect(wmra, "time_offset", "acc4")
    model = Model(wmra, [e])
    x = np.array([0.012])
    pred, jac = model.predict_with_jacobian(state, x, streams=["acc4"], state_at=sc.state,
                                            units="physical")
    h = 1e-5
    num = (model.predict(state, x + h, ["acc4"], state_at=sc.state, units="physical")["acc4"]
           - model.predict(state, x - h, ["acc4"], state_at=sc.state, units="physical")["acc4"]) / (2 * h)
    # dy/dt comes from the samples (second-order differences): good to ~1 % where the
    # motion's jerk jumps (the ends of a minimum-jerk move), far better elsewhere
    J = jac["acc4"]["acc4.time_offset"][..., 0]
    np.testing.assert_allclose(J, num, atol=1e-2 * np.abs(num).max())
    assert np.median(np.abs(J - num)) < 1e-4 * np.abs(num).max()
    # and the exact shift agrees with the first-order one to well under the noise (3 mg)
    first = model.predict(state, x, ["acc4"], units="physical")["acc4"]
    assert np.abs(first - pred["acc4"])[5:-5].max() < 5e-4


def test_time_drift_jacobian_and_its_first_order_prediction(wmra, scene):
    """A drifting offset reads the state at t - (offset + rate t): exactly with a state
    function, to first order without one; both Jacobians are -t dy/dt, and its first-order
    prediction agrees with the exact one to well under the noise."""
    sc, _ = scene
    state = sc.state(np.arange(1200, 1400) / 100.0)
    model = Model(wmra, [build_effect(wmra, "time_drift", "acc4")])
    x = np.array([8e-4])  # 10 ms at 12.5 s
    exact, jac = model.predict_with_jacobian(state, x, streams=["acc4"], state_at=sc.state, units="physical")
    first, jac1 = model.predict_with_jacobian(state, x, streams=["acc4"], units="physical")
    h = 1e-7
    num = (model.predict(state, x + h, ["acc4"], state_at=sc.state, units="physical")["acc4"]
           - model.predict(state, x - h, ["acc4"], state_at=sc.state, units="physical")["acc4"]) / (2 * h)
    J = jac["acc4"]["acc4.time_drift"][..., 0]
    # dy/dt from the samples: off where the chair's jerk jumps (one instant in 200), times t
    np.testing.assert_allclose(J, num, atol=0.1 * np.abs(num).max())
    assert np.mean(np.abs(J - num) > 1e-2 * np.abs(num).max()) < 0.01
    assert np.median(np.abs(J - num)) < 1e-3 * np.abs(num).max()
    # the first-order Jacobian reads dy/dt at the stamp, not 10 ms earlier: close where the
    # motion is smooth (the excitation's chair jerks)
    J1 = jac1["acc4"]["acc4.time_drift"][..., 0]
    assert np.median(np.abs(J1 - num)) < 2e-2 * np.abs(num).max()
    assert np.median(np.abs(first["acc4"] - exact["acc4"])) < 5e-4
    # at the same instant a plain offset of offset + rate t reads the same
    t = state.t_s[100]
    off = Model(wmra, [build_effect(wmra, "time_offset", "acc4")])
    at = off.predict(state, np.array([8e-4 * t]), ["acc4"], state_at=sc.state, units="physical")["acc4"]
    np.testing.assert_allclose(exact["acc4"][100], at[100], atol=1e-9)


# --------------------------------------------------------------------------------------
def _fit_block(model, block, state, rec, q0):
    """Weighted least squares of one block from zero; estimate and its 1-σ."""
    streams = [s for s in model.effect(block).streams if s in rec.streams]
    sms = model.stream_models()
    meas = {s: rec.streams[s].values.astype(float) for s in streams}
    w = {s: np.tile(1.0 / sms[s].sigma_counts, state.N) for s in streams}

    def resid(p):
        pred = model.predict(state, model.pack({block: p}), streams, encoder_zero_rad=q0)
        return np.concatenate([(pred[s] - meas[s]).ravel() * w[s] for s in streams])

    def jac(p):
        pred, J = model.predict_with_jacobian(state, model.pack({block: p}), streams,
                                              encoder_zero_rad=q0, blocks=[block])
        D = model.dense_jacobian(J, pred, [block])
        return D * np.concatenate([w[s] for s in streams])[:, None]

    b = model.block(block)
    res = least_squares(resid, np.zeros(b.size), jac=jac, x_scale=b.prior_sigma, method="lm")
    cov = np.linalg.inv(res.jac.T @ res.jac)
    chi2 = 2 * res.cost / (len(res.fun) - b.size)
    return res.x, np.sqrt(np.diag(cov)), chi2


@pytest.mark.parametrize(("name", "target"), CASES, ids=IDS)
def test_simulated_data_with_known_parameters_gives_them_back(wmra, scene, name, target, rng):
    sc, state = scene
    e = build_effect(wmra, name, target)
    truth_model = Model(wmra, [e])
    true = _draw(e, rng, 2.0).reshape(-1)
    true = np.where(np.abs(true) < 0.3 * e.default_sigma(), 0.3 * e.default_sigma(), true)  # not ~0
    rec, truth = simulate(wmra, sc, effects=truth_model.with_values({e.block_name: true}),
                          seed=int(rng.integers(1000)))
    est, sigma, chi2 = _fit_block(truth_model, e.block_name, state, rec,
                                  np.array(truth["encoder_zero_rad"]))
    assert np.all(np.abs(est - true) < 4 * sigma + 1e-12), (est, true, sigma)
    assert np.all(sigma < e.default_sigma()), sigma  # the data say more than the prior
    assert 0.5 < chi2 < 1.5  # residuals at the noise floor: the model is the simulator's


# --------------------------------------------------------------------------------------
def test_effects_apply_in_physical_order_whatever_the_list_order(wmra, short, rng):
    effs = [build_effect(wmra, n, "acc2") for n in ("accel_bias", "accel_scale", "accel_axes",
                                                     "mount_rotation", "temperature_drift")]
    m1 = Model(wmra, effs)
    vals = realistic_values(m1, rng)
    m2 = Model(wmra, effs[::-1], vals)
    p1 = m1.with_values(vals).predict(short, streams=["acc2"])
    np.testing.assert_allclose(p1["acc2"], m2.predict(short, streams=["acc2"])["acc2"], atol=1e-12)


def test_parameters_are_named_blocks_in_one_flat_vector(wmra):
    model = Model(wmra, [build_effect(wmra, "mount_rotation", "acc3"),
                         build_effect(wmra, "joint_offset", "j4")])
    assert [b.name for b in model.blocks] == ["acc3.mount_rotation", "j4.joint_offset"]
    x = model.pack({"j4.joint_offset": [0.01], "acc3.mount_rotation": [0.1, 0.2, 0.3]})
    np.testing.assert_array_equal(x, [0.1, 0.2, 0.3, 0.01])
    assert model.index["j4.joint_offset"] == slice(3, 4)
    np.testing.assert_array_equal(model.unpack(x)["acc3.mount_rotation"], [0.1, 0.2, 0.3])
    assert model.element_names()[1] == "acc3.mount_rotation[y]"
    bigger = model.with_values(x).with_effects([build_effect(wmra, "accel_bias", "acc1")])
    np.testing.assert_array_equal(bigger.x0, [0.1, 0.2, 0.3, 0.01, 0, 0, 0])
    with pytest.raises(ValueError, match="listed twice"):
        Model(wmra, [build_effect(wmra, "joint_offset", "j4")] * 2)


def test_every_effect_explains_itself(wmra):
    rows = describe_effects()
    assert [r["effect"] for r in rows] == list(EFFECTS)
    for r in rows:
        assert len(r["description"]) > 80 and r["seen_in"] and r["units"]
        assert r["key"].split("_")[-1] in ("g", "rad", "m", "s", "c", "nm", "ut", "am2", "error") or r["key"]
    # every effect fits somewhere on the WMRA, and the datasheet magnitudes are positive
    for e in all_effects(wmra):
        assert np.all(e.default_sigma() > 0)


def test_the_manual_documents_every_effect_and_its_units():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "effects.md").read_text()
    for name, cls in EFFECTS.items():
        assert f"| `{name}` |" in text and f"**`{name}`**" in text, name
        assert f"`{cls.key}`" in text, cls.key


# --------------------------------------------------------------------------------------
# effects in the arm config
def _config_with(wmra_data, effects):
    data = dict(wmra_data)
    data["effects"] = effects
    return build_arm(data, "test.yaml")


@pytest.fixture(scope="module")
def wmra_data():
    import yaml
    from armfusion.fusion.configfile import resolve_config_path

    return yaml.safe_load(resolve_config_path("wmra").read_text())


def test_config_effects_load_into_a_model(wmra_data, short):
    arm = _config_with(wmra_data, [
        {"effect": "mount_rotation", "target": "acc3", "params": {"rotvec_rad": [0.01, 0.02, 0]},
         "sigma": {"rotvec_rad": 0.002}},
        {"effect": "gyro_bias", "params": {"bias_rad_s": [0.01, 0, 0]}},
        {"effect": "accel_axes", "target": "acc1",
         "params": {"axis_angles_rad": [[0, 0.01], [0, 0], [0.02, 0]]}},
        {"effect": "joint_offset", "target": "j2"},
    ])
    model = model_from_arm(arm)
    assert [b.name for b in model.blocks] == ["acc3.mount_rotation", "imu.gyro_bias", "acc1.accel_axes",
                                              "j2.joint_offset"]
    np.testing.assert_allclose(model.unpack()["acc3.mount_rotation"], [0.01, 0.02, 0])
    np.testing.assert_allclose(model.block("acc3.mount_rotation").prior_sigma, 0.002)
    np.testing.assert_allclose(model.unpack()["acc1.accel_axes"], [[0, 0.01], [0, 0], [0.02, 0]])
    assert model.unpack()["j2.joint_offset"] == 0.0  # listed without a value: to be estimated
    # the entries written back load to the same model
    again = model_from_entries(arm, entries_from_model(model))
    np.testing.assert_array_equal(again.x0, model.x0)
    p = model.predict(MotionState.static(arm.ready_pose_rad))
    assert p["acc3"].shape == (1, 3)


def test_config_effect_errors_name_the_key_and_are_reported_together(wmra_data):
    arm = _config_with(wmra_data, [
        {"effect": "accel_bias", "target": "acc1"},
        {"effect": "mount_rotation", "target": "acc9"},
        {"effect": "acel_bias", "target": "acc1"},
        {"effect": "accel_bias", "target": "acc2", "params": {"bias": [0, 0, 0]}},
        {"effect": "accel_bias", "target": "acc3", "params": {"bias_g": [0, 0]}},
        {"effect": "joint_offset", "target": "j2", "params": {"offset_rad": 2.0}},
        {"effect": "accel_bias", "target": "acc1"},
        {"effect": "accel_scale"},
        {"effect": "gyro_bias", "sigma": {"bias_rad_s": [0.1, -1, 0.1]}},
    ])
    with pytest.raises(ConfigError) as err:
        model_from_arm(arm)
    msg = str(err.value)
    assert "9 problems" not in msg and "8 problems" in msg
    assert "test.yaml: effects[1].target: mount_rotation applies to a link accelerometer: one of acc1, " \
           "acc2, acc3, acc4; not 'acc9'" in msg
    assert "effects[2].effect: unknown effect 'acel_bias'; known: accel_bias, accel_scale" in msg
    assert "(did you mean 'accel_bias'?)" in msg
    assert "effects[3].params.bias: unknown parameter 'bias' of accel_bias; it has 'bias_g': 3 values " \
           "(x, y, z) in g" in msg
    assert "effects[4].params.bias_g: expected 3 values (x, y, z) in g, got 2" in msg
    assert "effects[5].params.offset_rad: offset = 2 is outside the bounds [-0.35, 0.35] rad" in msg
    assert "effects[6]: accel_bias on acc1 is already given by effects[0]" in msg
    assert "effects[7].target: accel_scale needs a target" in msg
    assert "effects[8].sigma.bias_rad_s: every sigma must be positive" in msg


def test_command_line_effect_option():
    assert parse_effect_option("mount_rotation:acc3=0.01,0.02,0") == {
        "effect": "mount_rotation", "target": "acc3", "value": [0.01, 0.02, 0.0]}
    assert parse_effect_option("gyro_bias=0.1,0,0")["target"] is None
    with pytest.raises(ValueError, match=r"expected NAME\[:TARGET\]=VALUE"):
        parse_effect_option("gyro_bias")
    with pytest.raises(ValueError, match="must be numbers separated by commas"):
        parse_effect_option("gyro_bias=a,b")


def test_sag_and_play_see_gravity_where_the_links_really_stand(wmra, rng):
    """Tilting the base about joint 1's axis (WMRA: the base's y) and turning joint 1's zero
    back by the same angle leaves every link exactly where it was, so no link accelerometer
    may tell the two apart, sag and play included. Evaluated at the controller's angles
    instead of the real ones, the gravity torque differs, a long fit reads that difference
    as information, and the encoder zero comes out confidently wrong."""
    axis = wmra.joints[0].R_pre @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(axis, [0.0, 1.0, 0.0], atol=1e-12)
    effs = [build_effect(wmra, "joint_offset", "j1")] + \
        [build_effect(wmra, n, j) for n in ("link_compliance", "backlash") for j in wmra.joint_names]
    model = Model(wmra, effs)
    x = model.pack(realistic_values(model, rng)) * 3.0
    n = 50
    q = rng.uniform(wmra.min_rad, wmra.max_rad, size=(n, wmra.n_joints))
    roll, pitch = np.zeros(n), rng.normal(0, 0.05, n)  # roll 0: pitch turns about the base's y
    streams = [s.name for s in wmra.link_accelerometers]
    before = model.predict(MotionState.static(q, roll, pitch), x, streams, units="physical")
    delta_rad = 0.03
    x2 = x.copy()
    x2[model.index["j1.joint_offset"]] += delta_rad
    after = model.predict(MotionState.static(q, roll, pitch - delta_rad), x2, streams, units="physical")
    for s in streams:
        np.testing.assert_allclose(after[s], before[s], atol=1e-9, err_msg=s)
