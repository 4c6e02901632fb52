"""The ``embodmocap batch`` and ``embodmocap catalog`` commands (registered in :mod:`embodmocap.cli`).

Only configs are imported here; the batch machinery, the catalog and Ray load when a command runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from embodmocap.batch.config import BatchConfig
from embodmocap.pipeline import PipelineConfig


@dataclass(frozen=True)
class Batch:
    """Run every stage of every session of a dataset: each scene's Stage I and each sequence's
    Stages II-IV as tasks on a local process pool or on Ray (scenes before their sequences, the
    sequences of a scene in parallel), failed tasks retried, DATASET/catalog.sqlite kept up to date.
    Resumable: run the same command again after a failure or Ctrl-C."""

    dataset: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATASET")]
    """A folder of session folders, one session folder, or a text file listing session folders."""
    config: Annotated[BatchConfig, tyro.conf.arg(name="")] = BatchConfig()
    """Scheduling settings."""
    stages: Annotated[PipelineConfig, tyro.conf.arg(name="")] = PipelineConfig()
    """Settings of every stage (as `embodmocap run` takes them)."""

    def run(self) -> int:
        from embodmocap.batch.plan import STAGES, make_plan
        from embodmocap.batch.run import LOG_DIR, run_batch
        from embodmocap.io.dataset import dataset_root

        if self.config.dry_run:
            plan = make_plan(self.dataset, self.config.only or STAGES, self.stages.include_failed, self.config.evaluate)
            for t in plan.tasks:
                print(f"{t.key:<48} after {', '.join(t.deps) or '-'}")
            for session, seq, why in plan.skipped:
                print(f"{session.name}/{seq}: {why}; skipped")
            return 0
        res = run_batch(self.dataset, self.config, self.stages, say=lambda m: print(m, flush=True))
        print()
        bad = [s for s in res.states.values() if s.status in ("failed", "blocked", "interrupted")]
        for s in bad:
            print(f"  {s.task.key:<48} {s.status:<11} attempts {s.attempts}  {s.error}")
        root = dataset_root(self.dataset)
        print(f"{len(res.states)} tasks in {res.seconds:.0f} s on {res.executor}: "
              f"{res.count('ok')} done, {res.count('current')} already up to date, {res.count('failed')} failed, "
              f"{res.count('blocked')} blocked; logs in {root / LOG_DIR}"
              + (f"; catalog {root / 'catalog.sqlite'}" if self.config.catalog else ""))
        if res.interrupted:
            print("interrupted: run the same command again to resume")
        elif bad:
            print("fix the causes above and run the same command again: finished work is not redone")
        return res.exit_status


@dataclass(frozen=True)
class Catalog:
    """The dataset's catalog (DATASET/catalog.sqlite): rebuild it from the sessions' files, print a
    summary, run an SQL query, export catalog.parquet."""

    dataset: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATASET")]
    """A folder of session folders, one session folder, or a text file listing session folders."""
    rebuild: bool = False
    """Recreate the catalog from every session's files (keeps the batch's record of attempts)."""
    query: str | None = None
    """An SQL query to run on the catalog (read-only), printed as a table; tables in docs/formats.md."""
    summary: bool = False
    """Print stages done / failed, sequences, frames and hours of finished motion."""
    parquet: bool = False
    """Write DATASET/catalog.parquet (one row per sequence, metrics as columns; extra `catalog`)."""
    json: bool = False
    """Print --summary / --query as JSON."""

    def run(self) -> int:
        import json as _json

        from embodmocap.io.dataset import dataset_root
        from embodmocap.catalog import views
        from embodmocap.catalog.db import rebuild

        root = dataset_root(self.dataset)
        if self.rebuild or not (root / "catalog.sqlite").is_file():
            print(f"catalog: {rebuild(self.dataset)}")
        db = views.open_read_only(root)
        try:
            if self.summary or not (self.query or self.parquet):
                s = views.summary(db)
                print(_json.dumps(s, indent=2) if self.json else views.format_summary(s))
            if self.query:
                cols, rows = views.run_query(db, self.query)
                print(_json.dumps([dict(zip(cols, r)) for r in rows], indent=2) if self.json
                      else views.format_table(cols, rows))
            if self.parquet:
                print(f"wrote {views.export_parquet(db, views.default_parquet(root))}")
        finally:
            db.close()
        return 0

