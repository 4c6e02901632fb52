"""The package's layering rules, checked on the source (AST), so a violation fails here:

- production code never imports the synthetic studio (``embodmocap.synth``), except the commands
  that exist to run it (``synth``, ``demo`` in the CLI; ``benchmark``, which synthesises the
  sessions it measures);
- no package imports another package's private (underscore) names, neither by ``from ... import _x``
  nor as ``module._x`` through an imported module;
- ``embodmocap --help`` imports neither torch nor open3d;
- no module is over 600 lines (one known exception, to be split).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

#: Modules outside embodmocap.synth allowed to import it, and why.
SYNTH_IMPORTERS = {
    "embodmocap/cli.py": "the `synth` and `demo` commands run the studio",
    "embodmocap/evaluate/benchmark.py": "the `benchmark` command synthesises the sessions it measures",
}


#: Modules allowed over the size limit for now, and why.
LONG_MODULES: dict[str, str] = {}
MAX_LINES = 600


def _package(rel: Path) -> str:
    """``embodmocap/<pkg>/...`` -> pkg; a top-level module is its own package."""
    return rel.parts[1] if len(rel.parts) > 2 else rel.stem


def _resolve(rel: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = list(rel.with_suffix("").parts[: -node.level])
    return ".".join(base + ([node.module] if node.module else []))


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def layering_problems(root: Path) -> list[str]:
    """Every violation of the rules above in the ``embodmocap`` tree under ``root``."""
    problems = []
    for path in sorted((root / "embodmocap").rglob("*.py")):
        rel = path.relative_to(root)
        pkg = _package(rel)
        tree = ast.parse(path.read_text(), filename=str(path))
        aliases: dict[str, str] = {}  # local name -> package of an imported embodmocap module
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                mod = _resolve(rel, node)
                if not mod.startswith("embodmocap"):
                    continue
                parts = mod.split(".")
                target = parts[1] if len(parts) > 1 else ""
                if target == "synth" and pkg != "synth" and rel.as_posix() not in SYNTH_IMPORTERS:
                    problems.append(f"{rel}:{node.lineno}: imports {mod} (production code must not use the studio)")
                for a in node.names:
                    if target != pkg and _is_private(a.name):
                        problems.append(f"{rel}:{node.lineno}: imports private {mod}.{a.name}")
                    if a.name == "synth" and mod == "embodmocap" and pkg != "synth" and rel.as_posix() not in SYNTH_IMPORTERS:
                        problems.append(f"{rel}:{node.lineno}: imports embodmocap.synth")
                    sub = f"{mod}.{a.name}"
                    if len(parts) >= 2 and "." in sub:  # `from embodmocap.pkg import module`
                        aliases[a.asname or a.name] = sub.split(".")[1]
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if not a.name.startswith("embodmocap."):
                        continue
                    target = a.name.split(".")[1]
                    if target == "synth" and pkg != "synth" and rel.as_posix() not in SYNTH_IMPORTERS:
                        problems.append(f"{rel}:{node.lineno}: imports {a.name} (production code must not use the studio)")
                    if a.asname:
                        aliases[a.asname] = target
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and aliases[node.value.id] != pkg and _is_private(node.attr)):
                problems.append(f"{rel}:{node.lineno}: uses private {node.value.id}.{node.attr} of package "
                                f"{aliases[node.value.id]}")
    return problems


def test_the_package_keeps_its_layering():
    assert layering_problems(SRC) == []


def test_the_scan_finds_each_kind_of_violation(tmp_path):
    pkg = tmp_path / "embodmocap"
    (pkg / "motion").mkdir(parents=True)
    (pkg / "calibrate").mkdir()
    (pkg / "synth").mkdir()
    (pkg / "motion" / "bad.py").write_text(
        "from embodmocap.synth.motion import foot_vertex_ids\n"
        "from embodmocap.calibrate.stage import _track_pairs\n"
        "from embodmocap.calibrate import stage as s3\n"
        "import embodmocap.synth.render as r\n"
        "x = s3._fps\n"
        "from embodmocap.motion.stage import _priors\n"  # same package: allowed
        "from embodmocap import __version__\n")  # dunder: allowed
    (pkg / "synth" / "ok.py").write_text("from embodmocap.synth.spec import SceneSpec\n")
    found = layering_problems(tmp_path)
    assert len(found) == 4, found
    assert any("synth.motion" in p for p in found) and any("_track_pairs" in p for p in found)
    assert any("s3._fps" in p for p in found) and any("synth.render" in p for p in found)


def test_help_imports_neither_torch_nor_open3d():
    code = ("import sys\nfrom embodmocap.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "import json\nprint(json.dumps([m for m in ('torch', 'open3d', 'scipy.optimize') if m in sys.modules]))")
    env_path = str(SRC)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin"})
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert "torch" not in loaded and "open3d" not in loaded, loaded


def test_no_module_is_over_600_lines():
    long = {p.relative_to(SRC).as_posix(): n for p in sorted((SRC / "embodmocap").rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert set(long) <= set(LONG_MODULES), {k: v for k, v in long.items() if k not in LONG_MODULES}
