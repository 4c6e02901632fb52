"""Resumable stages: each step's outputs are recorded with a fingerprint of what produced them.

A stage is a list of steps. Before a step runs, the stage computes its fingerprint from the
step's config, the fingerprints of its input files and those of the steps it depends on. The step
is skipped when the manifest holds the same fingerprint and every output it recorded still exists;
otherwise it runs and the manifest is rewritten (atomically) right after it, so a run interrupted
between steps resumes at the first step that is not done.

The manifest (``manifest.json`` next to the stage's outputs) also carries what users want to see:
the resolved config, the package version, timings and the quality figures of each step.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any, Iterable

from embodmocap import __version__
from embodmocap.io.atomic import write_json

log = logging.getLogger(__name__)

MANIFEST_VERSION = 1


def path_fingerprint(path: str | Path) -> list:
    """A cheap fingerprint of a file or folder: names, sizes and modification times.

    Content hashes of multi-GB captures would cost minutes; size + mtime changes whenever a file is
    rewritten, which is what matters for deciding whether to redo a step.
    """
    p = Path(path)
    if p.is_file():
        st = p.stat()
        return [p.name, st.st_size, st.st_mtime_ns]
    if p.is_dir():
        out = []
        for f in sorted(p.rglob("*")):
            if f.is_file() and not f.name.startswith("."):
                st = f.stat()
                out.append([str(f.relative_to(p)), st.st_size, st.st_mtime_ns])
        return out
    return [str(p), None]


def fingerprint(*parts: Any) -> str:
    """SHA-256 of a JSON rendering of ``parts`` (dataclasses, paths, numbers, lists, dicts)."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=_plain).encode()).hexdigest()[:16]


def _plain(o: Any) -> Any:
    if is_dataclass(o):
        return asdict(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"cannot fingerprint {type(o).__name__}")


class StageManifest:
    """The manifest of one stage's run: steps done, their fingerprints, timings and figures."""

    def __init__(self, path: str | Path, stage: str, config: Any) -> None:
        self.path = Path(path)
        self.stage = stage
        self.data: dict[str, Any] = {
            "version": MANIFEST_VERSION, "stage": stage, "package_version": __version__,
            "config": json.loads(json.dumps(config, default=_plain)), "steps": {}, "figures": {},
        }
        old = self._load()
        if old is not None:
            self.data["steps"] = old.get("steps", {})
            self.data["figures"] = old.get("figures", {})

    def _load(self) -> dict | None:
        if not self.path.is_file():
            return None
        try:
            old = json.loads(self.path.read_text())
        except (OSError, json.JSONDecodeError):
            log.warning("%s: unreadable stage manifest, redoing every step", self.path)
            return None
        if old.get("version") != MANIFEST_VERSION or old.get("stage") != self.stage:
            return None
        return old

    def is_current(self, step: str, fp: str) -> bool:
        """True when ``step`` was done with fingerprint ``fp`` and all its outputs still exist."""
        rec = self.data["steps"].get(step)
        if rec is None or rec.get("fingerprint") != fp:
            return False
        root = self.path.parent
        return all((root / o).exists() for o in rec.get("outputs", []))

    def record(self, step: str, fp: str, outputs: Iterable[str | Path], seconds: float,
               figures: dict[str, Any] | None = None) -> None:
        """Mark ``step`` done and rewrite the manifest atomically."""
        root = self.path.parent
        outs = [str(Path(o).relative_to(root)) if Path(o).is_absolute() else str(o) for o in outputs]
        self.data["steps"][step] = {
            "fingerprint": fp, "outputs": outs, "seconds": round(float(seconds), 3),
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        if figures:
            self.data["figures"].update(figures)
        self.save()

    def figures(self) -> dict[str, Any]:
        return dict(self.data["figures"])

    def save(self) -> None:
        write_json(self.path, self.data)
