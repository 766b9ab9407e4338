"""``tools/bench_maneuver.py --quick``: the smoke run writes its section, with both maneuvers'
rows, to the file ``--out`` names (keeping what else it holds) and nowhere else."""

from __future__ import annotations

from pathlib import Path

from tools import bench_maneuver
from tools.benchdoc import bench_texts


def test_the_quick_run_writes_its_section_to_the_file_it_is_given(tmp_path: Path, capsys) -> None:
    before = bench_texts()
    out = tmp_path / "bench.md"
    out.write_text("# Benchmarks\n\nsomething else\n", encoding="utf-8")
    fig = tmp_path / "sigma.png"
    bench_maneuver.main(["--quick", "--out", str(out), "--figure", str(fig)])
    text = out.read_text(encoding="utf-8")
    assert text.startswith("# Benchmarks\n\nsomething else\n")  # kept
    assert "<!-- bench_maneuver:start -->" in text and "<!-- bench_maneuver:end -->" in text
    rows = [line for line in text.splitlines() if line.startswith(("| planned 30 s", "| renk-maneuver 60 s"))]
    assert len(rows) == 2
    assert "fitted σ over predicted σ" in text and "Target: the planned maneuver's worst joint" in text
    # the figure's predictions: planned 20 and 30 s, renk-maneuver 30 and 60 s, and the drawing
    assert sum(line.startswith(("| planned | ", "| renk-maneuver | ")) for line in text.splitlines()) == 4
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert bench_texts() == before  # the benchmark pages untouched
    assert f"written to {out}" in capsys.readouterr().out
