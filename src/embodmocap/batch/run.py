"""``embodmocap batch``: run a dataset's plan on an executor, with retries, a catalog and progress.

    plan = make_plan(DATASET)                    scenes' Stage I, then each sequence's II -> III -> IV
    while tasks are left:
        submit every ready task (its dependencies done) while the executor has room
        wait for one to end:
            ok / up to date            -> done; its dependents become ready
            failed, attempts <= retries -> submitted again
            failed, no retries left     -> failed with its cause; the tasks that need it are
                                           ``blocked`` (recorded with the cause); the rest goes on
        the catalog records the attempt and re-reads the session's files

The scheduling is the same for the local pool and for Ray; only :class:`Executor` differs. Ctrl-C
interrupts the running tasks (their stages record ``interrupted``), records them, closes the
executor and returns status 130: running the same command again resumes (each stage's
fingerprints make finished work a no-op). The first Ctrl-C only sets a flag that the loop reads
between two waits, so it never lands inside Ray's, SQLite's or the pool's own calls; a second one
(while the tasks are being stopped) stops waiting for them.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

from embodmocap.batch.config import BatchConfig
from embodmocap.batch.plan import STAGES, Plan, Task, make_plan
from embodmocap.batch.task import TaskResult
from embodmocap.io.dataset import dataset_root
from embodmocap.pipeline import PipelineConfig

log = logging.getLogger(__name__)

#: Folder under the dataset root holding one log file per task.
LOG_DIR = "batch_logs"


class Executor(Protocol):
    """What the scheduler needs from an executor (:class:`LocalPool`, :class:`RayExecutor`)."""

    name: str
    capacity: int

    def submit(self, task: Task, log_file: Path | None) -> None: ...
    def wait(self, timeout: float) -> list[TaskResult]: ...
    def interrupt(self, grace_s: float = 60.0) -> list[TaskResult]: ...
    def close(self) -> None: ...


@dataclass
class TaskState:
    """Where one task stands: ``pending``, ``running``, ``ok``, ``current`` (up to date, nothing
    redone), ``failed`` (no retries left), ``blocked`` (a task it needs failed) or ``interrupted``."""

    task: Task
    status: str = "pending"
    attempts: int = 0
    error: str = ""
    seconds: float = 0.0
    """Time of the last attempt."""
    causes: list[str] = field(default_factory=list)
    """The error of every failed attempt, in order."""


@dataclass
class BatchResult:
    """What a batch did; ``exit_status``: 0 all done, 1 some task failed or was blocked, 130 interrupted."""

    plan: Plan
    states: dict[str, TaskState]
    executor: str
    seconds: float
    interrupted: bool = False

    def count(self, status: str, stage: str | None = None) -> int:
        return sum(1 for s in self.states.values() if s.status == status and (stage is None or s.task.stage == stage))

    @property
    def exit_status(self) -> int:
        if self.interrupted:
            return 130
        return 1 if any(s.status in ("failed", "blocked") for s in self.states.values()) else 0


def progress_line(states: dict[str, TaskState]) -> str:
    """``scene 1/2 done, 1 running | sequence 0/4 done | ... | failed 1, retried 2``."""
    parts = []
    retried = sum(max(0, s.attempts - 1) for s in states.values())
    for stage in STAGES + ("evaluate",):
        ss = [s for s in states.values() if s.task.stage == stage]
        if not ss:
            continue
        c = Counter(s.status for s in ss)
        bits = [f"{stage} {c['ok'] + c['current']}/{len(ss)} done"]
        for k in ("running", "failed", "blocked", "interrupted"):
            if c[k]:
                bits.append(f"{c[k]} {k}")
        parts.append(", ".join(bits))
    tail = f" | retried {retried}" if retried else ""
    return " | ".join(parts) + tail


def make_executor(cfg: BatchConfig, pipeline: PipelineConfig) -> Executor:
    """The executor ``cfg.executor`` names (``auto``: Ray when installed, else the local pool)."""
    import importlib.util

    kind = cfg.executor
    if kind == "auto":
        kind = "ray" if (cfg.address or importlib.util.find_spec("ray") is not None) else "local"
    if kind == "ray":
        from embodmocap.batch.ray_executor import RayExecutor

        return RayExecutor(cfg, pipeline, cfg.force)
    from embodmocap.batch.local_pool import LocalPool

    return LocalPool(cfg.worker_count(), pipeline, cfg.force)


def task_log_file(root: Path, task: Task) -> Path:
    """``DATASET/batch_logs/<session>/<stage>-<target>.log`` (every attempt appends)."""
    return root / LOG_DIR / task.session_name / f"{task.stage}-{task.target}.log"


@contextlib.contextmanager
def _sigint_flag(flag: list[bool]):
    """While the batch runs: the first SIGINT sets ``flag[0]`` instead of raising; later ones raise
    KeyboardInterrupt as usual. Nothing changes outside the main thread or where SIGINT is ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.getsignal(signal.SIGINT)
    if not callable(before):  # ignored (a background job) or not set from Python: leave it
        yield
        return

    def on_sigint(signum, frame):
        if flag[0]:
            before(signum, frame)  # the second Ctrl-C: as the caller would have it (KeyboardInterrupt)
        flag[0] = True

    signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def run_batch(dataset: str | Path, cfg: BatchConfig = BatchConfig(), pipeline: PipelineConfig = PipelineConfig(),
              *, executor: Executor | None = None, say: Callable[[str], None] | None = None,
              on_result: Callable[[TaskResult, dict[str, TaskState], Executor], None] | None = None) -> BatchResult:
    """Run every task of the dataset's plan (see the module docstring).

    Args:
        dataset: a folder of session folders, one session folder, or a list file.
        cfg: scheduling settings; ``pipeline``: every stage's settings (as ``embodmocap run``).
        executor: use this executor instead of the one ``cfg`` names (it is closed at the end).
        say: where progress lines go (default: stderr).
        on_result: called after each attempt is recorded (tests use it to inject faults).
    """
    t_start = time.perf_counter()
    say = say or (lambda m: print(m, file=sys.stderr, flush=True))
    only = cfg.only or STAGES
    plan = make_plan(dataset, only, include_failed=pipeline.include_failed, evaluate=cfg.evaluate)
    root = dataset_root(dataset)
    states = {t.key: TaskState(t) for t in plan.tasks}
    dependents = plan.dependents()
    catalog = None
    if cfg.catalog:
        from embodmocap.catalog.db import Catalog

        catalog = Catalog(root)
        catalog.refresh_sessions(sorted({t.session for t in plan.tasks}))
    for session, seq, why in plan.skipped:
        say(f"{session.name}/{seq}: {why}; skipped")
    stop = [False]
    with _sigint_flag(stop):
        return _schedule(plan, root, states, dependents, catalog, cfg, pipeline, executor, say, on_result, stop, t_start)


