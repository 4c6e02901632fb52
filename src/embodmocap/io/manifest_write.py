"""Writing the session manifest (``session.toml``); the format and the reader are in
:mod:`embodmocap.io.manifest`, which re-exports :func:`write_manifest` and :func:`manifest_to_dict`."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

import tomli_w

from embodmocap.io.atomic import write_bytes
from embodmocap.io.manifest import MANIFEST_NAME, SequenceEntry, SessionManifest, _absolute

logger = logging.getLogger("embodmocap.io.manifest")


def write_manifest(manifest: SessionManifest, path: str | Path | None = None) -> Path:
    """Write ``manifest`` as TOML atomically; returns the path written.

    ``path`` defaults to ``<root>/session.toml``. Paths inside the folder of the written file are
    stored relative to it (that folder is the root when the file is loaded again), others absolute.
    ``load_manifest(write_manifest(m)) == m`` for a manifest whose root is that folder.
    """
    path = _absolute(Path(path) if path is not None else manifest.root / MANIFEST_NAME)
    if path.parent != manifest.root:
        logger.warning("writing manifest to %s, outside its root %s: paths become relative to %s", path, manifest.root, path.parent)
    write_bytes(path, tomli_w.dumps(manifest_to_dict(manifest, path.parent)).encode("utf-8"))
    return path


def manifest_to_dict(manifest: SessionManifest, root: Path | None = None) -> dict[str, Any]:
    """The TOML document of ``manifest`` as plain dicts (no None values; paths as strings)."""
    root = _absolute(Path(root)) if root is not None else manifest.root
    rel = lambda p: _path_text(p, root)  # noqa: E731
    doc: dict[str, Any] = {"version": manifest.version}
    if manifest.body_model is not None:
        doc["body_model"] = rel(manifest.body_model)
    doc["gender"] = manifest.gender
    doc["scenes"] = {
        name: {"capture": rel(s.capture), "indoor": s.indoor, **({"markers": {k: list(v) for k, v in s.markers.items()}} if s.markers else {})}
        for name, s in manifest.scenes.items()
    }
    doc["sequences"] = {name: _sequence_to_dict(s, rel) for name, s in manifest.sequences.items()}
    return doc


def _sequence_to_dict(seq: SequenceEntry, rel: Callable[[Path], str]) -> dict[str, Any]:
    out: dict[str, Any] = {"scene": seq.scene, "optim_scale": seq.optim_scale, "failed": seq.failed}
    if seq.note:
        out["note"] = seq.note
    # Written only when not the default, so older readers keep reading files that do not use them.
    if not seq.subframe_sync:
        out["subframe_sync"] = False
    if seq.sync_force:
        out["sync_force"] = True
    if seq.contacts:
        out["contacts"] = [
            {"frame": c.frame, "marker": c.marker} if c.marker is not None else {"frame": c.frame, "xyz": list(c.xyz)}
            for c in seq.contacts
        ]
    views: dict[str, Any] = {}
    for vname, v in seq.views.items():
        view: dict[str, Any] = {"capture": rel(v.capture)}
        if v.sync_frame is not None:
            view["sync_frame"] = v.sync_frame
        for attr in ("keypoints", "masks", "depth", "body_prior"):
            if getattr(v, attr) is not None:
                view[attr] = rel(getattr(v, attr))
        views[vname] = view
    out["views"] = views
    return out


def _path_text(path: Path, root: Path) -> str:
    """POSIX text of ``path``, relative to ``root`` when inside it (so sessions can move)."""
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.as_posix()
