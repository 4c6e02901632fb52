"""Import a session manifest from the paper release's spreadsheet (``seq_info.xlsx`` or a CSV).

One row per sequence. Columns (header names are matched case-insensitively):

============  =========================================================================
scene_folder  scene recording folder, relative to the session root or absolute (required)
seq_name      sequence folder name inside the scene folder (required)
in_door       boolean, per scene (default true); rows of one scene should agree
v1_start      raw frame where the laser dot disappears in view 1; ``-``/empty = detect
v2_start      the same for view 2; ``-1`` in either means "skip this sequence"
FAILED        boolean (default false): the sequence is marked failed (skipped by ``run``)
note          free text
contacts      Python-literal list: ``[[frame, [x, y, z]], ...]`` or ``[[frame, id], ...]``
optim_scale   boolean (default false)
character, skills, keyframes, vertical   read and ignored
============  =========================================================================

In an XLSX, every sheet except ``contact`` holds sequence rows (concatenated in sheet order). The
``contact`` sheet (columns ``scene``, ``contacts`` = list of xyz) defines the points that id-form
contacts refer to: id ``k`` is the k-th point (0-based) of that scene's list. They become named
markers ``"k"`` of the scene in the manifest. For a CSV, pass the contact table as a second CSV.

Choices where the release is ambiguous: booleans accept real booleans, ``TRUE/FALSE/True/true``,
``1/0/1.0/0.0``, ``yes/no`` and empty (= the column default). ``-1`` as a start frame marks the
sequence failed (the release skips every step of such a row) with the reason added to its note. A
scene's ``in_door`` comes from its first row (a warning names disagreeing rows). The scene name is
the last component of ``scene_folder``. A ``seq_name`` used in several scenes becomes
``<scene>_<seq_name>`` for every one of them, so manifest names stay unique.
"""

from __future__ import annotations

import ast
import csv
import io
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import (
    ContactMarker,
    SceneEntry,
    SequenceEntry,
    SessionManifest,
    ViewEntry,
    validate_manifest,
    write_manifest,
)

logger = logging.getLogger(__name__)

#: Where a view's recording lives. Placeholders: {scene_folder} (as written in the sheet),
#: {scene} (scene name), {seq_name}, {view} ("v1"/"v2"), {index} (1/2). Relative results are
#: resolved against the session root. The default matches the release: <scene>/<seq>/raw1, raw2.
DEFAULT_CAPTURE_PATTERN = "{scene_folder}/{seq_name}/raw{index}"

CONTACT_SHEET = "contact"
_KNOWN_COLUMNS = (
    "scene_folder", "seq_name", "in_door", "v1_start", "v2_start", "character", "skills",
    "keyframes", "failed", "note", "contacts", "optim_scale", "vertical",
)
_IGNORED_COLUMNS = ("character", "skills", "keyframes", "vertical")
_TRUE = {"true", "1", "1.0", "yes", "y", "t"}
_FALSE = {"false", "0", "0.0", "no", "n", "f", ""}
#: Longest contacts text parsed; literal_eval of huge nested input can exhaust the stack.
_MAX_LITERAL_CHARS = 100_000


@dataclass(frozen=True)
class _Row:
    """One data row of a sheet: where it came from and its cells by lower-case column name."""

    sheet: str | None
    """Sheet name (None for a CSV)."""
    number: int
    """1-based row number as a spreadsheet shows it (the header is row 1)."""
    cells: dict[str, Any]
    """Cell values by lower-case, stripped column name (None for empty cells)."""
    labels: dict[str, str]
    """Column names as the header writes them, by lower-case name (for messages)."""


