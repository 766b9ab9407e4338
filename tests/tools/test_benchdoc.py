"""``tools/benchdoc.py``: a tool names its section and the section lands on its area's page of
docs/benchmarks/, whatever path the tool passes for the one-file layout; a branch's one-file
docs/benchmarks.md is rerouted section by section; the committed pages agree with the map."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tools import benchdoc


@pytest.fixture
def pages(tmp_path: Path, monkeypatch) -> Path:
    """The benchmark pages in a scratch folder."""
    monkeypatch.setattr(benchdoc, "ROOT", tmp_path)
    monkeypatch.setattr(benchdoc, "BENCH_DOC", tmp_path / "docs" / "benchmarks.md")
    monkeypatch.setattr(benchdoc, "BENCH_DIR", tmp_path / "docs" / "benchmarks")
    return tmp_path / "docs" / "benchmarks"


def test_a_section_goes_to_its_areas_page_and_replaces_itself(pages: Path) -> None:
    assert benchdoc.write_section("bench_track", "## Tracker\n\nfirst") == pages / "tracking.md"
    benchdoc.write_section("bench_alarm", "## Alarm")
    benchdoc.write_section("bench_track", "## Tracker\n\nsecond")
    text = (pages / "tracking.md").read_text()
    assert text.startswith("# Benchmarks: Tracking\n")
    assert "second" in text and "first" not in text
    assert list(benchdoc.sections(text)) == ["bench_track", "bench_alarm"]
    # a tool that still passes the one-file path is routed the same
    assert benchdoc.write_section("bench_kinematics", "## K", benchdoc.BENCH_DOC) == pages / "speed.md"
    assert not benchdoc.BENCH_DOC.exists()


def test_names_a_tool_composes_find_their_page(pages: Path) -> None:
    assert benchdoc.page_for("soak-150hz-10ms").name == "service.md"
    assert benchdoc.page_for("soak-150hz-10ms-hostile").name == "service.md"
    assert benchdoc.page_for("soak-150hz-10ms-cpu-hog").name == "service-load.md"
    assert benchdoc.page_for("bench_calibrated_ramp_references").name == "calibration-ramp.md"
    assert benchdoc.page_for("bench_calibrated_inclinometer_references").name == "calibration.md"


def test_an_unmapped_section_is_kept_and_named(pages: Path, capsys) -> None:
    path = benchdoc.write_section("bench_new_thing", "## New")
    assert path == pages / "more.md" and "bench_new_thing" in path.read_text()
    assert "bench_new_thing" in capsys.readouterr().err


def test_an_out_file_gets_the_section_and_no_page_is_touched(pages: Path, tmp_path: Path) -> None:
    out = tmp_path / "out.md"
    assert benchdoc.write_section("bench_track", "## Tracker", out) == out
    assert "<!-- bench_track:start -->" in out.read_text() and not pages.exists()


def test_a_one_file_branch_is_rerouted_only_where_it_changed(pages: Path) -> None:
    benchdoc.write_section("bench_track", "## Tracker\n\nours, newer")
    benchdoc.write_section("bench_startup", "## Startup\n\nas at the base")

    def one_file(**bodies: str) -> str:
        return "# Benchmarks\n\n" + "\n\n".join(f"<!-- {n}:start -->\n{b}\n<!-- {n}:end -->"
                                                for n, b in bodies.items()) + "\n"

    base = benchdoc.sections(one_file(bench_track="## Tracker\n\nold",
                                      bench_startup="## Startup\n\nas at the base"))
    theirs = benchdoc.sections(one_file(bench_track="## Tracker\n\nold",
                                        bench_startup="## Startup\n\nre-run on the branch",
                                        bench_null="## Null\n\nnew on the branch"))
    said = benchdoc.reroute(theirs, base)
    assert [s.split()[0] for s in said] == ["bench_startup", "bench_null"]
    assert "re-run on the branch" in (pages / "startup.md").read_text()
    assert "new on the branch" in (pages / "workbench.md").read_text()
    assert "ours, newer" in (pages / "tracking.md").read_text()  # the branch did not touch it


def test_the_committed_pages_hold_each_section_where_the_map_puts_it() -> None:
    """No tool's section on the index, none on a page the map does not name, none unmapped; every
    page linked from the index and only mapped pages present."""
    index = benchdoc.BENCH_DOC.read_text(encoding="utf-8")
    assert set(benchdoc.sections(index)) == {benchdoc.INDEX_BLOCK}  # tools/headline.py's table only
    for path in sorted(benchdoc.BENCH_DIR.glob("*.md")):
        names = list(benchdoc.sections(path.read_text(encoding="utf-8")))
        assert path.stem in benchdoc.PAGES, (f"{path.name} is no page of PAGES: give its sections "
                                             f"{names} a page in SECTION_PAGES of tools/benchdoc.py")
        assert f"(benchmarks/{path.name})" in index, f"the index does not link {path.name}"
        for name in names:
            assert benchdoc.is_mapped(name), f"{name} has no page in tools/benchdoc.py"
            assert benchdoc.page_for(name) == path, f"{name} is on {path.name}, mapped elsewhere"
    mkdocs = (benchdoc.ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    assert all(re.search(rf"benchmarks/{p}\.md", mkdocs) for p in benchdoc.PAGES)
