"""The dataset catalog, ``DATASET/catalog.sqlite``: one SQL database describing every session.

SQLite, not DuckDB: it is in Python's standard library (the catalog needs no extra and opens on
any machine, from any language, with the ``sqlite3`` shell), it has atomic transactions and a
single-writer lock that suit one batch driver updating rows as tasks end while users query, and a
catalog of thousands of sequences is tiny for it. DuckDB shines for large analytical scans, which
the Parquet export (``catalog.parquet``, read by DuckDB, pandas, polars) serves instead.

What is in it comes from the sessions' own files (``session.toml``, the stage manifests, Stage IV's
``smpl_world.npz``, ``evaluation.json``), so ``embodmocap catalog DATASET --rebuild`` can always
recreate it; only the ``attempts`` table (every batch attempt and its cause) is the batch's own
record, and a rebuild keeps it. Tables and columns: ``docs/formats.md``, "Dataset catalog".
"""

from __future__ import annotations

import logging
import math
import os
import sqlite3
import time
from pathlib import Path
from typing import Any, Iterable

from embodmocap.errors import EmbodMocapError, InputError
from embodmocap.io.jsonfile import read_json
from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import load_manifest

log = logging.getLogger(__name__)

CATALOG_NAME = "catalog.sqlite"
PARQUET_NAME = "catalog.parquet"
#: Bumped when a table changes; an older catalog is rebuilt from the files.
SCHEMA_VERSION = 1

SCHEMA = """
CREATE TABLE IF NOT EXISTS info (key TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS sessions (
  session TEXT PRIMARY KEY, path TEXT, scenes INTEGER, sequences INTEGER, ground_truth INTEGER,
  scanned_at TEXT);
CREATE TABLE IF NOT EXISTS scenes (
  session TEXT, scene TEXT, capture TEXT, indoor INTEGER, status TEXT, keyframes INTEGER,
  mesh_vertices INTEGER, mesh_faces INTEGER, mesh_area_m2 REAL, sfm_images INTEGER, sfm_points INTEGER,
  PRIMARY KEY (session, scene));
CREATE TABLE IF NOT EXISTS sequences (
  session TEXT, sequence TEXT, scene TEXT, marked_failed INTEGER, note TEXT, status TEXT,
  failed_stage TEXT, error TEXT, frames INTEGER, fps REAL, duration_s REAL, motion_frames INTEGER,
  valid_frames INTEGER, path TEXT, PRIMARY KEY (session, sequence));
CREATE TABLE IF NOT EXISTS views (
  session TEXT, sequence TEXT, view TEXT, capture TEXT, sync_frame INTEGER, sync_confidence REAL,
  frames_with_person INTEGER, mean_keypoint_confidence REAL, registered_fraction REAL, reproj_px REAL,
  PRIMARY KEY (session, sequence, view));
CREATE TABLE IF NOT EXISTS stages (
  session TEXT, stage TEXT, target TEXT, status TEXT, seconds REAL, steps INTEGER, error TEXT,
  ended TEXT, package_version TEXT, manifest_version INTEGER, attempts INTEGER, source TEXT,
  PRIMARY KEY (session, stage, target));
CREATE TABLE IF NOT EXISTS metrics (
  session TEXT, sequence TEXT, key TEXT, value REAL, PRIMARY KEY (session, sequence, key));
CREATE TABLE IF NOT EXISTS skill_clips (
  session TEXT, sequence TEXT, skill TEXT, start_frame INTEGER, end_frame INTEGER);
CREATE TABLE IF NOT EXISTS attempts (
  id INTEGER PRIMARY KEY AUTOINCREMENT, session TEXT, stage TEXT, target TEXT, attempt INTEGER,
  status TEXT, seconds REAL, error TEXT, worker TEXT, log_file TEXT, at TEXT, final INTEGER);
"""
#: Tables rebuilt from the sessions' files (``attempts`` is not: it is the batch's own record).
FILE_TABLES = ("sessions", "scenes", "sequences", "views", "stages", "metrics", "skill_clips")


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S")


def _read_json(path: Path) -> dict | None:
    try:
        data = read_json(path, max_bytes=64 << 20, what=path.name)
    except InputError:
        return None
    return data if isinstance(data, dict) else None


