"""``tools/bench_null.py``: the rates' Wilson intervals, and the quick run writes its section
(every group's row, the target line) to the file ``--out`` names and nowhere else."""

from __future__ import annotations

from pathlib import Path

import pytest

from tools import bench_null
from tools.benchdoc import bench_texts


def test_wilson_interval_of_a_rate():
    """0 of 200 still allows up to 1.9 %; 10 of 200 (5 %) is 2.7-9.0 %: the interval, not the
    count, says whether a ≤ 5 % target is shown."""
    assert bench_null.wilson(0, 200) == pytest.approx((0.0, 0.01884), abs=1e-4)
    assert bench_null.wilson(10, 200) == pytest.approx((0.02737, 0.08962), abs=1e-4)
    assert bench_null._rate(10, 200) == "10 of 200 (5.0 %, 2.7–9.0 %)"


def test_the_quick_run_writes_its_section_to_the_file_it_is_given(tmp_path: Path, capsys) -> None:
    before = bench_texts()
    out = tmp_path / "null.md"
    bench_null.main(["--quick", "--only", "renk-maneuver 30 s", "--out", str(out)])
    text = out.read_text(encoding="utf-8")
    assert text.startswith("## False alarms on clean recordings")
    assert "| shipped, `renk-maneuver`, 30 s | 0 of 4 (0.0 %, 0.0–49.0 %) |" in text
    assert "| target ≤ 5 % over all | met | met | met |" in text
    assert "The score tests one by one on `renk-maneuver`" in text
    assert bench_texts() == before
    assert f"wrote {out}" in capsys.readouterr().out
