"""The session manifest, ``session.toml``: which scenes and sequences a session holds.

The manifest names every raw capture and every piece of precomputed perception a session uses,
the sync frames that override automatic detection, and the optional contact markers. It is loaded
strictly: an unknown key, a wrong type, a sequence naming an unknown scene or a folder that does not
exist is reported, and *all* problems of a file are reported at once in one :class:`ManifestError`.

Paths in the file are relative to the session folder (the folder holding ``session.toml``) or
absolute. In memory every path is absolute: :class:`SessionManifest` resolves relative paths
against its ``root`` when it is built, so consumers use the paths as they are. The writer turns
paths inside the session folder back into relative ones, so a session folder can be moved.

Format (version 1), see ``docs/formats.md``::

    version = 1
    body_model = "body_model.npz"       # optional; omitted = the generated test model
    gender = "neutral"                  # optional: neutral | male | female
    [scenes.room]
    capture = "captures/room"
    indoor = true                       # optional, default true
    [scenes.room.markers]               # optional named contact markers, scene frame, metres
    door = [1.0, 2.0, 0.0]
    [sequences.seq0]
    scene = "room"
    contacts = [{frame = 120, xyz = [1.0, 2.0, 0.0]}, {frame = 300, marker = "door"}]
    optim_scale = false                 # optional
    subframe_sync = true                # optional: apply the measured sub-frame part of manual sync
    sync_force = false                  # optional: keep manual sync frames the geometry contradicts
    failed = false                      # optional: failed sequences are skipped unless forced
    note = ""                           # optional
    [sequences.seq0.views.v1]
    capture = "captures/seq0/v1"
    sync_frame = 57                     # optional
    keypoints = "perception/seq0/v1/keypoints"   # optional
    masks = "perception/seq0/v1/masks"           # optional
    depth = "perception/seq0/v1/depth"           # optional
    body_prior = "perception/seq0/v1/body_prior.npz"  # optional
    [sequences.seq0.views.v2]
    capture = "captures/seq0/v2"
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Callable

import tomli_w

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_bytes
from embodmocap.io.layout import VIEWS, SessionLayout
# The manifest's typed entries (their own module; imported from here as before).
from embodmocap.io.manifest_entries import (GENDERS, MANIFEST_NAME, MANIFEST_VERSION, ContactMarker,  # noqa: F401
                                            ManifestError, SceneEntry, SequenceEntry, SessionManifest, ViewEntry, Xyz,
                                            absolute_path)

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10 only
    import tomli as tomllib  # type: ignore[no-redef]

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Loading: a small strict reader that records every problem instead of stopping at the first.


class _Reader:
    """Reads typed values out of parsed TOML tables, collecting problems by dotted key path."""

    def __init__(self) -> None:
        self.problems: list[str] = []
        # Dotted keys of markers present but unusable: references to them are not reported
        # again, so one mistake gives one line.
        self.broken: set[str] = set()

    def add(self, key: str, message: str) -> None:
        self.problems.append(f"{key}: {message}" if key else message)

    def table(self, value: Any, key: str) -> dict[str, Any] | None:
        if isinstance(value, dict):
            return value
        self.add(key, f"expected a table, got {_describe(value)}")
        return None

    def keys(self, table: dict[str, Any], key: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> None:
        """Report unknown keys (listing the allowed ones) and missing required keys."""
        for k in table:
            if k not in allowed:
                self.add(_join(key, k), f"unknown key (allowed: {', '.join(allowed)})")
        for k in required:
            if k not in table:
                self.add(_join(key, k), "missing required key")

    def get(self, table: dict[str, Any], name: str, key: str, kind: str, default: Any = None) -> Any:
        """The value of ``table[name]`` checked against ``kind``; ``default`` when absent or bad."""
        if name not in table:
            return default
        value = table[name]
        checked = _CHECKS[kind](value)
        if checked is None:
            self.add(_join(key, name), f"expected {kind}, got {_describe(value)}")
            return default
        return checked


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _describe(value: Any) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 40 else text[:37] + '...'}"


def _as_int(v: Any) -> int | None:
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def _as_xyz(v: Any) -> Xyz | None:
    ok = (
        isinstance(v, list)
        and len(v) == 3
        and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v)
    )
    return tuple(float(c) for c in v) if ok else None  # type: ignore[return-value]


_CHECKS: dict[str, Callable[[Any], Any]] = {
    "an integer": _as_int,
    "a boolean": lambda v: v if isinstance(v, bool) else None,
    "a string": lambda v: v if isinstance(v, str) else None,
    "a path string": lambda v: Path(v) if isinstance(v, str) and v.strip() else None,
    "a list": lambda v: v if isinstance(v, list) else None,
    "a list of 3 finite numbers": _as_xyz,
}

_TOP_KEYS = ("version", "body_model", "gender", "scenes", "sequences")
_SCENE_KEYS = ("capture", "indoor", "markers")
_SEQUENCE_KEYS = ("scene", "views", "contacts", "optim_scale", "note", "failed", "subframe_sync", "sync_force")
_VIEW_KEYS = ("capture", "sync_frame", "keypoints", "masks", "depth", "body_prior")
_CONTACT_KEYS = ("frame", "xyz", "marker")


def load_manifest(path: str | Path) -> SessionManifest:
    """Read ``session.toml`` strictly; raise one :class:`ManifestError` listing every problem.

    ``path`` may be the file or the session folder holding it. The session root is the file's
    folder. Checks: unknown keys (at every level), types, required keys, version, scene references,
    marker references, exactly the views ``v1`` and ``v2``, and that every named folder/file exists.
    """
    manifest, problems, path = _read(path)
    if problems:
        raise ManifestError(path, problems)
    logger.debug("loaded %s: %d scenes, %d sequences", path, len(manifest.scenes), len(manifest.sequences))
    return manifest


def read_manifest(path: str | Path) -> tuple[SessionManifest, list[str]]:
    """Read ``session.toml`` leniently: the part that could be built and every problem found.

    For ``embodmocap inspect``, which reports a session's problems without stopping at them. A
    file that is missing or not TOML at all still raises :class:`InputError`.
    """
    manifest, problems, _ = _read(path)
    return manifest, problems


def _read(path: str | Path) -> tuple[SessionManifest, list[str], Path]:
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    if not path.is_file():
        raise InputError(path, "session manifest not found", "create it, or import a sheet with `embodmocap session import`")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise InputError(path, f"not valid TOML: {err}", "fix the syntax at the position shown") from err

    reader = _Reader()
    manifest, broken_scenes = _parse(data, path.parent, reader)
    problems = reader.problems + _semantic_problems(manifest, declared_scenes=broken_scenes)
    return manifest, problems, path


def _parse(data: dict[str, Any], root: Path, r: _Reader) -> tuple[SessionManifest, set[str]]:
    """Build what can be built; returns the manifest and the names of scenes that failed to parse."""
    r.keys(data, "", _TOP_KEYS, required=("version",))
    version = r.get(data, "version", "", "an integer", default=MANIFEST_VERSION)
    body_model = r.get(data, "body_model", "", "a path string")
    gender = r.get(data, "gender", "", "a string", default="neutral")

    scenes: dict[str, SceneEntry] = {}
    broken: set[str] = set()
    for name, raw in (r.table(data.get("scenes", {}), "scenes") or {}).items():
        scene = _parse_scene(name, raw, r)
        if scene is None:
            broken.add(name)
        else:
            scenes[name] = scene

    sequences: dict[str, SequenceEntry] = {}
    for name, raw in (r.table(data.get("sequences", {}), "sequences") or {}).items():
        seq = _parse_sequence(name, raw, scenes, r)
        if seq is not None:
            sequences[name] = seq

    manifest = SessionManifest(
        root=root, scenes=scenes, sequences=sequences, body_model=body_model, gender=gender, version=version
    )
    return manifest, broken


def _parse_scene(name: str, raw: Any, r: _Reader) -> SceneEntry | None:
    key = f"scenes.{name}"
    table = r.table(raw, key)
    if table is None:
        return None
    r.keys(table, key, _SCENE_KEYS, required=("capture",))
    capture = r.get(table, "capture", key, "a path string")
    indoor = r.get(table, "indoor", key, "a boolean", default=True)
    markers: dict[str, Xyz] = {}
    for mname, value in (r.table(table.get("markers", {}), f"{key}.markers") or {}).items():
        xyz = r.get({mname: value}, mname, f"{key}.markers", "a list of 3 finite numbers")
        if xyz is not None:
            markers[mname] = xyz
        else:
            r.broken.add(f"{key}.markers.{mname}")
    if capture is None:
        return None
    return SceneEntry(name=name, capture=capture, indoor=indoor, markers=markers)


def _parse_sequence(name: str, raw: Any, scenes: dict[str, SceneEntry], r: _Reader) -> SequenceEntry | None:
    key = f"sequences.{name}"
    table = r.table(raw, key)
    if table is None:
        return None
    r.keys(table, key, _SEQUENCE_KEYS, required=("scene", "views"))
    scene = r.get(table, "scene", key, "a string")
    optim_scale = r.get(table, "optim_scale", key, "a boolean", default=False)
    note = r.get(table, "note", key, "a string", default="")
    failed = r.get(table, "failed", key, "a boolean", default=False)
    subframe_sync = r.get(table, "subframe_sync", key, "a boolean", default=True)
    sync_force = r.get(table, "sync_force", key, "a boolean", default=False)

    views: dict[str, ViewEntry] = {}
    views_ok = True
    for vname, vraw in (r.table(table.get("views", {}), f"{key}.views") or {}).items():
        if vname not in VIEWS:
            r.add(f"{key}.views.{vname}", f"unknown view (allowed: {', '.join(VIEWS)}; one view v1 or two views v1, v2)")
            continue
        view = _parse_view(f"{key}.views.{vname}", vraw, r)
        views_ok &= view is not None
        if view is not None:
            views[vname] = view

    markers = scenes[scene].markers if scene in scenes else None
    contacts: list[ContactMarker] = []
    for i, craw in enumerate(r.get(table, "contacts", key, "a list", default=[])):
        contact = _parse_contact(f"{key}.contacts[{i}]", craw, scene, markers, r)
        if contact is not None:
            contacts.append(contact)

    # An entry with a missing/bad scene or view is not built: its problem is reported already, and
    # building it anyway would only add follow-on noise (missing views, unknown scene ...).
    if scene is None or not views_ok or "views" not in table:
        return None
    return SequenceEntry(
        name=name, scene=scene, views=views, contacts=tuple(contacts),
        optim_scale=optim_scale, note=note, failed=failed, subframe_sync=subframe_sync, sync_force=sync_force,
    )


def _parse_view(key: str, raw: Any, r: _Reader) -> ViewEntry | None:
    table = r.table(raw, key)
    if table is None:
        return None
    r.keys(table, key, _VIEW_KEYS, required=("capture",))
    capture = r.get(table, "capture", key, "a path string")
    fields = {k: r.get(table, k, key, "a path string") for k in ("keypoints", "masks", "depth", "body_prior")}
    sync_frame = r.get(table, "sync_frame", key, "an integer")
    if capture is None:
        return None
    return ViewEntry(capture=capture, sync_frame=sync_frame, **fields)


def _parse_contact(
    key: str, raw: Any, scene: str | None, markers: dict[str, Xyz] | None, r: _Reader
) -> ContactMarker | None:
    """A contact is ``{frame, xyz}`` or ``{frame, marker}`` (a name in the scene's markers)."""
    table = r.table(raw, key)
    if table is None:
        return None
    r.keys(table, key, _CONTACT_KEYS, required=("frame",))
    frame = r.get(table, "frame", key, "an integer")
    xyz = r.get(table, "xyz", key, "a list of 3 finite numbers")
    marker = r.get(table, "marker", key, "a string")
    if ("xyz" in table) == ("marker" in table):
        r.add(key, "give exactly one of 'xyz' (a point) or 'marker' (a name in the scene's markers)")
        return None
    if marker is not None:
        # An unknown or broken scene/marker is reported where it is defined, not again here.
        if markers is None or f"scenes.{scene}.markers.{marker}" in r.broken:
            return None
        if marker not in markers:
            known = ", ".join(markers) or "none"
            r.add(f"{key}.marker", f"the scene has no marker {marker!r} (known markers: {known})")
            return None
        xyz = markers[marker]
    if frame is None or xyz is None:
        return None
    return ContactMarker(frame=frame, xyz=xyz, marker=marker)


# --------------------------------------------------------------------------------------------
# Validation of a built manifest (also what `inspect` shows).


def validate_manifest(manifest: SessionManifest) -> list[str]:
    """Every problem of a built manifest, one line each (``dotted.key: problem``); [] when fine.

    Checks the version, gender, names usable as folder names, scene and marker references, the
    views (v1 and v2, or v1 alone), non-negative frames, and that every named folder or file exists.
    """
    return _semantic_problems(manifest, declared_scenes=set())


def _semantic_problems(m: SessionManifest, declared_scenes: set[str]) -> list[str]:
    """``declared_scenes``: scenes present in the file but unparsable (already reported there)."""
    problems: list[str] = []
    add = lambda key, msg: problems.append(f"{key}: {msg}")  # noqa: E731
    if m.version != MANIFEST_VERSION:
        add("version", f"unsupported version {m.version} (this release reads version {MANIFEST_VERSION})")
    if m.gender not in GENDERS:
        add("gender", f"unknown gender {m.gender!r} (allowed: {', '.join(GENDERS)})")
    if m.body_model is not None and not m.body_model.is_file():
        add("body_model", f"file does not exist: {m.body_model}")

    for name, scene in m.scenes.items():
        key = f"scenes.{name}"
        _check_name(name, key, add)
        _check_path(scene.capture, f"{key}.capture", "capture", add)

    for name, seq in m.sequences.items():
        key = f"sequences.{name}"
        _check_name(name, key, add)
        scene = m.scenes.get(seq.scene)
        if scene is None and seq.scene not in declared_scenes:
            add(f"{key}.scene", f"unknown scene {seq.scene!r} (scenes: {', '.join(m.scenes) or 'none'})")
        if set(seq.views) not in (set(VIEWS), set(VIEWS[:1])):
            add(f"{key}.views", f"need the views {', '.join(VIEWS)} (two phones) or {VIEWS[0]} alone (one phone), "
                f"got {', '.join(seq.views) or 'none'}")
        for vname, view in seq.views.items():
            vkey = f"{key}.views.{vname}"
            _check_path(view.capture, f"{vkey}.capture", "capture", add)
            for attr in ("keypoints", "masks", "depth"):
                _check_path(getattr(view, attr), f"{vkey}.{attr}", "folder", add)
            _check_path(view.body_prior, f"{vkey}.body_prior", "file", add)
            if view.sync_frame is not None and view.sync_frame < 0:
                add(f"{vkey}.sync_frame", f"must be >= 0, got {view.sync_frame}")
        for i, c in enumerate(seq.contacts):
            ckey = f"{key}.contacts[{i}]"
            if c.frame < 0:
                add(f"{ckey}.frame", f"must be >= 0, got {c.frame}")
            if c.marker is not None and scene is not None and scene.markers.get(c.marker) != tuple(c.xyz):
                add(f"{ckey}.marker", f"marker {c.marker!r} is not a marker of scene {scene.name!r} with this xyz")
    return problems


def _check_name(name: str, key: str, add: Callable[[str, str], None]) -> None:
    """Names become folder names: no separators, not '.'/'..', no surrounding blanks."""
    bad = name in ("", ".", "..") or any(c in name for c in "/\\\0") or name != name.strip()
    if bad:
        add(key, f"name {name!r} cannot be a folder name (use letters, digits, '_', '-', '.')")


def _check_path(path: Path | None, key: str, kind: str, add: Callable[[str, str], None]) -> None:
    if path is None:
        return
    # A capture is a folder, or a Record3D .r3d file (a zip of the same folder).
    exists = (path.is_dir() or (kind == "capture" and path.is_file() and path.suffix.lower() == ".r3d")) \
        if kind in ("folder", "capture") else path.is_file()
    if not exists and kind == "capture" and path.is_file():
        # A video or a zip named as a capture: say what a capture is (scene and view alike).
        add(key, f"{path} is a file, not a capture: point to the folder the phone app exported "
                 "(Stray Scanner, Spectacular AI, Record3D EXR + JPG or unzipped .r3d) or to a Record3D .r3d file"
                 + (" (unzip a zipped recording first)" if path.suffix.lower() == ".zip" else ""))
    elif not exists:
        what = " (the folder the phone app exported, or a Record3D .r3d file)" if kind == "capture" else ""
        add(key, f"{kind} does not exist: {path}{what}")


# ------------------------------------------------------------------------------------------------
# Writing (the reader above owns the format; one module, so neither imports the other)


def write_manifest(manifest: SessionManifest, path: str | Path | None = None) -> Path:
    """Write ``manifest`` as TOML atomically; returns the path written.

    ``path`` defaults to ``<root>/session.toml``. Paths inside the folder of the written file are
    stored relative to it (that folder is the root when the file is loaded again), others absolute.
    ``load_manifest(write_manifest(m)) == m`` for a manifest whose root is that folder.
    """
    path = absolute_path(Path(path) if path is not None else SessionLayout(manifest.root).manifest)
    if path.parent != manifest.root:
        logger.warning("writing manifest to %s, outside its root %s: paths become relative to %s", path, manifest.root, path.parent)
    write_bytes(path, tomli_w.dumps(manifest_to_dict(manifest, path.parent)).encode("utf-8"))
    return path


def manifest_to_dict(manifest: SessionManifest, root: Path | None = None) -> dict[str, Any]:
    """The TOML document of ``manifest`` as plain dicts (no None values; paths as strings)."""
    root = absolute_path(Path(root)) if root is not None else manifest.root
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
