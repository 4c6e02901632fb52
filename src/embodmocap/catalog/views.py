"""What ``embodmocap catalog`` prints and exports: the summary, query tables, ``catalog.parquet``."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

from embodmocap.catalog.db import CATALOG_NAME, PARQUET_NAME
from embodmocap.errors import InputError, require

#: One row per sequence with its views and metrics folded in: the table ``catalog.parquet`` holds.
SEQUENCE_TABLE_SQL = """
SELECT q.session, q.sequence, q.scene, q.status, q.failed_stage, q.error, q.frames, q.fps, q.duration_s,
       q.motion_frames, q.valid_frames, q.marked_failed, q.path,
       v1.sync_frame AS v1_sync_frame, v2.sync_frame AS v2_sync_frame,
       v1.registered_fraction AS v1_registered_fraction, v2.registered_fraction AS v2_registered_fraction,
       v1.reproj_px AS v1_reproj_px, v2.reproj_px AS v2_reproj_px,
       (SELECT SUM(seconds) FROM stages s WHERE s.session = q.session AND s.target = q.sequence) AS stage_seconds
FROM sequences q
LEFT JOIN views v1 ON v1.session = q.session AND v1.sequence = q.sequence AND v1.view = 'v1'
LEFT JOIN views v2 ON v2.session = q.session AND v2.sequence = q.sequence AND v2.view = 'v2'
ORDER BY q.session, q.sequence
"""


def open_read_only(root: Path) -> sqlite3.Connection:
    """The catalog at ``root`` opened read-only (a query cannot change it)."""
    path = root / CATALOG_NAME
    if not path.is_file():
        raise InputError(path, "no catalog here", "run `embodmocap catalog DATASET --rebuild` or `embodmocap batch DATASET`")
    return sqlite3.connect(f"file:{path}?mode=ro", uri=True)


def run_query(db: sqlite3.Connection, sql: str) -> tuple[list[str], list[tuple]]:
    """Column names and rows of ``sql`` (one clear error for bad SQL)."""
    try:
        cur = db.execute(sql)
    except sqlite3.Error as err:
        raise InputError(None, f"query failed: {err}", "see docs/formats.md, 'Dataset catalog', for the tables") from None
    return [d[0] for d in cur.description or ()], cur.fetchall()


def format_table(cols: list[str], rows: list[tuple], max_width: int = 60) -> str:
    """A plain text table (values cut at ``max_width`` characters)."""
    def cell(v: Any) -> str:
        s = "" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v))
        return s if len(s) <= max_width else s[: max_width - 3] + "..."

    body = [[cell(v) for v in r] for r in rows]
    widths = [max([len(c)] + [len(r[i]) for r in body]) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths)) for r in body]
    return "\n".join(lines)


def summary(db: sqlite3.Connection) -> dict[str, Any]:
    """Stage counts by status, sequences done / failed, frames and hours of finished motion."""
    stages: dict[str, dict[str, int]] = {}
    for stage, status, n in db.execute("SELECT stage, status, COUNT(*) FROM stages GROUP BY stage, status"):
        stages.setdefault(stage, {})[status] = n
    seq = dict(db.execute("SELECT status, COUNT(*) FROM sequences GROUP BY status").fetchall())
    frames, seconds = db.execute("SELECT COALESCE(SUM(motion_frames), 0), COALESCE(SUM(duration_s), 0) FROM sequences"
                                 " WHERE status = 'done'").fetchone()
    n_sessions = db.execute("SELECT COUNT(*) FROM sessions").fetchone()[0]
    n_scenes = db.execute("SELECT COUNT(*) FROM scenes").fetchone()[0]
    return {"sessions": n_sessions, "scenes": n_scenes, "stages": stages, "sequences": seq,
            "motion_frames": int(frames), "motion_hours": round(float(seconds) / 3600.0, 4)}


def format_summary(s: dict[str, Any]) -> str:
    order = ("scene", "sequence", "calibrate", "motion")
    statuses = sorted({k for v in s["stages"].values() for k in v}, key=lambda k: (k != "ok", k))
    rows = [tuple([st] + [s["stages"].get(st, {}).get(k, 0) for k in statuses]) for st in order if st in s["stages"]]
    lines = [f"{s['sessions']} sessions, {s['scenes']} scenes, {sum(s['sequences'].values())} sequences "
             f"({', '.join(f'{n} {k}' for k, n in sorted(s['sequences'].items()))})", "",
             format_table(["stage"] + statuses, rows), "",
             f"finished motion: {s['motion_frames']} frames, {s['motion_hours'] * 60:.2f} min ({s['motion_hours']:.4f} h)"]
    return "\n".join(lines)


def export_parquet(db: sqlite3.Connection, out: Path) -> Path:
    """Write the per-sequence table (:data:`SEQUENCE_TABLE_SQL`) plus one column per metric
    (``metric.<key>``) to ``out`` as Parquet (extra ``catalog``: pyarrow), atomically."""
    pa = require("pyarrow", "catalog")
    pq = require("pyarrow.parquet", "catalog")
    from embodmocap.io.atomic import atomic_path

    cols, rows = run_query(db, SEQUENCE_TABLE_SQL)
    data: dict[str, list] = {c: [r[i] for r in rows] for i, c in enumerate(cols)}
    keys = [k for (k,) in db.execute("SELECT DISTINCT key FROM metrics ORDER BY key")]
    index = {(r[0], r[1]): i for i, r in enumerate(rows)}
    for k in keys:
        col: list = [None] * len(rows)
        for sess, seq, v in db.execute("SELECT session, sequence, value FROM metrics WHERE key = ?", (k,)):
            if (sess, seq) in index:
                col[index[(sess, seq)]] = v
        data[f"metric.{k}"] = col
    table = pa.table(data)
    with atomic_path(out, suffix=".parquet") as tmp:
        pq.write_table(table, tmp)
    return out


def default_parquet(root: Path) -> Path:
    return root / PARQUET_NAME
