"""The Ray executor (extra `cluster`) runs the same plan as the local pool: a local Ray instance with
one CPU, a session whose scene capture is broken, retries recorded with their causes."""

from __future__ import annotations

import os
import sqlite3

import pytest

from embodmocap.batch.config import BatchConfig
from embodmocap.batch.run import run_batch
from embodmocap.pipeline import PipelineConfig

from test_batch import _session

ray = pytest.importorskip("ray")



def test_ray_executor_retries_and_records_like_the_local_pool(tmp_path, monkeypatch):
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ds = tmp_path / "ds"
    _session(ds / "bad", {"r": ["q"]})
    res = run_batch(ds, BatchConfig(executor="ray", workers=1, retries=1, ray_object_store_gb=0.1),
                    PipelineConfig(), say=lambda m: None)
    assert not ray.is_initialized()  # the batch shut down the instance it started
    st = res.states
    assert res.executor == "ray" and st["bad/scene/r"].status == "failed" and st["bad/scene/r"].attempts == 2
    assert "captures/r" in st["bad/scene/r"].error
    assert all(st[f"bad/{s}/q"].status == "blocked" for s in ("sequence", "calibrate", "motion"))
    db = sqlite3.connect(ds / "catalog.sqlite")
    rows = db.execute("SELECT attempt, status, worker FROM attempts WHERE stage='scene' ORDER BY id").fetchall()
    assert [r[:2] for r in rows] == [(1, "failed"), (2, "failed")]
    assert all(r[2] and not r[2].endswith(f":{os.getpid()}") for r in rows)  # ran in Ray's worker processes
