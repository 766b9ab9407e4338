"""Render the table of headline results from ``docs/headline.json`` into the README and the
benchmarks' index (docs/benchmarks.md).

Each benchmark tool records its own headline rows there when it writes its section of the
benchmark pages (``tools.benchdoc.record_headline``), with the date, commit and machine it
measured them on; this script writes them into both files between their markers, each row
linking the page its section is on. ``--check`` writes nothing and exits 1 when either
table is not what the JSON gives.

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
sys.path.insert(0, str(ROOT))

from tools.benchdoc import BENCH_DOC, PAGES, page_for  # noqa: E402

README = ROOT / "README.md"
HEADLINE = ROOT / "docs" / "headline.json"
TARGETS = {README: "docs/", BENCH_DOC: ""}
"""Each file the table goes into, and the path from it to docs/ (for the links to the pages)."""
START, END = "<!-- headline:start -->", "<!-- headline:end -->"

ORDER = ("bench_startup_realistic", "bench_track_realistic", "bench_heading_broad", "bench_real_rig",
         "bench_workbench_twin")
"""The sections in the order a reader meets the jobs: startup, tracking, heading, real data,
the workbench."""


def table(data: dict, to_docs: str = "docs/") -> str:
    lines = ["| result | armfusion | baseline, same run | measured |", "| --- | --- | --- | --- |"]
    for name in sorted(data, key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n)):
        entry = data[name]
        page = page_for(name)
        title = PAGES.get(page.stem, (page.stem,))[0]
        when = (f"{entry['date']}, `{entry['commit']}`, "
                f"[{title[0].lower() + title[1:]}]({to_docs}benchmarks/{page.name})")
        for row in entry["rows"]:
            lines.append(f"| {row['what']} | {row['armfusion']} | {row.get('baseline') or '–'} | {when} |")
    return "\n".join(lines)


def render(text: str, data: dict, to_docs: str = "docs/", where: str = "README.md") -> str:
    block = f"{START}\n{table(data, to_docs)}\n{END}"
    if START not in text or END not in text:
        raise SystemExit(f"{where} has no {START} … {END} block to write into")
    return re.sub(re.escape(START) + r".*?" + re.escape(END), lambda _m: block, text, flags=re.S)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when the README's table is stale")
    a = ap.parse_args(argv)
    data = json.loads(HEADLINE.read_text(encoding="utf-8")) if HEADLINE.exists() else {}
    stale = []
    for path, to_docs in TARGETS.items():
        where = str(path.relative_to(ROOT))
        text = path.read_text(encoding="utf-8")
        new = render(text, data, to_docs, where)
        if a.check:
            if new != text:
                stale.append(where)
            continue
        path.write_text(new, encoding="utf-8")
        rows = sum(len(e["rows"]) for e in data.values())
        print(f"wrote the headline table of {where} ({rows} rows)")
    if stale:
        print(f"the headline table of {', '.join(stale)} is stale: run python tools/headline.py",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
