"""The workbench never makes the model worse: a mount rotation about its own joint's axis is
held (it is that joint's zero), a parameter at its bound is never significant nor written, and
every fit is judged on data it did not see, a rung or an added effect that fits those worse
refused."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from armfusion.fusion.cli.diagnose_write import without_bound
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.data import data_from_recording
from armfusion.fusion.workbench.candidates import at_bound
from armfusion.fusion.workbench.diagnose import add_effects, diagnose
from armfusion.fusion.workbench.discover import held_out_worse
from armfusion.fusion.workbench.gauges import structural_gauges
from armfusion.fusion.workbench.heldout import HeldOut, split_in_time
from armfusion.models.effects import build_effect, model_from_arm
from armfusion.models.simulator import simulate

WINDOW = 10


@pytest.fixture(scope="module")
def wmra():
    return load_arm("wmra")


@pytest.fixture(scope="module")
def ur5():
    return load_arm("ur5_two_imu")


def _sweep(arm, seed, duration_s=20.0, hidden=()):
    rec, _ = simulate(arm, "renk-maneuver", duration_s, seed=seed,
                      effects=[{"effect": e, "target": t, "params": {k: v}} for e, t, k, v in hidden])
    return data_from_recording(arm, rec, window=WINDOW)


@pytest.fixture(scope="module")
def turned(wmra):
    """acc4's board (on the last link) turned by 2° about its joint's axis and a little about x."""
    return _sweep(wmra, 31, hidden=[("mount_rotation", "acc4", "rotvec_rad", [0.01, 0.0, 0.035])])


def test_a_mount_about_its_own_joints_axis_is_held_where_it_is_that_joints_zero(wmra, ur5, turned):
    """From the model's Jacobians in still poses, for any arm: on the WMRA only the last
    board's turn about j7 (no other sensor sees j7's zero; acc2's turn about j4 is told apart
    by acc3 and acc4, which see j4's zero and not acc2's board); on the UR5 both boards (the
    shoulder, elbow and wrist 1 axes are parallel: the forearm's turn about the elbow's axis is
    the elbow's zero less wrist 1's)."""
    m = model_from_arm(wmra).with_effects([build_effect(wmra, "mount_rotation", s.name)
                                           for s in wmra.link_accelerometers])
    got = {g.block: (g.held, g.partners[0], g.structural) for g in structural_gauges(m, turned)}
    assert got == {"acc4.mount_rotation": ("acc4.mount_rotation[z]", "j7.joint_offset", True)}
    m5 = model_from_arm(ur5).with_effects([build_effect(ur5, "mount_rotation", s.name)
                                           for s in ur5.link_accelerometers])
    # the UR5's poses: any angles of its six joints will do (the identity is kinematic)
    st = turned.state.replace(q_rad=turned.state.q_rad[:, :6], qd_rad_s=turned.state.qd_rad_s[:, :6],
                              qdd_rad_s2=turned.state.qdd_rad_s2[:, :6])
    data5 = replace(turned, state=st, counts={}, q_ref_rad=turned.q_ref_rad[:6])
    got5 = {g.block: (g.held, g.partners[0]) for g in structural_gauges(m5, data5)}
    assert got5 == {"forearm.mount_rotation": ("forearm.mount_rotation[z]", "elbow.joint_offset"),
                    "wrist.mount_rotation": ("wrist.mount_rotation[y]", "wrist1.joint_offset")}


@pytest.fixture(scope="module")
def turned_diagnosed(wmra, turned):
    d = diagnose(model_from_arm(wmra), turned)
    return d, add_effects(d, [build_effect(wmra, "mount_rotation", "acc4")])


def test_the_gauge_is_held_in_the_candidates_refit_and_in_the_fit(turned_diagnosed):
    """The turned board's candidate is refitted with its z held at the prior (0) and says why;
    j7's zero carries the turn about its axis. Added to the model, z stays held, the turn about
    x is found within 3σ and the model fits to the noise."""
    d, d2 = turned_diagnosed
    c = next(c for c in d.candidates if c.name == "mount_rotation:acc4")
    assert c.refitted
    assert c.params["acc4.mount_rotation[z]"][0] == 0.0
    g = c.gauges[0]
    assert g.structural and g.held == "acc4.mount_rotation[z]" and g.partners[0] == "j7.joint_offset"
    assert "no motion separates it from j7's zero" in g.message
    sl = d2.fit.model.index["acc4.mount_rotation"]
    assert d2.fit.x[sl][2] == 0.0 and d2.fit.held[sl][2]
    assert [g.held for g in d2.gauges] == ["acc4.mount_rotation[z]"]
    assert abs(d2.fit.x[sl][0] - 0.01) < 3 * d2.fit.sigma[sl][0]
    assert d2.rms_ratio < 1.15, d2.rms_ratio


def test_a_turn_the_structure_separates_is_not_held(wmra):
    """acc2's turn about j4's axis: acc3 and acc4 see j4's zero, not acc2's board; it is free
    and found."""
    data = _sweep(wmra, 32, hidden=[("mount_rotation", "acc2", "rotvec_rad", [0.0, 0.0, 0.035])])
    d = add_effects(diagnose(model_from_arm(wmra), data), [build_effect(wmra, "mount_rotation", "acc2")])
    sl = d.fit.model.index["acc2.mount_rotation"]
    assert d.gauges == () and not d.fit.held[sl][2]
    assert abs(d.fit.x[sl][2] - 0.035) < 3 * d.fit.sigma[sl][2]


def test_a_parameter_at_its_bound_is_named_and_not_written(wmra):
    """``at_bound`` names an estimate within 2 % of a non-zero bound; a diagnosis's elements
    at their bound are written at their prior (value and σ)."""
    b = build_effect(wmra, "mount_rotation", "acc2").block()
    assert at_bound({"acc2.mount_rotation[z]": 0.349, "acc2.mount_rotation[x]": 0.2}, b) == [
        "acc2.mount_rotation[z]"]
    assert at_bound({"acc2.mount_rotation[y]": -0.35}, b) == ["acc2.mount_rotation[y]"]
    sag = build_effect(wmra, "link_compliance", "j2").block()
    assert at_bound({n: 0.0 for n in sag.element_names()}, sag) == []  # 0 is its floor, not a pull


def test_without_bound_writes_the_prior(turned_diagnosed):
    d = turned_diagnosed[1]
    name = "acc4.mount_rotation[x]"
    fit = without_bound(replace(d, at_bound=(name,)))
    i = list(d.fit.names).index(name)
    assert fit.x[i] == d.fit.x0[i] and fit.sigma[i] == d.fit.prior_sigma[i]
    assert d.fit.x[i] != d.fit.x0[i]


def test_split_in_time_fits_the_start_and_judges_the_end(wmra, turned):
    fit_part, held = split_in_time(turned)
    assert fit_part.n + held.data.n == turned.n
    assert abs(fit_part.n / turned.n - 0.7) < 0.01
    assert held.data.state.t_s[0] > fit_part.state.t_s[-1]
    with pytest.raises(ValueError, match="too few"):
        split_in_time(turned.subset(slice(0, 30)))
    d = diagnose(model_from_arm(wmra), fit_part, held_out=held)
    # the config lacks the turn: the end is not fitted either
    assert d.held_out_ratio > 2
    d2 = add_effects(d, [build_effect(wmra, "mount_rotation", "acc4")])
    assert d2.held_out_ratio < 1.2 and held_out_worse(d, d2) is None
    assert "held-out error rose" in held_out_worse(d2, d)


def test_an_effect_the_other_recording_lacks_is_refused(wmra):
    """Fitted on a recording with acc2's bias hidden and judged on one without it: adding the
    bias fits the first to the noise, the second worse than before; it is refused with that
    reason."""
    biased = _sweep(wmra, 41, hidden=[("accel_bias", "acc2", "bias_g", [0.0, 0.02, 0.0])])
    clean = _sweep(wmra, 42)
    held = HeldOut(clean, False, "the clean recording")
    d = diagnose(model_from_arm(wmra), biased, held_out=held)
    assert d.significant[0].name == "accel_bias:acc2"
    d2 = add_effects(d, [build_effect(wmra, "accel_bias", "acc2")])
    assert d2.rms_ratio < d.rms_ratio / 3
    why = held_out_worse(d, d2)
    assert why is not None and "held-out error rose" in why, (d.held_out_ratio, d2.held_out_ratio)
    assert np.isfinite(d2.held_out_ratio)


def test_a_config_whose_tracker_is_too_sure_on_the_held_out_part_is_not_written():
    """The write gate's rule: fewer innovations within 3σ on the held-out part than the config
    it replaces (beyond 1 %) refuses it and names the sensor; as many, or more, passes."""
    from armfusion.fusion.workbench.heldout import Tracked, tracked_worse

    before = Tracked({"forearm": 0.998, "wrist": 1.0}, {"forearm": 0.2, "wrist": 0.2})
    same = Tracked({"forearm": 0.995, "wrist": 1.0}, {"forearm": 0.3, "wrist": 0.3})
    assert tracked_worse(before, same) is None
    why = tracked_worse(before, Tracked({"forearm": 0.62, "wrist": 1.0}, {"forearm": 4.0, "wrist": 0.3}))
    assert why is not None and "forearm keeps 62.0 % of its innovations within 3σ against 99.8 %" in why
    assert "forearm's mean NIS per dof is 4.00" in why and "wrist" not in why


def test_a_config_whose_tracked_angles_wander_off_the_encoders_is_not_written():
    """Without the truth, the tracked error the held-out part shows: each joint's angle against
    its encoder wandering about its median, and the innovations' RMS. A config under which
    either grows (beyond 1 % and, for the angles, one encoder count) is refused, naming the
    joint or sensor; one under which they shrink passes, though it is more cautious."""
    from armfusion.fusion.workbench.heldout import Tracked, tracked_worse

    before = Tracked({"forearm": 1.0}, {"forearm": 0.3}, {"forearm": 0.020},
                     {"shoulder": 0.10, "elbow": 0.20}, 0.001)
    better = Tracked({"forearm": 1.0}, {"forearm": 0.1}, {"forearm": 0.012},
                     {"shoulder": 0.05, "elbow": 0.2005}, 0.001)
    assert tracked_worse(before, better) is None
    why = tracked_worse(before, Tracked({"forearm": 1.0}, {"forearm": 0.3}, {"forearm": 0.020},
                                        {"shoulder": 0.10, "elbow": 0.35}, 0.001))
    assert why is not None
    assert "elbow's tracked angle wanders 0.350° RMS off its encoder against 0.200°" in why
    assert "shoulder" not in why
    why = tracked_worse(before, Tracked({"forearm": 1.0}, {"forearm": 0.3}, {"forearm": 0.025},
                                        {"shoulder": 0.10, "elbow": 0.20}, 0.001))
    assert why is not None and "forearm's innovations are 0.025 RMS against 0.02" in why


def test_a_config_that_moves_the_angles_off_absolute_encoders_is_not_written():
    """Where the encoder reads the joint's own angle (a controller's absolute angles: the
    tracker keeps within its σ of them), the tracked angle's whole offset from it counts, its
    constant part included: a config that puts the elbow half a degree off it, steadily (a
    mount's turn about the elbow's axis taken for the elbow's zero), is refused, naming the
    joint; so is one that puts wrist 1 0.03° further off where chance allows 0.014° (the UR5
    twin's figures). Angles as close as before within chance pass, a wider wander included.
    A relative encoder (its count from the power-up pose) is judged by the wander alone."""
    from armfusion.fusion.workbench.heldout import Tracked, reads_its_own_angle, tracked_worse

    chance = {"shoulder": 0.0033, "elbow": 0.0033, "wrist1": 0.0047, "elbow + shoulder": 0.0033}

    def tracked(rms, wander=0.037):
        return Tracked({"forearm": 1.0}, {"forearm": 0.3}, {"forearm": 0.02},
                       {j: wander for j in ("shoulder", "elbow", "wrist1")}, 0.0003, rms, chance)

    before = tracked({"shoulder": 0.092, "elbow": 0.069, "wrist1": 1.19})
    # within chance (3σ: 0.0099° for the shoulder, 0.0141° for wrist 1), though the wander grew
    assert tracked_worse(before, tracked({"shoulder": 0.100, "elbow": 0.05, "wrist1": 1.20}, 0.05)) is None
    why = tracked_worse(before, tracked({"shoulder": 0.092, "elbow": 0.478, "wrist1": 1.19}))
    assert why is not None and "elbow's tracked angle is 0.478° RMS off its encoder" in why
    assert "shoulder" not in why and "wrist1" not in why
    why = tracked_worse(before, tracked({"shoulder": 0.092, "elbow": 0.069, "wrist1": 1.22}))
    assert why is not None and "wrist1's tracked angle is 1.220° RMS off its encoder" in why
    assert "against 1.190° (chance 0.0141°)" in why
    # each joint as close as before, but their sum (the forearm's pitch) further off
    group = {"shoulder": 0.092, "elbow": 0.069, "wrist1": 1.19}
    why = tracked_worse(tracked({**group, "elbow + shoulder": 0.05}),
                        tracked({**group, "elbow + shoulder": 0.4}))
    assert why is not None and "elbow + shoulder's tracked angle is 0.400° RMS off its encoder" in why
    # relative encoders: no whole offset, the wander judged against the same floor
    rel = Tracked({"forearm": 1.0}, {"forearm": 0.3}, {"forearm": 0.02}, {"elbow": 0.037}, 0.0003, {}, chance)
    assert tracked_worse(rel, replace(rel, offset_wander_deg={"elbow": 0.045})) is None
    why = tracked_worse(rel, replace(rel, offset_wander_deg={"elbow": 0.060}))
    assert why is not None
    assert "elbow's tracked angle wanders 0.060° RMS off its encoder against 0.037°" in why
    rng = np.random.default_rng(7)
    assert reads_its_own_angle(0.5 + 0.03 * rng.standard_normal(500), np.full(500, 3.4))
    assert not reads_its_own_angle(35.0 + 0.03 * rng.standard_normal(500), np.full(500, 2.0))


def test_the_chance_floor_comes_from_the_datasheet_noise_and_the_length_judged(wmra):
    """The gate's floor for a tracked angle (:func:`chance_deg`): the readings' noise over the
    part judged, not a hand-set figure. Four times the length halves it; accelerometers
    twice as noisy (the config's fast error √3 times the datasheet noise) double it; a joint
    more accelerometers ride after reads a smaller one than the last joint; a stream taken
    twice as often as the config's rate (resampled) counts no more independent readings."""
    from armfusion.fusion.workbench.heldout import chance_deg
    from armfusion.models.sensor_models import stream_models
    from armfusion.sensors.samples import Recording

    rec, _ = simulate(wmra, "renk-maneuver", 45.0, seed=31)
    t_end = max(float(s.t_s[-1]) for s in rec.streams.values())
    short, long = chance_deg(wmra, rec, t_end - 10.0), chance_deg(wmra, rec, t_end - 40.0)
    for j in wmra.joint_names:
        assert long[j] == pytest.approx(short[j] / 2.0, rel=0.02), j
    sm = stream_models(wmra)
    fast = {s.name: float(np.sqrt(3.0) * np.max(sm[s.name].sigma_counts / np.abs(sm[s.name].gain)))
            for s in wmra.link_accelerometers}
    noisy = replace(wmra, calibration=replace(wmra.calibration, accel_fast_error_g_per_sensor=fast))
    for j, v in chance_deg(noisy, rec, t_end - 10.0).items():
        assert v == pytest.approx(2.0 * short[j], rel=1e-6), j
    first, last = wmra.joint_names[0], wmra.joint_names[-1]
    assert 0.0 < short[first] < short[last]
    # each accelerometer's stream at twice its config's rate, the same readings twice over
    def doubled(s):
        half = np.tile([0.0, 0.5 * np.median(np.diff(s.t_s))], len(s))
        return replace(s, t_s=np.repeat(s.t_s, 2) + half, values=np.repeat(s.values, 2, axis=0))

    twice = Recording({k: doubled(s) if k in fast else s for k, s in rec.streams.items()}, dict(rec.meta))
    for j, v in chance_deg(wmra, twice, t_end - 10.0).items():
        assert v == pytest.approx(short[j], rel=0.02), j


def test_two_rms_figures_differ_by_chance_as_the_floor_says_whatever_the_filter():
    """The argument behind the floor, drawn: an error the model makes (0.3° and a slow swing)
    plus one reading's noise σ through a filter averaging 1, 10 or 50 readings (run in before
    the part, as the tracker is), RMS over N = 600 readings. Across seeded draws the RMS
    spreads by σ/√N (within 15 %), whatever the filter; two equally right figures differ by
    more than 3·√2·σ/√N in under 1 % of draw pairs, and an error 10·√2·σ/√N larger is beyond
    it in every draw."""
    rng = np.random.default_rng(11)
    n, draws, sigma = 600, 400, 0.08
    t = np.arange(n)
    s = 0.3 + 0.2 * np.sin(2 * np.pi * t / n)
    floor = 3.0 * np.sqrt(2.0) * sigma / np.sqrt(n)
    for k in (1, 10, 50):
        a = 1.0 / k
        noise = rng.normal(0.0, sigma, (2, draws, n + 10 * k))  # the filter run in before the part
        filt = np.empty_like(noise)
        filt[..., 0] = noise[..., 0]
        for i in range(1, noise.shape[-1]):
            filt[..., i] = (1 - a) * filt[..., i - 1] + a * noise[..., i]
        filt = filt[..., 10 * k:]
        rms = np.sqrt(np.mean((s + filt) ** 2, axis=-1))
        assert np.std(rms[0]) == pytest.approx(sigma / np.sqrt(n), rel=0.15), k
        assert np.mean(rms[1] - rms[0] > floor) < 0.01, k
        worse = np.sqrt(np.mean((s + 10.0 / 3.0 * floor + filt[1]) ** 2, axis=-1))
        assert np.all(worse - rms[0] > floor), k


def test_written_floors_are_at_least_the_held_out_excess(wmra, turned):
    """What the fit leaves on the held-out part (larger than in sample) sets the floor."""
    from armfusion.fusion.cli.diagnose_write import raise_floors

    fit_part, held = split_in_time(turned)
    d = diagnose(model_from_arm(wmra), fit_part, held_out=held)  # acc4's turn is missing
    cfg = {"calibration": {"accel_unmodelled_g_per_sensor": {"acc4": 1e-4}}}
    raise_floors(cfg, d)
    excess = d.held_out_fit.unmodelled("g")
    per = cfg["calibration"]["accel_unmodelled_g_per_sensor"]
    assert per["acc4"] == pytest.approx(excess["acc4"], rel=1e-3) and per["acc4"] > 5e-3
    assert cfg["calibration"]["accel_unmodelled_g"] == max(per.values())
    # and never below the floor of the config it replaces (the fit's window means do not see
    # what a tracker reading every sample meets)
    cfg2 = {"calibration": {}}
    raise_floors(cfg2, d, wmra)
    per2 = cfg2["calibration"]["accel_unmodelled_g_per_sensor"]
    assert all(per2[s.name] >= wmra.calibration.accel_floor_g(s.name) for s in wmra.link_accelerometers)


def test_cli_add_and_write_judged_on_a_second_recording(tmp_path):
    """`--validate` judges on a second recording: a bias the first recording has and the second
    lacks is refused there, nothing is written (exit 1, the reason said); the history carries
    both columns."""
    import json

    from armfusion.fusion.cli.main import app
    from typer.testing import CliRunner

    runner = CliRunner()
    biased, clean = tmp_path / "biased.csv", tmp_path / "clean.csv"
    for out, seed, extra in ((biased, 41, ["--effect", "accel_bias:acc2=0,0.02,0"]), (clean, 42, [])):
        r = runner.invoke(app, ["simulate", "--scenario", "renk-maneuver", "--duration", "20",
                                "--seed", str(seed), *extra, "--out", str(out)])
        assert r.exit_code == 0, r.output
    written = tmp_path / "w.yaml"
    r = runner.invoke(app, ["diagnose", str(biased), "--config", "wmra", "--add", "accel_bias:acc2",
                            "--validate", str(clean), "--write", str(written), "--json",
                            "--history", str(tmp_path / "h.json"), "--report", str(tmp_path / "r.html")])
    assert r.exit_code == 1, r.output
    doc = json.loads(r.stdout)
    assert "held-out error rose" in doc["add_refused"] and doc["write_refused"] == doc["add_refused"]
    assert doc["written"] is None and not written.exists()
    assert doc["held_out"]["data"] == f"the recording {clean}"
    assert doc["held_out"]["rms_ratio"] > doc["before"]["held_out"]["rms_ratio"]
    assert all(e["held_out_rms_ratio"] is not None for e in doc["ladder"])
    page = (tmp_path / "r.html").read_text(encoding="utf-8")
    assert f"on the held-out data (the recording {clean})" in page


def test_cli_a_recording_too_short_to_hold_out_is_diagnosed_but_never_written(tmp_path):
    from armfusion.fusion.cli.main import app
    from typer.testing import CliRunner

    runner = CliRunner()
    rec = tmp_path / "short.csv"
    r = runner.invoke(app, ["simulate", "--scenario", "renk-maneuver", "--duration", "4", "--seed", "3",
                            "--out", str(rec)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["diagnose", str(rec), "--config", "wmra", "--history", str(tmp_path / "h.json")])
    assert r.exit_code == 0 and "judged on nothing but itself" in r.output
    out = tmp_path / "w.yaml"
    r = runner.invoke(app, ["diagnose", str(rec), "--config", "wmra", "--history", str(tmp_path / "h.json"),
                            "--write", str(out)])
    assert r.exit_code == 2 and "--write needs a part the fit does not see" in r.output and not out.exists()


def test_the_held_out_tracker_check_sees_a_wrong_scale_without_the_truth(tmp_path):
    """acc2 reads 8 % low: tracked with the config that lacks it, acc2's innovations grow and
    the angles wander off the encoders on the held-out part, which the check names; with the
    config that has it, nothing is worse than without."""
    import yaml
    from armfusion.fusion.configfile import load_arm, resolve_config_path
    from armfusion.fusion.workbench.heldout import tracked, tracked_worse
    from armfusion.models.simulator import simulate

    base = yaml.safe_load(resolve_config_path("wmra").read_text(encoding="utf-8"))
    effect = {"effect": "accel_scale", "target": "acc2", "params": {"scale_error": [-0.08, -0.08, -0.08]}}
    arms = {}
    for label, eff in (("right", [*base.get("effects", []), effect]), ("lacking", base.get("effects", []))):
        p = tmp_path / f"{label}.yaml"
        p.write_text(yaml.safe_dump({**base, "effects": eff}), encoding="utf-8")
        arms[label] = load_arm(str(p))
    rec, _ = simulate(arms["lacking"], "renk-maneuver", 20.0, seed=7, effects=[effect])
    t_from = 14.0
    right, lacking = tracked(arms["right"], rec, t_from), tracked(arms["lacking"], rec, t_from)
    assert tracked_worse(lacking, right) is None
    why = tracked_worse(right, lacking)
    assert why is not None and "acc2's innovations" in why


@pytest.fixture(scope="module")
def twin_turned(ur5, tmp_path_factory):
    """The UR5 twin (tools/twin_ur5.py, seed 1: the forearm's board turned -0.97° about the
    shoulder's, elbow's and wrist 1's axes, the wrist's -0.45° about wrist 1's), imported, its
    scales and mounts fitted: what the twin draws, and the diagnosis."""
    from armfusion.fusion.cli.main import app
    from typer.testing import CliRunner

    from tools.twin_ur5 import make_twin, write_csv

    tmp = tmp_path_factory.mktemp("twin")
    twin = make_twin(seed=1, duration_s=20.0, arm=ur5)
    r = CliRunner().invoke(app, ["import", str(write_csv(twin, tmp / "twin.csv")), "--map", "ur5-csv",
                                 "--config", "ur5_two_imu", "--out", str(tmp / "twin.mcap"), "--json"])
    assert r.exit_code == 0, r.output
    from armfusion.sensors.recording import read_recording

    data = data_from_recording(ur5, read_recording(tmp / "twin.mcap"), window=WINDOW)
    m = model_from_arm(ur5).with_effects([build_effect(ur5, e, s.name) for s in ur5.link_accelerometers
                                          for e in ("accel_scale", "mount_rotation")])
    return twin, diagnose(m, data)


def test_a_held_turn_is_read_off_encoders_that_give_the_joints_own_angles(ur5, twin_turned):
    """The fit holds each board's turn about its joint's axis at none and lets the joints'
    zeros take it; with a controller's angles (the encoders read the joints' own angles) the
    written fit books it back to the board, so that the tracker, which finds the zeros from
    gravity through the board, puts the forearm's pitch where the controller does. The turn
    comes out within 0.05° of the twin's (the fit also leaves the clocks' offsets unmodelled
    here), and the zeros at the encoders'. Not where the tracker says the encoders are
    relative, nor where the zeros are further from the encoders' than a turn's prior allows
    (a relative encoder counting from 10° off the joint's zero)."""
    from armfusion.fusion.workbench.zeros import turns_from_encoder_zeros

    twin, d = twin_turned
    fit = without_bound(d)
    z = turns_from_encoder_zeros(fit, d.data, d.gauges, ur5.joint_names)
    assert z is not None and set(z.joints) == {"shoulder", "elbow", "wrist1"}
    drawn = {e["target"]: np.asarray(e["params"]["rotvec_rad"]) for e in twin.effects
             if e["effect"] == "mount_rotation"}
    for element, truth in (("forearm.mount_rotation[z]", drawn["forearm"][2]),
                           ("wrist.mount_rotation[y]", drawn["wrist"][1])):
        value, sigma = z.turns[element]
        assert abs(np.degrees(value - truth)) < 0.05, element
        assert 0.0 < np.degrees(sigma) < 0.05, element
        assert not z.fit.held[z.fit.names.index(element)]
    for j in z.joints:
        i = z.fit.names.index(f"{j}.joint_offset[offset]")
        assert z.fit.x[i] + z.fit.q_ref_rad[ur5.joint_names.index(j)] == pytest.approx(0.0, abs=1e-12)
    assert turns_from_encoder_zeros(fit, d.data, d.gauges, ("base", "shoulder")) is None
    q_ref = fit.q_ref_rad.copy()
    q_ref[ur5.joint_names.index("elbow")] += np.radians(10.0)
    assert turns_from_encoder_zeros(replace(fit, q_ref_rad=q_ref), d.data, d.gauges, ur5.joint_names) is None