def _num(v: Any) -> float | None:
    if isinstance(v, bool):
        return float(v)
    if isinstance(v, (int, float)) and math.isfinite(float(v)):
        return float(v)
    return None


def _flat_numbers(d: dict, prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a nested dict, keys joined with ``.``."""
    out: dict[str, float] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat_numbers(v, key + "."))
        else:
            x = _num(v)
            if x is not None:
                out[key] = x
    return out


def stage_manifest_facts(path: Path) -> dict[str, Any]:
    """Status, timing and error of one stage manifest (``missing`` when there is none).

    Manifests of version 1 (before statuses were recorded) count as ``ok`` when they list steps.
    """
    data = _read_json(path)
    if data is None:
        return {"status": "missing" if not path.exists() else "unreadable", "seconds": None, "steps": 0,
                "error": "", "ended": None, "package_version": None, "manifest_version": None, "figures": {}}
    steps = data.get("steps") if isinstance(data.get("steps"), dict) else {}
    seconds = sum(float(s.get("seconds", 0.0) or 0.0) for s in steps.values() if isinstance(s, dict))
    status = data.get("status") or ("ok" if steps else "missing")
    ended = data.get("ended") or max((str(s.get("finished")) for s in steps.values() if isinstance(s, dict)), default=None)
    return {"status": status, "seconds": round(seconds, 3), "steps": len(steps), "error": data.get("error", ""),
            "ended": ended, "package_version": data.get("package_version"), "manifest_version": data.get("version"),
            "figures": data.get("figures") if isinstance(data.get("figures"), dict) else {}}


class Catalog:
    """An open catalog of the dataset at ``root`` (created when missing)."""

    def __init__(self, root: str | Path, *, path: str | Path | None = None) -> None:
        self.root = Path(os.path.abspath(root))
        self.path = Path(path) if path is not None else self.root / CATALOG_NAME
        self.db = sqlite3.connect(self.path, timeout=60.0)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.executescript(SCHEMA)
        row = self.db.execute("SELECT value FROM info WHERE key='schema_version'").fetchone()
        if row is None:
            with self.db:
                self.db.execute("INSERT OR REPLACE INTO info VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
        elif int(row[0]) != SCHEMA_VERSION:
            raise EmbodMocapError(f"{self.path}: catalog schema {row[0]}, this version writes {SCHEMA_VERSION} "
                                  "(run `embodmocap catalog DATASET --rebuild`)")

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> "Catalog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- the batch's record -------------------------------------------------------------------

    def record_attempt(self, task, result, attempt: int, final: bool) -> None:
        """One attempt at a batch task (``final``: no further attempt will follow)."""
        with self.db:
            self.db.execute(
                "INSERT INTO attempts (session, stage, target, attempt, status, seconds, error, worker, log_file, at, final)"
                " VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                (task.session_name, task.stage, task.target, attempt, result.status, result.seconds, result.error,
                 result.worker, result.log_file, _now(), int(final)))

    def record_blocked(self, task, cause: str) -> None:
        """A task not run because a task it needs failed."""
        with self.db:
            self.db.execute(
                "INSERT INTO attempts (session, stage, target, attempt, status, seconds, error, worker, log_file, at, final)"
                " VALUES (?,?,?,0,'blocked',0,?,'','',?,1)", (task.session_name, task.stage, task.target, cause, _now()))

    def _last_final_attempt(self, session: str, stage: str, target: str) -> tuple | None:
        return self.db.execute(
            "SELECT status, error, at, (SELECT COUNT(*) FROM attempts b WHERE b.session=a.session AND b.stage=a.stage"
            " AND b.target=a.target AND b.attempt>0) FROM attempts a WHERE session=? AND stage=? AND target=?"
            " AND final=1 ORDER BY id DESC LIMIT 1", (session, stage, target)).fetchone()

    # -- rows from the sessions' files --------------------------------------------------------

    def refresh_sessions(self, sessions: Iterable[str | Path]) -> None:
        """Re-read the files of these session folders and replace their rows (one transaction)."""
        for folder in sessions:
            rows = self._scan(Path(folder))
            with self.db:
                name = Path(folder).name
                for table in FILE_TABLES:
                    self.db.execute(f"DELETE FROM {table} WHERE session=?", (name,))
                for table, items in rows.items():
                    for item in items:
                        cols = ", ".join(item)
                        marks = ", ".join("?" for _ in item)
                        self.db.execute(f"INSERT INTO {table} ({cols}) VALUES ({marks})", tuple(item.values()))

    def _stage_row(self, session: str, stage: str, target: str, manifest: Path) -> dict[str, Any]:
        f = stage_manifest_facts(manifest)
        row = {"session": session, "stage": stage, "target": target, "status": f["status"], "seconds": f["seconds"],
               "steps": f["steps"], "error": f["error"], "ended": f["ended"], "package_version": f["package_version"],
               "manifest_version": f["manifest_version"], "attempts": 0, "source": "manifest"}
        last = self._last_final_attempt(session, stage, target)
        if last is not None:
            status, error, at, attempts = last
            row["attempts"] = attempts
            # The batch saw this stage end later than its manifest did (or the stage failed before it
            # could write one): the batch's word is the newer one.
            if status in ("failed", "blocked") and (f["ended"] is None or str(at) >= str(f["ended"])):
                row.update(status=status, error=error, source="batch")
        row["_figures"] = f["figures"]
        return row

    def _scan(self, folder: Path) -> dict[str, list[dict[str, Any]]]:
        from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid

        lay = SessionLayout(folder)
        name = folder.name
        try:
            m = load_manifest(lay.manifest)
        except InputError as err:
            log.warning("%s: not catalogued: %s", folder, err)
            return {"sessions": [{"session": name, "path": str(folder), "scenes": 0, "sequences": 0,
                                  "ground_truth": int(lay.ground_truth.info.is_file()), "scanned_at": _now()}]}
        out: dict[str, list[dict[str, Any]]] = {t: [] for t in FILE_TABLES}
        out["sessions"].append({"session": name, "path": str(folder), "scenes": len(m.scenes),
                                "sequences": len(m.sequences), "ground_truth": int(lay.ground_truth.info.is_file()),
                                "scanned_at": _now()})
        scene_status = {}
        for sc, entry in m.scenes.items():
            row = self._stage_row(name, "scene", sc, lay.scene(sc).manifest)
            fig = row.pop("_figures")
            out["stages"].append(row)
            scene_status[sc] = row
            out["scenes"].append({"session": name, "scene": sc, "capture": str(entry.capture), "indoor": int(entry.indoor),
                                  "status": row["status"], "keyframes": fig.get("keyframes"),
                                  "mesh_vertices": fig.get("mesh_vertices"), "mesh_faces": fig.get("mesh_faces"),
                                  "mesh_area_m2": fig.get("mesh_area_m2"), "sfm_images": fig.get("sfm_images"),
                                  "sfm_points": fig.get("sfm_points")})
        evaluation = _read_json(lay.evaluation) or {}
        evals = evaluation.get("sequences") if isinstance(evaluation.get("sequences"), dict) else {}
        for sq, entry in m.sequences.items():
            sl = lay.sequence(sq)
            stage_rows = {}
            figs = {}
            for stage, path in (("sequence", sl.manifest), ("calibrate", sl.calibrate_manifest),
                                ("motion", sl.motion_manifest)):
                row = self._stage_row(name, stage, sq, path)
                figs[stage] = row.pop("_figures")
                out["stages"].append(row)
                stage_rows[stage] = row
            chain = [("scene", scene_status.get(entry.scene, {"status": "missing", "error": ""}))] + list(stage_rows.items())
            status, failed_stage, error = "done", None, ""
            for stage, row in chain:
                if row["status"] in ("failed", "blocked", "interrupted", "running", "unreadable"):
                    status, failed_stage, error = ("failed" if row["status"] in ("failed", "blocked", "unreadable")
                                                   else row["status"]), stage, row.get("error", "")
                    break
                if row["status"] != "ok":
                    status = "pending"
                    break
            frames = figs["sequence"].get("frames")
            fps = _num(figs["sequence"].get("fps"))
            motion_frames = valid_frames = None
            if status == "done":
                try:
                    params, _ = read_smpl_npz(sl.smpl_world)
                    motion_frames = len(params)
                    valid_frames = int(read_smpl_valid(sl.smpl_world).sum())
                    fps = fps or params.fps
                except InputError as err:
                    status, failed_stage, error = "failed", "motion", str(err)
            n = motion_frames if motion_frames is not None else frames
            out["sequences"].append({
                "session": name, "sequence": sq, "scene": entry.scene, "marked_failed": int(entry.failed),
                "note": entry.note, "status": status, "failed_stage": failed_stage, "error": error,
                "frames": frames, "fps": fps, "duration_s": round(n / fps, 4) if n and fps else None,
                "motion_frames": motion_frames, "valid_frames": valid_frames, "path": str(sl.root)})
            for v in entry.view_names:
                ve = entry.views.get(v)
                out["views"].append({
                    "session": name, "sequence": sq, "view": v, "capture": str(ve.capture) if ve else None,
                    "sync_frame": figs["sequence"].get(f"{v}_sync_frame"),
                    "sync_confidence": _num(figs["sequence"].get(f"{v}_sync_confidence")),
                    "frames_with_person": figs["sequence"].get(f"{v}_frames_with_person"),
                    "mean_keypoint_confidence": _num(figs["sequence"].get(f"{v}_mean_keypoint_confidence")),
                    "registered_fraction": _num(figs["calibrate"].get(f"{v}_registered_fraction")),
                    "reproj_px": _num(figs["motion"].get(f"{v}_reproj_px"))})
            ev = evals.get(sq) if isinstance(evals.get(sq), dict) else {}
            for k, x in sorted(_flat_numbers(ev).items()):
                out["metrics"].append({"session": name, "sequence": sq, "key": k, "value": x})
            out["skill_clips"] += _skill_clips(name, sq, sl.skill_clips)
        return out

    # -- reading ------------------------------------------------------------------------------

    def query(self, sql: str, params: tuple = ()) -> tuple[list[str], list[tuple]]:
        """Column names and rows of a read-only query."""
        cur = self.db.execute(sql, params)
        cols = [d[0] for d in cur.description or ()]
        return cols, cur.fetchall()


#: Optional per-sequence file of labelled clips (``docs/formats.md``).
SKILL_CLIPS_NAME = "skill_clips.json"


def _skill_clips(session: str, seq: str, path: Path) -> list[dict[str, Any]]:
    """Rows of ``sequences/<seq>/skill_clips.json`` when present: ``{"clips": [{"skill", "start_frame",
    "end_frame"}, ...]}`` (a file that does not parse is reported and skipped)."""
    if not path.is_file():
        return []
    data = _read_json(path)
    clips = data.get("clips") if data else None
    if not isinstance(clips, list):
        log.warning("%s: no `clips` list; skill clips not catalogued", path)
        return []
    rows = []
    for c in clips:
        try:
            rows.append({"session": session, "sequence": seq, "skill": str(c["skill"]),
                         "start_frame": int(c["start_frame"]), "end_frame": int(c["end_frame"])})
        except (KeyError, TypeError, ValueError):
            log.warning("%s: clip %r skipped (needs skill, start_frame, end_frame)", path, c)
    return rows


def rebuild(dataset: str | Path) -> Path:
    """Recreate the catalog from every session's files, keeping the batch's ``attempts`` record.
    Written to a temporary file and renamed, so a reader never sees a half-built catalog."""
    from embodmocap.io.dataset import dataset_root, session_folders

    root = dataset_root(dataset)
    final = root / CATALOG_NAME
    tmp = root / f".{CATALOG_NAME}.{os.getpid()}.tmp"
    tmp.unlink(missing_ok=True)
    cat = Catalog(root, path=tmp)
    try:
        if final.is_file():
            old = sqlite3.connect(final)
            try:
                rows = old.execute("SELECT session, stage, target, attempt, status, seconds, error, worker, log_file, at,"
                                   " final FROM attempts ORDER BY id").fetchall()
            except sqlite3.Error:
                rows = []
            finally:
                old.close()
            with cat.db:
                cat.db.executemany("INSERT INTO attempts (session, stage, target, attempt, status, seconds, error, worker,"
                                   " log_file, at, final) VALUES (?,?,?,?,?,?,?,?,?,?,?)", rows)
        cat.refresh_sessions(session_folders(dataset))
        cat.db.execute("PRAGMA journal_mode=DELETE")  # one self-contained file to rename
    finally:
        cat.close()
    for suffix in ("-wal", "-shm"):
        Path(str(final) + suffix).unlink(missing_ok=True)
    os.replace(tmp, final)
    return final
