"""The package's layering rules, checked on the source (AST), so a violation fails here:

- production code never imports the synthetic studio (``embodmocap.synth``), except the commands
  that exist to run it (``synth``, ``demo`` in the CLI; ``benchmark``, which synthesises the
  sessions it measures);
- no package imports another package's private (underscore) names, neither by ``from ... import _x``
  nor as ``module._x`` through an imported module;
- ``embodmocap --help`` imports neither torch nor open3d;
- no module is over 600 lines (one known exception, to be split);
- a stage's pure solve module (``<stage>/solve.py``) does no file work itself: it opens, reads and
  writes nothing (no ``open``, ``np.load``/``np.save``, ``read_*``/``write_*`` calls, no path
  methods), and imports neither paths (``pathlib``, the session layout's paths) nor the modules
  that write or fingerprint files (``io.atomic``, ``io.stage_manifest``, ``io.captures``,
  ``io.frame_stack``, ``io.mesh_file``); from ``io.stage_files`` only the file dataclasses. That the
  functions it calls touch no file either is shown by the stage tests, which run each solve on
  inputs read into memory from a session copy that is deleted first.
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


#: What a solve module may not import: modules that touch files or own paths.
#: Modules that hold part of a stage's solve (kept apart for size): scanned like the solve modules.
SOLVE_PARTS = ("calibrate/final_sync.py",)
SOLVE_FORBIDDEN_MODULES = ("pathlib", "os", "shutil", "embodmocap.io.atomic", "embodmocap.io.stage_manifest",
                           "embodmocap.io.captures", "embodmocap.io.frame_stack", "embodmocap.io.mesh_file",
                           "embodmocap.io.manifest", "embodmocap.io.smpl_file")
#: Calls a solve module may not make (names and attribute names).
SOLVE_FORBIDDEN_CALLS = {"open", "load", "save", "savez", "savez_compressed", "loadtxt", "savetxt", "Path",
                         "read_text", "write_text", "read_bytes", "write_bytes", "mkdir", "unlink", "rmtree",
                         "exists", "is_file", "is_dir", "glob", "rglob", "open_capture"}


def solve_problems(root: Path) -> list[str]:
    """File work in the ``embodmocap/*/solve.py`` modules under ``root`` (see the module docstring)."""
    problems = []
    for path in sorted([*(root / "embodmocap").glob("*/solve.py"),
                        *[root / "embodmocap" / m for m in SOLVE_PARTS if (root / "embodmocap" / m).is_file()]]):
        rel = path.relative_to(root)
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            mods: list[tuple[str, list[str]]] = []
            if isinstance(node, ast.Import):
                mods = [(a.name, []) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                mods = [(_resolve(rel, node), [a.name for a in node.names])]
            for mod, names in mods:
                if any(mod == m or mod.startswith(m + ".") for m in SOLVE_FORBIDDEN_MODULES):
                    problems.append(f"{rel}:{node.lineno}: imports {mod}")
                if mod == "embodmocap.io.stage_files":
                    problems += [f"{rel}:{node.lineno}: imports {mod}.{n}" for n in names if not n.endswith("File")]
                if mod == "embodmocap.io.layout":
                    problems += [f"{rel}:{node.lineno}: imports {mod}.{n}" for n in names if n != "VIEWS"]
                problems += [f"{rel}:{node.lineno}: imports {mod}.{n}" for n in names
                             if n.startswith(("read_", "write_", "load_", "save_"))]
            if isinstance(node, ast.Call):
                f = node.func
                name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
                if name in SOLVE_FORBIDDEN_CALLS or name.startswith(("read_", "write_")):
                    problems.append(f"{rel}:{node.lineno}: calls {name}")
    return problems


def test_solve_modules_do_no_file_work():
    assert solve_problems(SRC) == []
    assert {p.relative_to(SRC).as_posix() for p in (SRC / "embodmocap").glob("*/solve.py")} >= {
        "embodmocap/scene/solve.py", "embodmocap/sequence/solve.py", "embodmocap/calibrate/solve.py",
        "embodmocap/motion/solve.py", "embodmocap/mono/solve.py", "embodmocap/skills/solve.py",
        "embodmocap/robot/solve.py"}


def test_the_solve_scan_finds_each_kind_of_file_work(tmp_path):
    (tmp_path / "embodmocap" / "motion").mkdir(parents=True)
    (tmp_path / "embodmocap" / "motion" / "solve.py").write_text(
        "from pathlib import Path\n"
        "import numpy as np\n"
        "from embodmocap.io.atomic import write_npz\n"
        "from embodmocap.io.stage_files import CameraFile, read_cameras\n"
        "from embodmocap.io.layout import VIEWS, SessionLayout\n"
        "from embodmocap.io.layout import VIEWS as V\n"
        "def f(p):\n"
        "    a = np.load(p)\n"
        "    with open(p) as fh:\n"
        "        fh.read()\n"
        "    p.write_text('x')\n"
        "    return write_cameras(p, a)\n")
    found = solve_problems(tmp_path)
    for what in ("imports pathlib", "imports embodmocap.io.atomic", "write_npz", "read_cameras", "SessionLayout",
                 "calls load", "calls open", "calls write_text", "calls write_cameras"):
        assert any(what in p for p in found), (what, found)
    assert not any("CameraFile" in p or p.endswith("VIEWS") for p in found), found

