"""The dataset catalog: rows from the sessions' own files, the batch's attempts kept across a
rebuild, summary, read-only queries, Parquet export (fast: sessions whose captures are broken).
Rows of fully processed sessions are checked in test_batch_pipeline.py (slow)."""

from __future__ import annotations

import json
import sqlite3

import pytest

from embodmocap.batch.config import BatchConfig
from embodmocap.batch.run import run_batch
from embodmocap.catalog import views
from embodmocap.catalog.db import rebuild
from embodmocap.cli import main
from embodmocap.errors import InputError
from embodmocap.pipeline import PipelineConfig

from test_batch import _session


@pytest.fixture()
def dataset(tmp_path):
    ds = tmp_path / "ds"
    _session(ds / "a", {"r1": ["x", "y"], "r2": ["z"]}, failed=("z",))
    _session(ds / "b", {"room": ["w"]})
    return ds


def test_rebuild_reads_the_sessions_files(dataset):
    path = rebuild(dataset)
    db = sqlite3.connect(path)
    assert db.execute("SELECT session, scenes, sequences, ground_truth FROM sessions ORDER BY session").fetchall() == [
        ("a", 2, 3, 0), ("b", 1, 1, 0)]
    assert db.execute("SELECT scene, capture, indoor, status FROM scenes WHERE session='a' ORDER BY scene").fetchall() == [
        ("r1", str(dataset / "a" / "captures" / "r1"), 1, "missing"), ("r2", str(dataset / "a" / "captures" / "r2"), 1, "missing")]
    seqs = db.execute("SELECT sequence, scene, marked_failed, status FROM sequences WHERE session='a' ORDER BY sequence").fetchall()
    assert seqs == [("x", "r1", 0, "pending"), ("y", "r1", 0, "pending"), ("z", "r2", 1, "pending")]
    v = db.execute("SELECT view, capture FROM views WHERE session='b' ORDER BY view").fetchall()
    assert v == [("v1", str(dataset / "b" / "captures" / "w" / "v1")), ("v2", str(dataset / "b" / "captures" / "w" / "v2"))]
    assert db.execute("SELECT COUNT(*) FROM stages").fetchone()[0] == 3 + 4 * 3  # scenes + 3 stages per sequence


def test_batch_failures_survive_a_rebuild_and_show_in_the_summary(dataset, capsys):
    res = run_batch(dataset, BatchConfig(retries=0, executor="local", workers=2), PipelineConfig(), say=lambda m: None)
    assert res.exit_status == 1
    before = sqlite3.connect(dataset / "catalog.sqlite").execute("SELECT * FROM attempts ORDER BY id").fetchall()
    assert len(before) == 3 + 3 * 3  # every scene (even r2, whose only sequence is marked failed) + 9 blocked
    rebuild(dataset)
    db = sqlite3.connect(dataset / "catalog.sqlite")
    assert db.execute("SELECT * FROM attempts ORDER BY id").fetchall() == before
    rows = dict(((r[0], r[1], r[2]), r[3]) for r in db.execute("SELECT session, stage, target, status FROM stages"))
    assert rows[("a", "scene", "r1")] == "failed" and rows[("a", "motion", "x")] == "blocked"
    assert rows[("a", "sequence", "z")] == "missing"  # marked failed: not run, not blocked
    s = views.summary(db)
    assert s["stages"]["scene"] == {"failed": 3} and s["stages"]["calibrate"]["blocked"] == 3
    assert s["sequences"] == {"failed": 4} and s["motion_frames"] == 0
    assert main(["catalog", str(dataset), "--summary", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == s


def test_query_is_read_only_and_parquet_round_trips(dataset, capsys):
    pq = pytest.importorskip("pyarrow.parquet")
    rebuild(dataset)
    assert main(["catalog", str(dataset), "--query", "SELECT session, sequence FROM sequences ORDER BY 1, 2"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == ["session", "sequence"] and "a        z" in out
    db = views.open_read_only(dataset)
    with pytest.raises(InputError, match="query failed"):
        views.run_query(db, "DELETE FROM sequences")
    with pytest.raises(InputError, match="query failed"):
        views.run_query(db, "SELECT nonsense FROM nowhere")
    assert main(["catalog", str(dataset), "--parquet"]) == 0
    table = pq.read_table(dataset / "catalog.parquet").to_pylist()
    assert [(r["session"], r["sequence"], r["scene"]) for r in table] == [
        ("a", "x", "r1"), ("a", "y", "r1"), ("a", "z", "r2"), ("b", "w", "room")]


def test_skill_clips_are_catalogued_when_present(dataset):
    seq_dir = dataset / "a" / "sequences" / "x"
    seq_dir.mkdir(parents=True)
    (seq_dir / "skill_clips.json").write_text(json.dumps({"clips": [
        {"skill": "sit", "start_frame": 10, "end_frame": 40}, {"skill": "climb", "start_frame": 50, "end_frame": 90},
        {"skill": "no frames"}]}))
    db = sqlite3.connect(rebuild(dataset))
    rows = db.execute("SELECT session, sequence, skill, start_frame, end_frame FROM skill_clips ORDER BY start_frame").fetchall()
    assert rows == [("a", "x", "sit", 10, 40), ("a", "x", "climb", 50, 90)]  # the incomplete clip is skipped
