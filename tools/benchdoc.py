"""Shared by the benchmark scripts: write one section of the benchmark pages in place.

The figures live in ``docs/benchmarks/``, one page per area (startup, tracking, the service,
...); ``docs/benchmarks.md`` is their index. Each script owns the text between
``<!-- NAME:start -->`` and ``<!-- NAME:end -->`` on its area's page, so several scripts share a
page and re-running one replaces only its own section. Which page a section goes to is decided
here, in one place (``page_for``): a tool calls ``write_section(NAME, text)`` and need not know.

    python tools/benchdoc.py reroute MERGE_HEAD   # a branch's sections from the one-file layout
    python tools/benchdoc.py reroute --file OLD.md --all
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

ROOT = Path(__file__).resolve().parent.parent
BENCH_DOC = ROOT / "docs" / "benchmarks.md"
"""The index of the benchmark pages (it holds no section of its own)."""
BENCH_DIR = ROOT / "docs" / "benchmarks"
HEADLINE = BENCH_DOC.parent / "headline.json"
"""The few figures the README's table shows, each written by the tool that measured it, with
the date and commit it was measured on (``tools/headline.py`` renders them)."""

PAGES = {
    "startup": ("Startup calibration",
                "The startup solver on 10,000 random still poses, with the sensors as configured "
                "and with datasheet-typical unmodelled errors, against the sequential method."),
    "calibration": ("Calibrated by a maneuver, the chair parked",
                    "The WMRA's sensors identified from their own maneuver, then started; the "
                    "planned maneuver; how fast the identification runs."),
    "calibration-ramp": ("Calibrated by a maneuver on a ramp",
                         "The same as the parked chair's, the chair parked in turn on a ramp."),
    "tracking": ("Tracking",
                 "The tracker against the truth, on ideal and on imperfect sensors; its innovations "
                 "while the chair drives; the online model-change alarm."),
    "real-data": ("Real recordings",
                  "The one-joint IMU rig, the BROAD hand-held IMU's heading, importing a ROS bag."),
    "workbench": ("The workbench and an industrial arm",
                  "The model workbench's false alarms, detection power and discovery; the UR5 twin "
                  "set up from the docs."),
    "service": ("The service",
                "The fusion node through Zenoh: latency, CPU and losses at each rate and batch, "
                "and beside a hostile publisher."),
    "service-load": ("The service beside a busy machine",
                     "The fusion node and the demo with every core kept busy beside them."),
    "speed": ("Speed",
              "Kinematics, the simulator, the tracker at two revisions and what the alarm costs."),
}
"""Each page of ``docs/benchmarks/``: its title and the one line the index and the page open with."""

SECTION_PAGES = {
    "bench_startup": "startup", "bench_startup_realistic": "startup",
    "bench_calibrated": "calibration", "bench_calibrated_inclinometer": "calibration",
    "bench_calibrated_references": "calibration", "bench_maneuver": "calibration",
    "bench_identify": "calibration",
    "bench_calibrated_ramp": "calibration-ramp", "bench_calibrated_ramp_inclinometer": "calibration-ramp",
    "bench_calibrated_ramp_references": "calibration-ramp",
    "bench_track": "tracking", "bench_track_realistic": "tracking", "bench_drive_whiteness": "tracking",
    "bench_alarm": "tracking",
    "bench_real_rig": "real-data", "bench_heading_broad": "real-data", "bench_import_bag": "real-data",
    "bench_workbench": "workbench", "bench_discover": "workbench", "bench_null": "workbench",
    "bench_workbench_twin": "workbench", "bench_real_arm": "workbench",
    "demo-cpu-hog": "service-load",
    "bench_kinematics": "speed", "bench_simulate": "speed", "bench_track_revisions": "speed",
    "bench_alarm_cost": "speed", "bench_imu_speed": "speed",
}
"""Every section's page, by the name its tool writes it under."""

SECTION_FAMILIES = (
    (re.compile(r"soak-.*-cpu-hog"), "service-load"),    # tools/soak.py --cpu-hog
    (re.compile(r"soak-.*"), "service"),                 # soak-<rate>hz-<batch>ms[-hostile]
    (re.compile(r"bench_calibrated_ramp.*"), "calibration-ramp"),  # bench_calibrated.py's variants
    (re.compile(r"bench_calibrated.*"), "calibration"),
)
"""Sections whose names a tool composes from its options: the first pattern that matches the
whole name decides."""