class _Problems:
    """Collects cell problems so one error can list them all."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.lines: list[str] = []

    def add(self, row: _Row, column: str, message: str) -> None:
        sheet = f"sheet {row.sheet!r}, " if row.sheet is not None else ""
        label = row.labels.get(column, column)
        self.lines.append(f"{sheet}row {row.number}, column {label!r}: {message}")

    def raise_if_any(self) -> None:
        if not self.lines:
            return
        if len(self.lines) == 1:
            raise InputError(self.path, self.lines[0], "fix the cell and import again")
        listed = "".join(f"\n  - {line}" for line in self.lines)
        raise InputError(self.path, f"{len(self.lines)} bad cells (fix them and import again):{listed}")


# --------------------------------------------------------------------------------------------
# Public API


def import_sheet(
    path: str | Path,
    session_root: str | Path,
    capture_pattern: str = DEFAULT_CAPTURE_PATTERN,
    contact_sheet: str | Path | None = None,
    body_model: str | Path | None = None,
    gender: str = "neutral",
) -> SessionManifest:
    """Build a manifest from a release-style XLSX or CSV (see the module docstring).

    ``contact_sheet``: for a CSV only, a CSV with columns ``scene, contacts`` (the XLSX ``contact``
    sheet). Folders are not checked here (see :func:`validate_manifest`). Raises InputError naming
    the file, sheet, row and column of every bad cell.
    """
    path = Path(path)
    rows, contact_rows = _read_tables(path, contact_sheet)
    problems = _Problems(path)
    parsed = [p for p in (_parse_row(row, problems) for row in rows) if p is not None]
    problems.raise_if_any()
    ignored = sorted({c for row in rows for c in _IGNORED_COLUMNS if row.cells.get(c) is not None})
    if ignored:
        # `vertical` is forced on by the release itself; the others carry no pipeline input.
        logger.info("%s: columns %s are not used by the manifest and were ignored", path, ", ".join(ignored))
    if not parsed:
        raise InputError(path, "no sequence rows found", "add rows with scene_folder and seq_name")

    root = Path(session_root)
    scenes = _build_scenes(path, parsed, root)
    _add_markers(path, scenes, contact_rows)
    sequences = _build_sequences(path, parsed, scenes, root, capture_pattern, problems)
    problems.raise_if_any()
    manifest = SessionManifest(
        root=root, scenes=scenes, sequences=sequences, body_model=body_model, gender=gender
    )
    logger.info("imported %s: %d scenes, %d sequences", path, len(scenes), len(sequences))
    return manifest


def import_sheet_cli(
    sheet: Path,
    session: Path,
    capture_pattern: str = DEFAULT_CAPTURE_PATTERN,
    contact_sheet: Path | None = None,
    body_model: Path | None = None,
    force: bool = False,
    check: bool = True,
) -> Path:
    """Import a spreadsheet (XLSX or CSV) and write ``<session>/session.toml``.

    Args:
        sheet: the XLSX or CSV file (the paper release's ``seq_info.xlsx`` layout).
        session: the session folder; relative scene folders in the sheet are resolved against it.
        capture_pattern: where view recordings live; placeholders {scene_folder}, {scene},
            {seq_name}, {view}, {index}.
        contact_sheet: for a CSV sheet, a CSV with columns scene, contacts (list of xyz).
        body_model: body model file to record in the manifest (default: the generated test model).
        force: overwrite an existing session.toml.
        check: refuse to write a manifest whose folders do not exist.

    Returns the path of the written manifest.
    """
    target = SessionLayout(Path(session)).manifest
    if target.exists() and not force:
        raise InputError(target, "already exists", "pass --force to overwrite it")
    manifest = import_sheet(sheet, session, capture_pattern, contact_sheet, body_model)
    if check:
        problems = validate_manifest(manifest)
        if problems:
            listed = "".join(f"\n  - {p}" for p in problems)
            raise InputError(
                sheet,
                f"the imported manifest has {len(problems)} problem(s), nothing written "
                f"(check scene_folder, --capture-pattern, or pass --no-check):{listed}",
            )
    return write_manifest(manifest, target)


# --------------------------------------------------------------------------------------------
# Reading tables


def _read_tables(path: Path, contact_csv: str | Path | None) -> tuple[list[_Row], list[_Row]]:
    """Sequence rows (all non-contact sheets, in order) and contact rows."""
    if not path.is_file():
        raise InputError(path, "sheet file not found", "check the path")
    suffix = path.suffix.lower()
    if suffix in (".xlsx", ".xlsm"):
        if contact_csv is not None:
            raise InputError(contact_csv, "a separate contact sheet is only for CSV input", f"use the '{CONTACT_SHEET}' sheet of {path.name}")
        return _read_xlsx(path)
    if suffix in (".csv", ".tsv", ".txt"):
        contacts = list(_read_csv(Path(contact_csv))) if contact_csv is not None else []
        return list(_read_csv(path)), contacts
    raise InputError(path, f"unsupported sheet type {path.suffix!r}", "give an .xlsx or .csv file")


def _read_xlsx(path: Path) -> tuple[list[_Row], list[_Row]]:
    import openpyxl  # a core dependency; imported here so manifest users do not pay for it

    try:
        # data_only: formulas give their cached values, as a user sees them in Excel.
        book = openpyxl.load_workbook(path, read_only=True, data_only=True)
    except Exception as err:  # openpyxl raises many types for a damaged file
        raise InputError(path, f"cannot read the workbook: {err}", "save it again as .xlsx") from err
    try:
        rows: list[_Row] = []
        contacts: list[_Row] = []
        for ws in book.worksheets:
            target = contacts if ws.title.strip().lower() == CONTACT_SHEET else rows
            target.extend(_rows_of(ws.iter_rows(values_only=True), ws.title))
    finally:
        book.close()
    return rows, contacts


def _read_csv(path: Path) -> Iterator[_Row]:
    if not path.is_file():
        raise InputError(path, "file not found", "check the path")
    # utf-8-sig: Excel's CSV export starts with a byte-order mark.
    text = path.read_text(encoding="utf-8-sig")
    first = text.split("\n", 1)[0]
    # Header names never contain a delimiter, so the most frequent candidate in it is the one;
    # csv.Sniffer is fooled by the commas inside the contacts lists.
    delimiter = max(",;\t", key=first.count)
    yield from _rows_of(csv.reader(io.StringIO(text, newline=""), delimiter=delimiter), None)


def _rows_of(table: Any, sheet: str | None) -> Iterator[_Row]:
    """Rows after the header, keyed by normalised header; blank rows are skipped."""
    it = iter(table)
    header = next(it, None)
    if header is None:
        return
    labels = [str(h).strip() if h is not None else "" for h in header]
    names = [label.lower() for label in labels]
    by_name = {n: label for n, label in zip(names, labels) if n}
    for number, values in enumerate(it, start=2):
        cells = {n: _blank_to_none(v) for n, v in zip(names, values) if n}
        if any(v is not None for v in cells.values()):
            yield _Row(sheet, number, cells, by_name)


def _blank_to_none(value: Any) -> Any:
    if isinstance(value, str):
        value = value.strip()
        return value or None
    return value


# --------------------------------------------------------------------------------------------
# Cell parsing


@dataclass(frozen=True)
class _ParsedRow:
    row: _Row
    scene_folder: str
    seq_name: str
    indoor: bool | None
    starts: tuple[int | None, int | None]
    failed: bool
    note: str
    contacts: list[tuple[int, Any]]
    """(frame, xyz tuple or int id) pairs, ids resolved later against the contact sheet."""
    optim_scale: bool


def _parse_row(row: _Row, problems: _Problems) -> _ParsedRow | None:
    n_before = len(problems.lines)
    unknown = [c for c in row.cells if c not in _KNOWN_COLUMNS]
    if unknown:
        logger.warning("%s row %d: ignoring unknown column(s) %s", row.sheet or "csv", row.number, ", ".join(unknown))
    scene_folder = _text(row, "scene_folder", problems, required=True)
    seq_name = _text(row, "seq_name", problems, required=True)
    indoor = _boolean(row, "in_door", problems, default=None)
    starts = (_start(row, "v1_start", problems), _start(row, "v2_start", problems))
    failed = _boolean(row, "failed", problems, default=False)
    optim_scale = _boolean(row, "optim_scale", problems, default=False)
    note = _text(row, "note", problems) or ""
    contacts = _contacts_cell(row, "contacts", problems)

    skipped = [f"v{i + 1}_start" for i, s in enumerate(starts) if s == -1]
    if skipped:
        # The release skips every step of such a row; the manifest says so with `failed`.
        reason = f"skipped: {' and '.join(skipped)} = -1 in the sheet"
        note = f"{note}; {reason}" if note else reason
        failed = True
        starts = tuple(None if s == -1 else s for s in starts)  # type: ignore[assignment]
    if len(problems.lines) > n_before:
        return None
    return _ParsedRow(row, scene_folder, seq_name, indoor, starts, failed, note, contacts, optim_scale)  # type: ignore[arg-type]


def _text(row: _Row, column: str, problems: _Problems, required: bool = False) -> str | None:
    value = row.cells.get(column)
    if value is None:
        if required:
            problems.add(row, column, "empty, but required")
        return None
    if isinstance(value, float) and value.is_integer():
        value = int(value)  # Excel stores a typed-in 3 as 3.0
    return str(value).strip()


def _boolean(row: _Row, column: str, problems: _Problems, default: bool | None) -> bool | None:
    value = row.cells.get(column)
    if value is None:
        return default
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    problems.add(row, column, f"not a boolean: {value!r} (use TRUE/FALSE, 1/0 or leave empty)")
    return default


def _start(row: _Row, column: str, problems: _Problems) -> int | None:
    """A raw sync frame: int >= 0, -1 = skip, '-'/empty = detect automatically (None)."""
    value = row.cells.get(column)
    if value is None or value == "-":
        return None
    number = _integer(value)
    if number is None or number < -1:
        problems.add(row, column, f"not a frame number: {value!r} (use an integer >= 0, '-' to detect, -1 to skip)")
    return number


def _integer(value: Any) -> int | None:
    """An int from an int, an integral float or their text; None otherwise (bools are not ints)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            return None
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return int(value)
    return None


def _literal(row: _Row, column: str, problems: _Problems) -> Any:
    """The cell's Python literal, parsed with ast.literal_eval: data only, never code."""
    value = row.cells.get(column)
    if value is None:
        return None
    text = str(value)
    if len(text) > _MAX_LITERAL_CHARS:
        problems.add(row, column, f"text longer than {_MAX_LITERAL_CHARS} characters")
        return None
    try:
        return ast.literal_eval(text)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        problems.add(row, column, f"not a list literal: {text[:60]!r} (write e.g. [[120, [1.0, 2.0, 0.0]], [300, 2]])")
        return None


def _point(value: Any) -> tuple[float, float, float] | None:
    ok = (
        isinstance(value, (list, tuple))
        and len(value) == 3
        and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in value)
    )
    return tuple(float(c) for c in value) if ok else None  # type: ignore[return-value]


