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
    # the page keeps a section of the latest session's figures (its number changes each session)
    assert any(re.match(r"## Session \d+ \(", line) for line in lines)


def _anchors(doc: Path) -> set[str]:
    from embodmocap.settings_doc import slug

    text = doc.read_text()
    fenced = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    heads = {slug(m) for m in re.findall(r"^#{1,6} (.+)$", fenced, flags=re.M)}
    return heads | set(re.findall(r'<a id="([^"]+)"', text))


def test_relative_links_point_to_files_and_headings_that_exist():
    missing = []
    for doc in _documents():
        text = re.sub(r"^```.*?^```", "", doc.read_text(), flags=re.S | re.M)
        for target, anchor in LINK.findall(text):
            if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                continue
            path = doc.parent / target
            if not path.exists():
                missing.append(f"{doc.relative_to(ROOT)} -> {target}")
            elif anchor and path.suffix == ".md" and anchor[1:] not in _anchors(path):
                missing.append(f"{doc.relative_to(ROOT)} -> {target}{anchor}")
    assert not missing, missing


def test_history_index_lists_every_history_file():
    history = ROOT / "benchmarks" / "history"
    index = (history / "README.md").read_text()
    # session files named YYYY-MM-DD-sN-*.md are listed by pattern in the index, the topic files by name
    files = [p.name for p in history.glob("*.md") if p.name != "README.md" and not re.match(r"\d{4}-\d\d-\d\d-s\d+-", p.name)]
    assert files, "no history files"
    assert [f for f in files if f"]({f})" not in index] == []


def test_generated_settings_tables_and_contents_are_up_to_date():
    # docs/settings.md is generated from the config dataclasses' field docstrings and formats.md's
    # contents list from its headings; a change to either without rerunning the generator fails here.
    from embodmocap.settings_doc import generated

    stale = [str(p.relative_to(ROOT)) for p, text in generated().items() if p.read_text() != text]
    assert not stale, f"{stale} stale: run `python -m embodmocap.settings_doc`"


def test_settings_tables_cover_every_config_field():
    # every field of every command's settings appears as a row, with the meaning its docstring gives
    import dataclasses
    import typing

    from embodmocap.pipeline import PipelineConfig
    from embodmocap.settings_doc import field_docstrings, rows

    def leaves(cls, prefix=""):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if dataclasses.is_dataclass(hints[f.name]):
                yield from leaves(hints[f.name], f"{prefix}{f.name}.")
            else:
                yield f"{prefix}{f.name}", field_docstrings(cls).get(f.name, "")

    table = "\n".join(rows(PipelineConfig))
    for key, doc in leaves(PipelineConfig):
        assert f"| `{key}` |" in table, key
        assert doc, f"PipelineConfig.{key} has no docstring"
        assert " ".join(doc.split()).replace("|", "\\|") in table, key


def test_readme_starts_with_demo_and_test_names_every_command_and_links_every_doc():
    from embodmocap.cli import Commands
    from embodmocap.cli_settings import subcommands

    readme = (ROOT / "README.md").read_text()
    first_block = readme.split("```")[1]
    assert "./run demo" in first_block and "./run test" in first_block
    missing = [n for n in subcommands(Commands) if f"embodmocap {n.replace(':', ' ')} " not in readme]
    assert not missing, f"commands not in the README: {missing}"
    for fmt in ("mjcf", "trc", "smplx", "amass", "bvh", "glb", "training"):
        assert fmt in readme, fmt
    linked = {target for target, _ in LINK.findall(readme)}
    docs = [p.relative_to(ROOT).as_posix() for p in sorted((ROOT / "docs").rglob("*")) if p.suffix in (".md", ".toml")]
    assert [d for d in docs if d not in linked] == []