INDEX_BLOCK = "headline"
"""The one marked block of the index: the headline table ``tools/headline.py`` writes."""

UNMAPPED = "more"
"""Where a section no rule names lands (and the docs test names it, to be given a page)."""

HEADER = (
    "Measured by the scripts in `tools/`, each of which rewrites its own section below.\n"
    "Timings are wall-clock on the machine named in each section; where a baseline exists it\n"
    "runs in the same process, on the same data, so the ratio is the figure to trust.\n"
    "The index of every page, and how to re-run them, is [Benchmarks](../benchmarks.md).\n"
)


def page_for(name: str) -> Path:
    """The page of ``docs/benchmarks/`` the section ``name`` belongs on."""
    page = SECTION_PAGES.get(name)
    if page is None:
        page = next((p for rx, p in SECTION_FAMILIES if rx.fullmatch(name)), UNMAPPED)
    return BENCH_DIR / f"{page}.md"


def is_mapped(name: str) -> bool:
    return name in SECTION_PAGES or any(rx.fullmatch(name) for rx, _ in SECTION_FAMILIES)


def _page_header(path: Path) -> str:
    title, line = PAGES.get(path.stem, ("More", "Sections not yet given a page."))
    return f"# Benchmarks: {title}\n\n{line}\n\n{HEADER}"


def sections(text: str) -> dict[str, str]:
    """Every ``<!-- NAME:start -->`` ... ``<!-- NAME:end -->`` section of a page, its body
    without the markers, in the page's order."""
    found = re.finditer(r"<!-- (\S+):start -->\n(.*?)\n?<!-- \1:end -->", text, flags=re.S)
    return {m.group(1): m.group(2) for m in found}


def bench_texts() -> dict[str, str]:
    """The text of the index and of every benchmark page, by path (to see that a run wrote
    nothing)."""
    paths = [BENCH_DOC, *sorted(BENCH_DIR.glob("*.md"))] if BENCH_DIR.exists() else [BENCH_DOC]
    return {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8") for p in paths if p.exists()}


def machine_line() -> str:
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"NumPy {np.__version__}")


def write_section(name: str, body_md: str, path: Path | None = None) -> Path:
    """Put ``body_md`` as the section ``name``: on its area's page (``page_for``) unless
    ``path`` names another file (a tool's ``--out``); replaces the section where it is, else
    appends it. Returns the file written."""
    if path is None or Path(path).resolve() == BENCH_DOC:
        path = page_for(name)
        if not is_mapped(name):
            print(f"benchdoc: section {name!r} has no page: it went to {path.relative_to(ROOT)}; "
                  "give it one in SECTION_PAGES of tools/benchdoc.py", file=sys.stderr)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = path.read_text(encoding="utf-8") if path.exists() else _page_header(path)
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    block = f"{start}\n{body_md.rstrip()}\n{end}"
    if start in text and end in text:
        text = re.sub(re.escape(start) + r".*?" + re.escape(end), lambda _m: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.write_text(text, encoding="utf-8")
    return path


def publish(name: str, body_md: str, out: Path | None, quick: bool = False) -> None:
    """A tool's section: to ``out`` when given, else (not ``quick``) into its place on its
    benchmark page; says where."""
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(body_md + "\n", encoding="utf-8")
        print(f"wrote {out}")
    elif not quick:
        print("wrote", write_section(name, body_md))


def wilson(k: int, n: int) -> tuple[float, float]:
    """The Wilson 95 % interval on a proportion of ``k`` in ``n``."""
    ci = binomtest(k, n).proportion_ci(0.95, method="wilson")
    return float(ci.low), float(ci.high)


def measured_on() -> dict:
    """The date (UTC), the commit (``+`` when the work tree's code differed from it: changes to
    docs/ and the README alone do not count) and the machine a figure is measured on."""
    root = ROOT
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                                text=True, timeout=10).stdout.strip()
        # changes to the docs alone (a benchmark writing its section) do not make a figure's code
        # other than the commit's
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                ":!docs", ":!README.md"], cwd=root, capture_output=True, text=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit, dirty = "", ""
    return {"date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
            "commit": (commit or "unknown") + ("+" if dirty else ""), "machine": machine_line()}