def _contacts_cell(row: _Row, column: str, problems: _Problems) -> list[tuple[int, Any]]:
    """[[frame, [x, y, z]] or [frame, id], ...] -> (frame, point or int id) pairs."""
    value = _literal(row, column, problems)
    if value is None:
        return []
    if not isinstance(value, (list, tuple)):
        problems.add(row, column, f"expected a list of [frame, [x, y, z]] or [frame, id], got {type(value).__name__}")
        return []
    out: list[tuple[int, Any]] = []
    for i, item in enumerate(value):
        frame = _integer(item[0]) if isinstance(item, (list, tuple)) and len(item) == 2 else None
        target = item[1] if frame is not None else None
        where = _point(target) if isinstance(target, (list, tuple)) else _integer(target)
        if frame is None or frame < 0 or where is None or (isinstance(where, int) and where < 0):
            problems.add(row, column, f"item {i} is {item!r}, expected [frame, [x, y, z]] or [frame, id] with frame, id >= 0")
            continue
        out.append((frame, where))
    return out


# --------------------------------------------------------------------------------------------
# Building the manifest


def _scene_name(scene_folder: str) -> str:
    return Path(scene_folder).name


def _build_scenes(path: Path, rows: list[_ParsedRow], root: Path) -> dict[str, SceneEntry]:
    """One scene per distinct scene folder; ``in_door`` from the scene's first row."""
    first: dict[str, _ParsedRow] = {}
    for r in rows:
        name = _scene_name(r.scene_folder)
        seen = first.setdefault(name, r)
        if Path(seen.scene_folder) != Path(r.scene_folder):
            raise InputError(
                path,
                f"{_where(r.row)}: scene folders {seen.scene_folder!r} and {r.scene_folder!r} share the name {name!r}",
                "rename one folder so scene names are unique",
            )
        if r.indoor is not None and seen.indoor is not None and r.indoor != seen.indoor:
            logger.warning(
                "%s: scene %r is in_door=%s at %s but %s at %s; using the first",
                path, name, seen.indoor, _where(seen.row), r.indoor, _where(r.row),
            )
    return {
        name: SceneEntry(name=name, capture=root / r.scene_folder, indoor=True if r.indoor is None else r.indoor)
        for name, r in first.items()
    }


