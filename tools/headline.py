"""Render the README's table of headline results from ``docs/headline.json``.

Each benchmark tool records its own headline rows there when it writes its section of
docs/benchmarks.md (``tools.benchdoc.record_headline``), with the date, commit and machine
it measured them on; this script writes them into the README between its markers.
``--check`` writes nothing and exits 1 when the README's table is not what the JSON gives.

    python tools/headline.py           # after a benchmark ran
    python tools/headline.py --check   # the test suite
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
HEADLINE = ROOT / "docs" / "headline.json"
START, END = "<!-- headline:start -->", "<!-- headline:end -->"

ORDER = ("bench_startup_realistic", "bench_track_realistic", "bench_heading_broad", "bench_real_rig")
"""The sections in the order a reader meets the jobs: startup, tracking, heading, real data."""


def table(data: dict) -> str:
    lines = ["| result | armfusion | baseline, same run | measured |", "| --- | --- | --- | --- |"]
    for name in sorted(data, key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n)):
        entry = data[name]
        when = f"{entry['date']}, `{entry['commit']}`"
        for row in entry["rows"]:
            lines.append(f"| {row['what']} | {row['armfusion']} | {row.get('baseline') or '–'} | {when} |")
    return "\n".join(lines)


def render(readme: str, data: dict) -> str:
    block = f"{START}\n{table(data)}\n{END}"
    if START not in readme or END not in readme:
        raise SystemExit(f"README.md has no {START} … {END} block to write into")
    return re.sub(re.escape(START) + r".*?" + re.escape(END), lambda _m: block, readme, flags=re.S)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when the README's table is stale")
    a = ap.parse_args(argv)
    data = json.loads(HEADLINE.read_text(encoding="utf-8")) if HEADLINE.exists() else {}
    text = README.read_text(encoding="utf-8")
    new = render(text, data)
    if a.check:
        if new != text:
            print("README.md's headline table is stale: run python tools/headline.py", file=sys.stderr)
            return 1
        return 0
    README.write_text(new, encoding="utf-8")
    rows = sum(len(e["rows"]) for e in data.values())
    print(f"wrote the headline table of {README.relative_to(ROOT)} ({rows} rows)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