def record_headline(name: str, rows: list[dict], path: Path = HEADLINE, measured: dict | None = None) -> Path:
    """Keep a tool's headline rows (each ``{"what", "armfusion", "baseline"}``: the figure
    in words, ours, and the baseline's in the same run or "" where there is none) under its
    name in ``docs/headline.json``, with when and where they were measured (``measured``: as
    :func:`measured_on` gave it then, for figures kept from an earlier run; default now)."""
    data = json.loads(path.read_text(encoding="utf-8")) if path.exists() else {}
    data[name] = {"rows": rows, **(measured_on() if measured is None else measured)}
    path.write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------------------
# sections from the one-file layout (a branch that wrote docs/benchmarks.md whole)


def _git_text(rev: str, rel: str = "docs/benchmarks.md") -> str:
    done = subprocess.run(["git", "show", f"{rev}:{rel}"], cwd=ROOT, capture_output=True, text=True,
                          timeout=30)
    if done.returncode != 0:
        raise SystemExit(f"reroute: cannot read {rel} at {rev}: {done.stderr.strip()}")
    return done.stdout


def _base_sections(rev: str) -> dict[str, str]:
    """The sections at the merge base of HEAD and ``rev``, from its one file and its pages."""
    base = subprocess.run(["git", "merge-base", "HEAD", rev], cwd=ROOT, capture_output=True, text=True,
                          timeout=30).stdout.strip()
    if not base:
        raise SystemExit(f"reroute: HEAD and {rev} have no merge base")
    listed = subprocess.run(["git", "ls-tree", "-r", "--name-only", base, "--", "docs/benchmarks.md",
                             "docs/benchmarks/"], cwd=ROOT, capture_output=True, text=True,
                            timeout=30).stdout.split()
    found: dict[str, str] = {}
    for rel in listed:
        found.update(sections(_git_text(base, rel)))
    return found


def reroute(source: dict[str, str], base: dict[str, str] | None) -> list[str]:
    """Write each section of ``source`` onto its page, unless ``base`` is given and holds it
    unchanged (a section the other side did not touch keeps the current page's text). Returns
    one line per section: what was written where, and where both sides changed it."""
    current: dict[str, str] = {}
    for path in BENCH_DIR.glob("*.md"):
        current.update(sections(path.read_text(encoding="utf-8")))
    said = []
    for name, body in source.items():
        if name == INDEX_BLOCK:
            continue
        if base is not None and base.get(name) == body:
            continue
        if current.get(name) == body:
            continue
        both = base is not None and name in current and current[name] != base.get(name)
        path = write_section(name, body)
        said.append(f"{name} -> {path.relative_to(ROOT)}"
                    + ("  (changed on both sides: the source's text kept; `git diff` shows the other)"
                       if both else ""))
    return said


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Route the sections of a one-file docs/benchmarks.md (a branch from before the "
                    "benchmark pages) onto their pages in docs/benchmarks/.")
    sub = ap.add_subparsers(dest="command", required=True)
    rr = sub.add_parser("reroute", help="write a branch's (or a file's) sections onto their pages")
    rr.add_argument("rev", nargs="?", help="a git revision (e.g. MERGE_HEAD) whose docs/benchmarks.md "
                                           "to read; only the sections it changed since the merge base "
                                           "with HEAD are written")
    rr.add_argument("--file", type=Path, help="read this file instead of a revision's")
    rr.add_argument("--all", action="store_true", help="write every section, changed or not")
    a = ap.parse_args(argv)
    if (a.rev is None) == (a.file is None):
        ap.error("reroute takes a revision or --file, one of them")
    text = a.file.read_text(encoding="utf-8") if a.file else _git_text(a.rev)
    source = sections(text)
    base = None if a.all or a.file else _base_sections(a.rev)
    said = reroute(source, base)
    print("\n".join(said) if said else "no section to write: the pages already hold them")
    print(f"({len(source)} sections read, {len(said)} written)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