def _add_markers(path: Path, scenes: dict[str, SceneEntry], contact_rows: list[_Row]) -> None:
    """Give each scene the markers "0", "1", ... of its contact-sheet list (mutates ``scenes``)."""
    problems = _Problems(path)
    by_scene: dict[str, tuple[_Row, list[tuple[float, float, float]]]] = {}
    for row in contact_rows:
        folder = _text(row, "scene", problems, required=True)
        points = _literal(row, "contacts", problems)
        if folder is None or points is None:
            continue
        checked = [_point(p) for p in points] if isinstance(points, (list, tuple)) else [None]
        if any(p is None for p in checked):
            problems.add(row, "contacts", "expected a list of [x, y, z] points")
            continue
        name = _scene_name(folder)
        if name in by_scene:
            problems.add(row, "scene", f"scene {name!r} already listed at {_where(by_scene[name][0])} (ids would be ambiguous)")
            continue
        by_scene[name] = (row, checked)  # type: ignore[assignment]
    problems.raise_if_any()
    for name, (row, points) in by_scene.items():
        if name not in scenes:
            logger.warning("%s: %s names scene %r, which no sequence row uses; ignored", path, _where(row), name)
            continue
        markers = {str(i): p for i, p in enumerate(points)}
        scenes[name] = SceneEntry(name=name, capture=scenes[name].capture, indoor=scenes[name].indoor, markers=markers)


