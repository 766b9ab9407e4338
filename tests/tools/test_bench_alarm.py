"""``tools/bench_alarm.py``: the false-alarm rate's exact Poisson interval, its options
refused naming what, and a small run writing its section to the file ``--out`` names."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tools import bench_alarm
from tools.benchdoc import bench_texts


def test_poisson_interval_of_a_false_alarm_rate():
    """No alarm in 5 units (of 20 h) still allows up to 0.74 per unit: 100 clean hours with
    none is what shows a rate of at most 1 per 20 h; 2 in 10 units is 0.024-0.72."""
    assert bench_alarm.poisson_interval(0, 5.0) == pytest.approx((0.0, 0.7378), abs=1e-4)
    assert bench_alarm.poisson_interval(2, 10.0) == pytest.approx((0.02422, 0.7225), abs=1e-4)


@pytest.mark.parametrize(("argv", "message"), [
    (["--seeds", "1002,x"], "--seeds: comma-separated integers, not '1002,x'"),
    (["--kinds", "mount_rotation,sagging"], "--kinds: one or more of mount_rotation, bias_jump, "
                                            "hard_iron \\(got 'sagging'\\)"),
    (["--jobs", "0"], "--jobs >= 1"),
])
def test_bad_options_are_refused_naming_what(argv, message, capsys):
    with pytest.raises(SystemExit):
        bench_alarm.main(argv)
    assert re.search(message, capsys.readouterr().err)


def test_a_small_run_writes_its_section_to_the_file_it_is_given(tmp_path: Path, capsys):
    before = bench_texts()
    out = tmp_path / "alarm.md"
    bench_alarm.main(["--kinds", "hard_iron", "--seeds", "3", "--duration", "40", "--clean-hours", "0.004",
                      "--clean-duration", "15", "--out", str(out)])
    text = out.read_text(encoding="utf-8")
    assert text.startswith("## The online model-change alarm")
    assert "this run has fewer: 1 hard_iron, 0.0 clean hours" in text
    assert "| hard_iron | 1 | 20.0 uT |" in text
    assert "recordings of 15 s): " in text and "exact Poisson 95 % interval" in text
    assert bench_texts() == before
    assert f"wrote {out}" in capsys.readouterr().out


def test_the_cost_baseline_is_the_same_tracker_without_the_alarm_s_work():
    """``--cost`` compares the tracker with a stand-in alarm that does nothing: on a recording
    with a 2° mount turn the real alarm names it and the stand-in raises nothing, while every
    joint estimate is the same until the real alarm down-weights the sensor (the one thing an
    alarm does to the estimate)."""
    from tools.bench_track import calibrated_wmra

    arm = calibrated_wmra()
    rec, _ = bench_alarm.simulate(arm, "daily-use", 90.0, seed=1003)
    rec = bench_alarm.mount_turned(rec, "acc4", 60.0, np.radians([2.0, 0.0, 0.0]))
    real, _ = bench_alarm.start_from_recording(arm, rec)
    silent, _ = bench_alarm.start_from_recording(arm, rec)
    silent.alarm = bench_alarm.SilentAlarm()
    a, b = real.run(rec), silent.run(rec)
    assert [al.sensor for al in real.alarm.raised] == ["acc4"]
    assert silent.alarm.raised == ()
    t_raised = real.alarm.raised[0].raised_s
    before = a.t_s <= t_raised
    assert before.sum() > 1000
    assert np.array_equal(a.q_rad[before], b.q_rad[before])
