"""Shared by the benchmark scripts: write one section of docs/benchmarks.md in place.

Each script owns the text between ``<!-- NAME:start -->`` and ``<!-- NAME:end -->``, so
several scripts share the file and re-running one replaces only its own section.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import subprocess
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

BENCH_DOC = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
HEADLINE = BENCH_DOC.parent / "headline.json"
"""The few figures the README's table shows, each written by the tool that measured it, with
the date and commit it was measured on (``tools/headline.py`` renders them)."""
HEADER = (
    "# Benchmarks\n\n"
    "Measured by the scripts in `tools/`, each of which rewrites its own section below.\n"
    "Timings are wall-clock on the machine named in each section; where a baseline exists it\n"
    "runs in the same process, on the same data, so the ratio is the figure to trust.\n"
)


def machine_line() -> str:
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"NumPy {np.__version__}")


def write_section(name: str, body_md: str, path: Path = BENCH_DOC) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    text = path.read_text() if path.exists() else HEADER
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    block = f"{start}\n{body_md.rstrip()}\n{end}"
    if start in text and end in text:
        text = re.sub(re.escape(start) + r".*?" + re.escape(end), lambda _m: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.write_text(text)
    return path


def publish(name: str, body_md: str, out: Path | None, quick: bool = False) -> None:
    """A tool's section: to ``out`` when given, else (not ``quick``) into its place in
    docs/benchmarks.md; says where."""
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
    root = BENCH_DOC.parent.parent
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


def record_headline(name: str, rows: list[dict], path: Path = HEADLINE) -> Path:
    """Keep a tool's headline rows (each ``{"what", "armfusion", "baseline"}``: the figure
    in words, ours, and the baseline's in the same run or "" where there is none) under its
    name in ``docs/headline.json``, with when and where they were measured."""
    data = json.loads(path.read_text(encoding="utf-8")) if path.exists() else {}
    data[name] = {"rows": rows, **measured_on()}
    path.write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return path
