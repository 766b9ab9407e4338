"""The model-change alarm (fusion/tracking/alarm.py): naming on synthetic innovations, and
in the tracker on a simulated recording: a 2 deg mount turn and a bias jump named on the
right sensor, a clean recording raising nothing, a hard iron on the compass."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.tracking.alarm import Alarm, ModelChangeAlarm, reference_or_filter
from armfusion.fusion.tracking.alarm_naming import name_shift, onset
from armfusion.fusion.tracking.settings import C_REACQUISITIONS
from armfusion.fusion.tracking.tracker import start_from_recording
from armfusion.models.rotations import DEG, exp_so3

from tools.bench_alarm import bias_jumped, iron_gained, mount_turned
from tools.bench_track import with_stream

T_CHANGE_S = 70.0
TURN_RAD = np.array([1.0, -1.0, 0.5]) * 2.0 * DEG / 1.5  # 2 deg
BIAS_G = np.array([0.03, -0.02, 0.04])


def _gravity_path(rng, n, step=0.08):
    """Unit specific forces (g) that wander as a moving arm's do in a sensor's axes (``step``
    0: an arm that holds its pose)."""
    g = np.cumsum(rng.normal(scale=step, size=(n, 3)), axis=0) + np.array([0.0, 0.0, 1.0])
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def _turned(g):
    """The innovations of a board turned by ``TURN_RAD``: the reading ``R g`` less ``g``."""
    return g @ exp_so3(TURN_RAD).T - g


def test_name_shift_tells_a_turned_board_from_a_bias_as_the_arm_moves():
    rng = np.random.default_rng(3)
    g = _gravity_path(rng, 60)
    noise = rng.normal(scale=0.001, size=(60, 3))
    var = np.full(60, 0.001**2)
    n = name_shift(_turned(g) + noise, g, var)
    assert (n.effect, n.candidates) == ("mount_rotation", ("mount_rotation",))
    assert abs(n.size - 2.0) < 3 * n.sigma + 0.05 and n.sigma < 0.2
    n = name_shift(BIAS_G + noise, g, var)
    assert (n.effect, n.candidates) == ("bias_jump", ("bias_jump",))
    assert abs(n.size - np.linalg.norm(BIAS_G)) < 0.002


def test_a_bias_across_a_force_that_does_not_turn_is_not_guessed():
    """At one pose a bias across the force reads as a turn would: both stay named until the
    arm moves; a bias with a part along the force is named at once."""
    rng = np.random.default_rng(5)
    g = _gravity_path(rng, 30, step=0.0)
    noise = rng.normal(scale=0.001, size=(30, 3))
    var = np.full(30, 0.001**2)
    across = np.cross([0.0, 0.0, 1.0], BIAS_G)
    n = name_shift(across + noise, g, var)
    assert set(n.candidates) == {"mount_rotation", "bias_jump"}
    n = name_shift(_turned(g) + noise, g, var)
    assert set(n.candidates) == {"mount_rotation", "bias_jump"}
    n = name_shift(BIAS_G + noise, g, var)
    assert n.candidates == ("bias_jump",)


def test_a_lurching_block_does_not_name_a_turn_a_bias():
    """A block where the arm lurched (far along the force, its variance a hundred times the
    others') is left out of the naming."""
    rng = np.random.default_rng(6)
    g = _gravity_path(rng, 40)
    nu = _turned(g) + rng.normal(scale=0.001, size=(40, 3))
    var = np.full(40, 0.001**2)
    nu[10] += 0.08 * g[10]
    var[10] = 0.01**2
    n = name_shift(nu, g, var)
    assert n.candidates == ("mount_rotation",)


def test_onset_finds_the_step():
    rng = np.random.default_rng(4)
    nu = rng.normal(scale=0.001, size=(80, 3))
    nu[50:] += [0.01, 0.0, -0.01]
    assert abs(onset(nu) - 50) <= 1


def test_a_few_blocks_decide_nothing():
    """Three blocks far along the force (the filter diverging on a changed sensor just
    before the alarm) are no evidence yet: both effects stay named."""
    rng = np.random.default_rng(7)
    g = _gravity_path(rng, 3)
    nu = 0.2 * g + rng.normal(scale=0.001, size=(3, 3))
    assert set(name_shift(nu, g, np.full(3, 0.1**2)).candidates) == {"mount_rotation", "bias_jump"}
    nu = 0.2 * _gravity_path(rng, 4, step=0.0) + rng.normal(scale=0.001, size=(4, 3))
    assert name_shift(nu, _gravity_path(rng, 4, step=0.0), np.full(4, 0.1**2)).candidates == ("bias_jump",)


def test_an_undecided_alarm_says_so_and_survives_its_json_form():
    """``armfusion track`` prints its alarms from their JSON form: an alarm the motion has
    not yet decided names both effects there."""
    a = Alarm("acc4", "mount_rotation", 2.27, 4.9, "deg", 45.0, 49.0, ("mount_rotation", "bias_jump"))
    assert not a.decided and a.named_s is None
    assert a.line() == "acc4 mount_rotation 2.27 ± 4.9 deg or bias_jump (not yet told apart) since 45.0 s"
    assert Alarm.of_dict(a.as_dict()) == a
    b = Alarm("acc4", "mount_rotation", 1.89, 0.35, "deg", 45.0, 49.0, ("mount_rotation",), 62.0)
    assert b.decided and b.line() == "acc4 mount_rotation 1.89 ± 0.35 deg since 45.0 s"
    assert Alarm.of_dict(b.as_dict()) == b


def test_clear_names_an_unknown_sensor():
    al = ModelChangeAlarm(("acc1", "acc2"), "imu_mag", 0.0)
    with pytest.raises(KeyError, match="no sensor 'acc9'; the alarm watches"):
        al.clear("acc9")


@pytest.fixture(scope="module")
def arm(calibrated_wmra_arm):
    return calibrated_wmra_arm


@pytest.fixture(scope="module")
def daily(daily_use_110s):
    return daily_use_110s


def _alarms(arm, rec):
    tr, _ = start_from_recording(arm, rec)
    tr.run(rec)
    return tr


def test_a_clean_day_raises_nothing(arm, daily):
    tr = _alarms(arm, daily)
    assert tr.alarm.raised == []
    assert not tr.alarm.widen_g2.any()


def test_a_turned_board_is_named_and_down_weighted(arm, daily):
    rec = mount_turned(daily, "acc4", T_CHANGE_S, np.array([0.6, -0.8, 0.0]) * 2.0 * DEG)
    tr = _alarms(arm, rec)
    (a,) = tr.alarm.raised
    assert (a.sensor, a.effect, a.unit) == ("acc4", "mount_rotation", "deg")
    assert T_CHANGE_S - 2.0 <= a.since_s <= T_CHANGE_S + 2.0
    assert T_CHANGE_S < a.raised_s <= T_CHANGE_S + 30.0
    assert 0.7 < a.size < 5.0 and 0 < a.sigma < a.size
    assert "acc4 mount_rotation" in a.line()
    s = tr.link_names.index("acc4")
    assert tr.alarm.widen_g2[s] > 0 and tr.alarm.widen_g2.sum() == tr.alarm.widen_g2[s]
    tr.alarm.clear("acc4")  # recalibrated: its weight comes back
    assert not tr.alarm.widen_g2.any() and tr.alarm.alarms == ()


def test_a_raised_alarm_survives_a_restart_of_the_tracker(arm, daily):
    """A tracker restored from another's snapshot (a restarted node) keeps the alarm raised
    before the restart and its sensor down-weighted; the shift that goes on is not raised
    again as a new change."""
    import json

    from armfusion.fusion.tracking.filter import Tracker

    rec = mount_turned(daily, "acc4", T_CHANGE_S, np.array([0.6, -0.8, 0.0]) * 2.0 * DEG)
    a, _ = start_from_recording(arm, rec)
    a.run(rec, t_stop_s=T_CHANGE_S + 32.0)
    (raised,) = a.alarm.raised
    snap = json.loads(json.dumps(a.snapshot()))
    b = Tracker(arm)
    b.restore(snap)
    # (as published: sizes to the micro-unit) and published again
    assert [x.as_dict() for x in b.alarm.alarms] == [x.as_dict() for x in a.alarm.alarms]
    assert b.alarm.alarms and b.alarm.version > 0
    np.testing.assert_array_equal(b.alarm.widen_g2, a.alarm.widen_g2)
    b.run(rec)
    assert [al.sensor for al in b.alarm.raised] == ["acc4"] and b.alarm.raised[0].since_s == raised.since_s
    assert b.alarm.widen_g2[b.link_names.index("acc4")] > 0
    with pytest.raises(ValueError, match="the alarm's snapshot watches"):
        ModelChangeAlarm(("acc1",), None, 0.0).restore(snap["alarm"])


def test_a_bias_jump_is_named(arm, daily):
    rec = bias_jumped(daily, "acc3", T_CHANGE_S, np.array([0.0, 0.03, -0.04]))
    (a,) = _alarms(arm, rec).alarm.raised
    assert (a.sensor, a.effect, a.unit) == ("acc3", "bias_jump", "g")
    assert abs(a.size - 0.05) < 0.015


def test_hard_iron_is_named_on_the_compass(arm, daily):
    rec = iron_gained(daily, T_CHANGE_S, np.array([15.0, -10.0, 8.0]))
    alarms = _alarms(arm, rec).alarm.raised
    assert [(a.sensor, a.effect, a.unit) for a in alarms] == [("imu_mag", "hard_iron", "uT")]
    assert T_CHANGE_S <= alarms[0].raised_s <= T_CHANGE_S + 30.0


def test_a_compass_alarm_widens_no_accelerometer():
    """An arm without link accelerometers (IMU only) whose compass is alarmed: the update's
    variances are left as they are."""
    al = ModelChangeAlarm((), "imu_mag", 0.0)
    for t in np.arange(0.0, 25.0, 0.5):
        al.compass(float(t), True, 12.0)
    assert [a.effect for a in al.alarms] == ["hard_iron"]
    var = np.full(3, 1e-4)
    al.widen(np.array([0]), var)
    assert np.all(var == 1e-4)


def test_the_held_offsets_are_tested_only_where_the_other_sensors_agree_with_them():
    """After a re-acquisition the filter has moved joint offsets: a block is tested against
    the offsets held before (``nu + moved``) when the other sensors the move changed agree
    with those (a turned board the filter followed), and on the filter's own innovations
    when they agree with the move (an encoder slip) or when only one sensor saw the move."""
    rng = np.random.default_rng(8)
    var = np.full(3, 1e-6)
    floor = np.full(3, 0.004)
    moved = np.array([[0.03, -0.01, 0.0], [0.02, 0.0, 0.01], [-0.01, 0.02, 0.0]])
    noise = rng.normal(scale=0.001, size=(3, 3))
    turned = noise - moved  # the filter followed sensor 0's turn; 1 and 2 disagree by as much
    turned[0] += [0.0, 0.0, 0.035]
    pick = reference_or_filter
    assert np.array_equal(pick(turned, moved, var, floor), turned + moved)
    slipped = noise.copy()  # every sensor beyond the joint follows the new offsets
    assert np.array_equal(pick(slipped, moved, var, floor), slipped)
    alone = moved * [[1.0], [0.0], [0.0]]  # the move changed one sensor's prediction only
    assert np.array_equal(pick(turned, alone, var, floor), turned)


def test_a_turn_the_filter_followed_into_the_joints_is_raised_on_the_turned_board(arm):
    """bench_alarm's seed 1011: acc2 turned by 2 deg; the slip detector re-acquired at once
    and the filter moved j3 and j5 by degrees to follow it, acc2's own innovations fell back
    under the test and acc1 was blamed 20 s later. Against the offsets held before, acc2
    shows the turn in full."""
    from argparse import Namespace

    from tools.bench_alarm import trial

    r = trial(arm, "mount_rotation", 1011, 180.0, Namespace(mount_deg=2.0, bias_g=0.05, iron_ut=20.0,
                                                            within_s=30.0))
    assert r["sensor"] == "acc2" and r["detected"] and r["delay_s"] < 10.0
    assert [g[0] for g in r["got"]] == ["acc2"]


def test_an_encoder_slip_the_filter_follows_raises_nothing(arm, daily):
    """Every sensor beyond a slipped joint agrees with the offsets the filter re-acquired:
    no sensor changed."""
    enc = daily.get("enc")
    v = enc.values.copy()
    v[:, 2] -= np.round((enc.t_s >= T_CHANGE_S) * 1.0 * DEG * arm.counts_per_rad[2]).astype(np.int64)
    tr = _alarms(arm, with_stream(daily, "enc", v))
    assert tr.health.counts[:, C_REACQUISITIONS].sum() > 0  # the slip detector re-acquired
    assert tr.alarm.raised == []


def test_a_turn_whose_innovation_turns_with_the_force_is_named_within_30_s(arm):
    """bench_alarm's seed 1014: acc1 turned by 2 deg, raised at +3.7 s; the arm then swung
    the force through tens of degrees, the turn's innovation turning with it, while the
    along components showed only what the model leaves (~1 mg). On the along components
    alone it was named at +42 s; the whole innovation, a turn's and no bias's, names it
    within 30 s."""
    from argparse import Namespace

    from tools.bench_alarm import trial

    r = trial(arm, "mount_rotation", 1014, 180.0, Namespace(mount_deg=2.0, bias_g=0.05, iron_ut=20.0,
                                                            within_s=30.0))
    assert r["sensor"] == "acc1" and r["detected"] and r["named"]
    assert abs(r["size"] - 2.0) < 3 * r["sigma"] + 0.3