def _build_sequences(
    path: Path,
    rows: list[_ParsedRow],
    scenes: dict[str, SceneEntry],
    root: Path,
    pattern: str,
    problems: _Problems,
) -> dict[str, SequenceEntry]:
    names = _sequence_names(path, rows)
    sequences: dict[str, SequenceEntry] = {}
    for r, name in zip(rows, names):
        scene = scenes[_scene_name(r.scene_folder)]
        views = {
            view: ViewEntry(capture=root / _capture(pattern, r, scene.name, view, i + 1), sync_frame=r.starts[i])
            for i, view in enumerate(VIEWS)
        }
        contacts = []
        for frame, where in r.contacts:
            if isinstance(where, tuple):
                contacts.append(ContactMarker(frame=frame, xyz=where))
            elif str(where) in scene.markers:
                contacts.append(ContactMarker(frame=frame, xyz=scene.markers[str(where)], marker=str(where)))
            else:
                problems.add(r.row, "contacts", f"contact id {where} is not in the '{CONTACT_SHEET}' sheet's list for scene {scene.name!r} ({len(scene.markers)} points)")
        if name in sequences:
            raise InputError(path, f"{_where(r.row)}: sequence name {name!r} is used twice", "rename one sequence")
        sequences[name] = SequenceEntry(
            name=name, scene=scene.name, views=views, contacts=tuple(contacts),
            optim_scale=r.optim_scale, note=r.note, failed=r.failed,
        )
    return sequences


def _sequence_names(path: Path, rows: list[_ParsedRow]) -> list[str]:
    """``seq_name``, or ``<scene>_<seq_name>`` where several scenes use the same ``seq_name``."""
    scenes_of: dict[str, set[str]] = {}
    first_row: dict[tuple[str, str], _Row] = {}
    for r in rows:
        key = (_scene_name(r.scene_folder), r.seq_name)
        if key in first_row:
            raise InputError(path, f"{_where(r.row)}: sequence {r.seq_name!r} of scene {key[0]!r} already at {_where(first_row[key])}", "remove the duplicate row")
        first_row[key] = r.row
        scenes_of.setdefault(r.seq_name, set()).add(key[0])
    return [
        r.seq_name if len(scenes_of[r.seq_name]) == 1 else f"{_scene_name(r.scene_folder)}_{r.seq_name}"
        for r in rows
    ]


def _capture(pattern: str, r: _ParsedRow, scene: str, view: str, index: int) -> str:
    try:
        return pattern.format(scene_folder=r.scene_folder, scene=scene, seq_name=r.seq_name, view=view, index=index)
    except (KeyError, IndexError, ValueError) as err:
        raise InputError(
            None, f"bad capture pattern {pattern!r}: {err}",
            "use only the placeholders {scene_folder}, {scene}, {seq_name}, {view}, {index}",
        ) from err


def _where(row: _Row) -> str:
    return f"sheet {row.sheet!r} row {row.number}" if row.sheet is not None else f"row {row.number}"
