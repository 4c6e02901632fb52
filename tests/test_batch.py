"""`embodmocap batch`: the plan, retries and failure recording, a killed worker, the CLI's imports.

Fast tests: sessions are real session folders whose captures are broken (empty or missing files),
so every stage call is the real one and fails in about a second with its own message. The whole
pipeline on a real synthetic dataset is in test_batch_pipeline.py (slow).
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from embodmocap.batch.config import BatchConfig
from embodmocap.batch.local_pool import LocalPool
from embodmocap.batch.plan import Task, make_plan, session_folders
from embodmocap.batch.run import progress_line, run_batch
from embodmocap.errors import InputError
from embodmocap.pipeline import PipelineConfig


def _session(root: Path, scenes: dict[str, list[str]], failed: tuple[str, ...] = ()) -> Path:
    """A session folder whose manifest names empty capture folders (every stage fails on them at once)."""
    lines = ["version = 1", ""]
    for sc, seqs in scenes.items():
        (root / "captures" / sc).mkdir(parents=True)
        lines += [f"[scenes.{sc}]", f'capture = "captures/{sc}"', ""]
        for sq in seqs:
            lines += [f"[sequences.{sq}]", f'scene = "{sc}"'] + (["failed = true"] if sq in failed else []) + [""]
            for v in ("v1", "v2"):
                (root / "captures" / sq / v).mkdir(parents=True)
                lines += [f"[sequences.{sq}.views.{v}]", f'capture = "captures/{sq}/{v}"', ""]
    (root / "session.toml").write_text("\n".join(lines))
    return root


def test_plan_puts_scenes_first_and_each_sequence_in_stage_order(tmp_path):
    _session(tmp_path / "ds" / "s1", {"r1": ["a", "b"], "r2": ["c", "d"]}, failed=("d",))
    _session(tmp_path / "ds" / "s2", {"room": ["x"]})
    plan = make_plan(tmp_path / "ds")
    keys = [t.key for t in plan.tasks]
    pos = {k: i for i, k in enumerate(keys)}
    assert keys[:3] == ["s1/scene/r1", "s1/scene/r2", "s2/scene/room"]
    # Every dependency comes earlier; each sequence goes II -> III -> IV after its own scene.
    for t in plan.tasks:
        assert all(pos[d] < pos[t.key] for d in t.deps)
    by = plan.by_key()
    assert by["s1/sequence/c"].deps == ("s1/scene/r2",)
    assert by["s1/calibrate/c"].deps == ("s1/sequence/c",) and by["s1/motion/c"].deps == ("s1/calibrate/c",)
    assert len(plan) == 3 + 4 * 3 and "s1/sequence/d" not in by  # d is marked failed
    assert [(s.name, q) for s, q, _ in plan.skipped] == [("s1", "d")]
    assert "s1/sequence/d" in make_plan(tmp_path / "ds", include_failed=True).by_key()
    # Sequences of a scene run in parallel once the scene is done; nothing of r1 waits for r2.
    ready = {t.key for t in plan.ready(done=["s1/scene/r1"], started=["s1/scene/r1", "s1/scene/r2", "s2/scene/room"])}
    assert ready == {"s1/sequence/a", "s1/sequence/b"}
    # --only: the stages left out are not dependencies (they must be done already).
    only = make_plan(tmp_path / "ds", only=("calibrate", "motion"))
    assert {t.stage for t in only.tasks} == {"calibrate", "motion"}
    assert only.by_key()["s1/calibrate/a"].deps == () and only.by_key()["s1/motion/a"].deps == ("s1/calibrate/a",)


def test_dataset_forms(tmp_path):
    a = _session(tmp_path / "ds" / "a", {"r": ["q"]})
    b = _session(tmp_path / "ds" / "b", {"r": ["q"]})
    (tmp_path / "ds" / "notes").mkdir()  # a folder without session.toml is not a session
    assert session_folders(tmp_path / "ds") == [a, b]
    assert session_folders(a) == [a]
    lst = tmp_path / "ds" / "list.txt"
    lst.write_text("# my sessions\nb\n\na  # first take\n")
    assert session_folders(lst) == [b, a]
    lst.write_text("b\nnotes\n")
    with pytest.raises(InputError, match="line 2"):
        session_folders(lst)
    _session(tmp_path / "other" / "a", {"r": ["q"]})
    lst.write_text(f"a\n{tmp_path / 'other' / 'a'}\n")
    with pytest.raises(InputError, match="two sessions are named a"):
        session_folders(lst)
    with pytest.raises(InputError, match="no session folder"):
        session_folders(tmp_path / "ds" / "notes")


def test_a_failing_task_is_retried_then_recorded_and_the_rest_goes_on(tmp_path):
    ds = tmp_path / "ds"
    _session(ds / "bad", {"r": ["q"]})  # empty scene capture: Stage I fails at once, every time
    good = _session(ds / "good", {"r": ["q"]})
    # The second session's scene capture has its files, the sequence's views are still empty.
    (good / "captures" / "r" / "odometry.csv").write_text("timestamp, frame, x, y, z, qx, qy, qz, qw\n")
    lines: list[str] = []
    res = run_batch(ds, BatchConfig(retries=2, executor="local", workers=2), PipelineConfig(), say=lines.append)
    st = res.states
    assert st["bad/scene/r"].status == "failed" and st["bad/scene/r"].attempts == 3
    assert len(st["bad/scene/r"].causes) == 3 and "captures/r" in st["bad/scene/r"].error
    assert st["good/scene/r"].status == "failed" and st["good/scene/r"].attempts == 3  # tried on its own
    for s in ("bad", "good"):
        for stage in ("sequence", "calibrate", "motion"):
            assert st[f"{s}/{stage}/q"].status == "blocked" and f"{s}/scene/r failed" in st[f"{s}/{stage}/q"].error
            assert st[f"{s}/{stage}/q"].attempts == 0
    assert res.exit_status == 1
    assert any("retrying" in m for m in lines) and any("FAILED after 3 attempt(s)" in m for m in lines)
    # The catalog holds every attempt with its cause, and the stage rows say failed / blocked.
    db = sqlite3.connect(ds / "catalog.sqlite")
    rows = db.execute("SELECT attempt, status, error, final FROM attempts WHERE session='bad' AND stage='scene'"
                      " ORDER BY id").fetchall()
    assert [(r[0], r[1], r[3]) for r in rows] == [(1, "failed", 0), (2, "failed", 0), (3, "failed", 1)]
    assert all(r[2] == st["bad/scene/r"].error for r in rows)
    stages = dict(((r[0], r[1]), r[2:]) for r in db.execute(
        "SELECT stage, target, status, attempts, error FROM stages WHERE session='bad'"))
    assert stages[("scene", "r")][:2] == ("failed", 3) and stages[("motion", "q")][0] == "blocked"
    seq = db.execute("SELECT status, failed_stage FROM sequences WHERE session='bad'").fetchone()
    assert seq == ("failed", "scene")
    # Each attempt's log lines (with the traceback) are in the task's log file.
    log_text = (ds / "batch_logs" / "bad" / "scene-r.log").read_text()
    assert log_text.count("start on") == 3 and "Traceback" in log_text


def test_a_killed_worker_fails_only_its_task_and_is_replaced(tmp_path):
    """SIGKILL a worker in the middle of its task: the pool reports that task failed with the
    signal, starts a fresh worker, and the batch retries the task there."""
    ds = tmp_path / "ds"
    _session(ds / "s", {"r": ["q"]})
    pool = LocalPool(1, PipelineConfig())
    killed: list[int] = []

    def killer():
        deadline = time.time() + 60
        while time.time() < deadline and not killed:
            pids = pool.worker_pids()
            if "s/scene/r" in pids:
                os.kill(pids["s/scene/r"], signal.SIGKILL)
                killed.append(pids["s/scene/r"])
            time.sleep(0.01)

    th = threading.Thread(target=killer)
    th.start()
    res = run_batch(ds, BatchConfig(retries=1, only=("scene",), catalog=False), PipelineConfig(), executor=pool,
                    say=lambda m: None)
    th.join()
    st = res.states["s/scene/r"]
    assert killed and st.attempts == 2
    assert st.causes[0] == "worker process died (killed by signal 9) while running the task"
    assert "captures/r" in st.causes[1]  # the retry ran to the stage's own error on a new worker


def test_progress_line_counts_per_stage(tmp_path):
    from embodmocap.batch.run import TaskState

    s = tmp_path / "s"
    states = {k: TaskState(Task(s, st, t, "r")) for k, st, t in
              (("a", "scene", "r"), ("b", "sequence", "x"), ("c", "sequence", "y"), ("d", "calibrate", "x"))}
    states["a"].status, states["b"].status, states["c"].status = "ok", "running", "failed"
    states["c"].attempts = 3
    assert progress_line(states) == ("scene 1/1 done | sequence 0/2 done, 1 running, 1 failed | calibrate 0/1 done"
                                     " | retried 2")


def test_help_imports_no_heavy_module():
    code = ("import sys\nfrom embodmocap.cli import main\n"
            "for cmd in (['--help'], ['batch', '--help'], ['catalog', '--help']):\n"
            "    try:\n        main(cmd)\n    except SystemExit:\n        pass\n"
            "heavy = [m for m in ('torch', 'open3d', 'ray', 'duckdb', 'pyarrow') if m in sys.modules]\n"
            "print('HEAVY', heavy)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "COLUMNS": "100"})
    assert "HEAVY []" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


def test_evaluate_runs_after_every_sequence_of_its_session(tmp_path):
    _session(tmp_path / "ds" / "s1", {"r1": ["a", "b"]})
    plan = make_plan(tmp_path / "ds", evaluate=True)
    assert plan.tasks[-1].key == "s1/evaluate/s1" and plan.tasks[-1].deps == ("s1/motion/a", "s1/motion/b")
    # A session whose only sequence is marked failed: evaluate has nothing to wait for and runs
    # the real `evaluate` (evaluation.json lists the sequence as missing, naming why).
    ds = tmp_path / "ds2"
    s = _session(ds / "s", {"r": ["q"]}, failed=("q",))
    res = run_batch(ds, BatchConfig(only=("motion",), evaluate=True, executor="local", workers=1), PipelineConfig(),
                    say=lambda m: None)
    assert res.states["s/evaluate/s"].status == "ok" and res.exit_status == 0
    ev = json.loads((s / "evaluation.json").read_text())
    assert "marks it failed" in ev["sequences"]["q"]["missing"]
    db = sqlite3.connect(ds / "catalog.sqlite")
    assert db.execute("SELECT stage, status FROM attempts").fetchall() == [("evaluate", "ok")]