def _schedule(plan: Plan, root: Path, states: dict[str, TaskState], dependents, catalog, cfg: BatchConfig,
              pipeline: PipelineConfig, executor: Executor | None, say: Callable[[str], None], on_result,
              stop: list[bool], t_start: float) -> BatchResult:
    """The loop of :func:`run_batch` (``stop[0]``: Ctrl-C was pressed)."""
    try:
        ex = executor or make_executor(cfg, pipeline)
    except BaseException:
        if catalog is not None:
            catalog.close()
        raise
    say(f"batch: {len(plan)} tasks in {len({t.session for t in plan.tasks})} sessions on {ex.name} "
        f"({ex.capacity} at once, retries {cfg.retries})")
    last_line = ""

    def show() -> None:
        nonlocal last_line
        line = progress_line(states)
        if line != last_line:
            say(line)
            last_line = line

    def block(key: str, cause: str) -> None:
        for d in dependents[key]:
            st = states[d]
            if st.status == "pending":
                st.status, st.error = "blocked", cause
                if catalog is not None:
                    catalog.record_blocked(st.task, cause)
                block(d, cause)

    interrupted = False
    try:
        while True:
            if stop[0]:
                raise KeyboardInterrupt
            running = [s for s in states.values() if s.status == "running"]
            done = [k for k, s in states.items() if s.status in ("ok", "current")]
            started = [k for k, s in states.items() if s.status != "pending"]
            room = ex.capacity - len(running)
            for task in plan.ready(done, started)[:max(0, room)]:
                st = states[task.key]
                st.status = "running"
                st.attempts += 1
                ex.submit(task, task_log_file(root, task))
            show()
            if not any(s.status == "running" for s in states.values()):
                break
            for res in ex.wait(0.5):
                st = states[res.key]
                st.seconds = res.seconds
                if res.status == "interrupted":  # Ctrl-C reached the worker first: stop everything
                    st.status = "interrupted"
                    if catalog is not None:
                        catalog.record_attempt(st.task, res, st.attempts, final=True)
                    raise KeyboardInterrupt
                if res.status in ("ok", "current"):
                    st.status, st.error = res.status, ""
                elif st.attempts <= cfg.retries:
                    st.status = "pending"  # ready again at once: tried on the next round
                    st.causes.append(res.error)
                    say(f"{res.key}: attempt {st.attempts} failed ({res.error}); retrying")
                else:
                    st.causes.append(res.error)
                    st.status, st.error = "failed", res.error
                    say(f"{res.key}: FAILED after {st.attempts} attempt(s): {res.error}")
                    block(res.key, f"{res.key} failed: {res.error}")
                if catalog is not None:
                    catalog.record_attempt(st.task, res, st.attempts, final=st.status != "pending")
                    catalog.refresh_sessions([st.task.session])
                if on_result is not None:
                    on_result(res, states, ex)
    except KeyboardInterrupt:
        interrupted = True
        say("interrupted: stopping the running tasks (they record where they stopped) ...")
        for res in ex.interrupt(cfg.interrupt_grace_s):
            st = states.get(res.key)
            if st is None:
                continue
            st.status = res.status if res.status in ("ok", "current") else "interrupted"
            st.seconds = res.seconds
            if catalog is not None:
                catalog.record_attempt(st.task, res, st.attempts, final=True)
        for st in states.values():
            if st.status == "running":
                st.status = "interrupted"
        if catalog is not None:
            catalog.refresh_sessions(sorted({t.session for t in plan.tasks}))
    finally:
        ex.close()
        if catalog is not None:
            catalog.close()
    result = BatchResult(plan, states, ex.name, round(time.perf_counter() - t_start, 3), interrupted)
    show()
    return result
