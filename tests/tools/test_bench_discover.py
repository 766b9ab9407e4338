"""``tools/bench_discover.py``: ``--maneuvers planned`` plays the shipped plan (its poses,
with each seed's chair), an unsafe maneuver file is refused, and a draw moved to a sweep
that shows other pairs keeps what both show and gives every pair of the new sweep its share."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.planner import maneuver_problems
from armfusion.models.effects import all_effects

from tools import bench_discover as bd


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


def test_planned_sweep_holds_the_shipped_plans_poses_with_each_seeds_chair(arm) -> None:
    sweep = bd.sweep_named(arm, "planned", None)
    plan = sweep.maneuver
    assert sweep.label == "config/maneuvers/wmra-60s.yaml"
    assert sweep.duration_s == pytest.approx(60.0, abs=0.01)
    assert not maneuver_problems(arm, plan)
    mid = np.array([(t0 + t1) / 2 for _, t0, t1 in plan.schedule()])
    a, b = sweep.scenario(arm, 3000), sweep.scenario(arm, 3001)
    np.testing.assert_allclose(a.state(mid).q_rad, plan.poses_rad, atol=1e-9)
    np.testing.assert_allclose(b.state(mid).q_rad, plan.poses_rad, atol=1e-9)
    # the chair's tilt is the seed's, as `simulate --maneuver --seed` draws it
    assert not np.allclose(a.state(mid[:1]).R_WB, b.state(mid[:1]).R_WB)
    assert bd.sweep_named(arm, "renk-maneuver", None).scenario(arm, 3000) == "renk-maneuver"


def test_a_maneuver_file_outside_the_joint_limits_is_refused(arm, tmp_path: Path) -> None:
    data = yaml.safe_load(bd.SHIPPED_PLAN.read_text(encoding="utf-8"))
    data["poses"][1]["pose_deg"][1] = 400.0
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ValueError, match="bad.yaml: not safe to play on"):
        bd.sweep_named(arm, str(bad), None)


def test_a_redrawn_draw_keeps_the_shared_pairs_and_spreads_evenly_over_the_new_pool(arm) -> None:
    lib = [e for e in all_effects(arm) if e.name not in bd.NOT_DRAWN]
    base_pool, pool = lib[:40], lib[10:50]  # 30 shared, 10 lost, 10 new
    rng, again = np.random.default_rng(7), np.random.default_rng(8)
    names = {e.block_name for e in pool}
    counts: Counter = Counter()
    kept = shared = 0
    for _ in range(3000):
        drawn = bd.draw_hidden(base_pool, rng)
        moved = bd.redraw(drawn, base_pool, pool, again)
        blocks = [bd._block(h) for h in moved]
        assert len(moved) == len(drawn) and len(set(blocks)) == len(blocks)
        assert set(blocks) <= names
        for h in drawn:
            if bd._block(h) in names:
                shared += 1
                kept += any(m is h for m in moved)
        counts.update(blocks)
    # a shared pair stays unless its slot goes to a new pair (10 of 40): about 3 in 4
    assert kept / shared == pytest.approx(0.75, abs=0.03)
    # every pair of the new pool about equally often (7500 slots over 40 pairs: 187 each,
    # Poisson σ 14): lost and new pairs are not under- or over-drawn
    per = np.array([counts[n] for n in names])
    assert per.min() > 187 - 5 * 14 and per.max() < 187 + 5 * 14
