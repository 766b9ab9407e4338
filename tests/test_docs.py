"""The documentation as a reader meets it: the site builds with no broken link or page left
out, the generated references match the code, no page speaks of how the software was
made, and the tutorial's commands run as written."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
README = ROOT / "README.md"
BIN = Path(sys.executable).parent


def _user_pages() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def test_the_site_builds_strictly(tmp_path):
    """``mkdocs build --strict``: a broken link, a missing anchor, a page the navigation
    leaves out or an API entry that does not resolve fails it."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q",
                           "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert (tmp_path / "site" / "tutorial" / "index.html").exists()
    assert (tmp_path / "site" / "reference" / "cli" / "index.html").exists()


def test_the_generated_references_are_current():
    """The command-line and config references are what the code generates now: a new
    option or config key without a regenerated page fails here."""
    done = subprocess.run([sys.executable, "tools/docs_reference.py", "--check"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_the_cli_reference_lists_every_command_and_option():
    """The index links every command to the page of its group, which holds its options."""
    index = (DOCS / "reference" / "cli.md").read_text(encoding="utf-8")
    pages = {p.name: p.read_text(encoding="utf-8") for p in (DOCS / "reference").glob("cli-*.md")}
    for heading in ("armfusion track", "armfusion calibrate joints", "armfusion calibrate sensors",
                    "armfusion serve", "armfusion import"):
        link = re.search(rf"\[`{heading}`\]\((cli-[a-z]+\.md)#{heading.replace(' ', '-')}\)", index)
        assert link, heading
        assert f"## `{heading}`" in pages[link.group(1)]
    text = "\n".join(pages.values())
    assert "`--moving-start`" in text and "`--zenoh-config <path>`" in text


# an issue number ("issue 15", "issue #3", "(#12)"), or the word session outside Zenoh's own
# sessions (a Zenoh session, open_session, publisher sessions of the wire's seq)
_MAKING = re.compile(r"\bissues? #?\d+|\(#\d+\)|(?<![\w/])#\d+\b|\bsessions?\b", re.I)
_ZENOH_SESSION = re.compile(r"zenoh\b[^.\n]{0,40}\bsessions?\b|\bsessions?\b[^.\n]{0,3}(zenoh|open)|"
                            r"open_session|publisher sessions?|sessions? (it|they) open|"
                            r"session (per|for each|of its own)|every session|one session", re.I)


def test_no_page_speaks_of_issues_or_sessions():
    found = []
    for page in _user_pages():
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            for m in _MAKING.finditer(line):
                if m.group(0).lower().startswith("session") and _ZENOH_SESSION.search(line):
                    continue
                found.append(f"{page.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not found, "\n".join(found)


def _tutorial_blocks() -> list[str]:
    text = (DOCS / "tutorial.md").read_text(encoding="utf-8")
    return re.findall(r"```sh\n(.*?)```", text, flags=re.S)


def test_the_tutorial_runs_as_written(tmp_path):
    """Every ``sh`` block of the tutorial, in order, from a copy of the repository's layout
    (its shipped test data), with the installed ``armfusion`` on the path."""
    blocks = _tutorial_blocks()
    assert len(blocks) >= 6
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(ROOT / "tests" / "data")
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    for block in blocks:
        done = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, (f"{block}\n--- stdout\n{done.stdout[-2000:]}"
                                      f"\n--- stderr\n{done.stderr[-2000:]}")
    assert (tmp_path / "out" / "tutorial" / "roll-est.csv").stat().st_size > 0
    assert (tmp_path / "out" / "tutorial" / "broad-track.json").stat().st_size > 0


def _stated_limits() -> tuple[int, int]:
    """The longest a page and the README may be, as the docs' index states them."""
    text = " ".join((DOCS / "index.md").read_text(encoding="utf-8").split())
    m = re.search(r"No page of this site is longer than (\d+) lines, and the README no longer than (\d+)",
                  text)
    assert m, "docs/index.md no longer states how long a page may be"
    return int(m.group(1)), int(m.group(2))


def test_no_page_is_longer_than_the_docs_say():
    """Every page under docs/ (generated ones too) within the stated length, the README
    within its own: a page that grows is split, not excepted."""
    page_max, readme_max = _stated_limits()
    long = [f"{p.relative_to(ROOT)}: {n} lines (at most {readme_max if p == README else page_max})"
            for p in _user_pages()
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > (readme_max if p == README
                                                                         else page_max)]
    assert not long, "\n".join(long)


@pytest.mark.parametrize("page", ["README.md"])
def test_the_readme_is_short_and_opens_with_its_quick_start(page):
    text = (ROOT / page).read_text(encoding="utf-8")
    quick = text.index("## Quick start")
    blocks = re.findall(r"```sh\n(.*?)```", text[quick:], flags=re.S)
    assert len(blocks) >= 2 and "pytest" in blocks[1]


def test_the_readme_headline_table_is_what_the_benchmarks_recorded():
    """Every row of the README's table comes from docs/headline.json, written by the tool
    that measured it, with a date and a commit."""
    import json

    data = json.loads((DOCS / "headline.json").read_text(encoding="utf-8"))
    assert data, "no benchmark has recorded a headline"
    for name, entry in data.items():
        assert re.fullmatch(r"\d{4}-\d{2}-\d{2}", entry["date"]) and entry["commit"], name
        assert entry["rows"] and all(r["what"] and r["armfusion"] for r in entry["rows"]), name
    done = subprocess.run([sys.executable, "tools/headline.py", "--check"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
