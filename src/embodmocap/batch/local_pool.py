"""The local executor: N worker processes on this machine (the default without Ray).

Each worker is a long-lived process (``spawn``: a fresh interpreter, so nothing of the parent's
state leaks in) that runs one task at a time and keeps its imports (torch, open3d) between
tasks. The pool knows which task each worker holds, so a worker that dies (killed, out of memory)
fails exactly that task, with the exit code as its cause, and a fresh worker takes its place; the
batch then retries the task like any other failure. ``concurrent.futures.ProcessPoolExecutor``
cannot do this: one dead worker breaks the whole pool and every task in it.

Ctrl-C: the workers let the first SIGINT interrupt their task (the stage records ``interrupted``
in its manifest) and ignore further ones, so the terminal's SIGINT and the one :meth:`interrupt`
forwards do not cut the stage's own clean-up short.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path

from embodmocap.batch.plan import Task
from embodmocap.batch.task import TaskResult
from embodmocap.pipeline import PipelineConfig


def _worker_main(conn: Connection) -> None:
    """A worker's loop: receive ``(task, cfg, force, log_file)``, send back the :class:`TaskResult`."""
    from embodmocap import errors
    from embodmocap.batch.task import run_task

    errors.interrupt_once()  # the first Ctrl-C interrupts the task; the rest must not interrupt its clean-up
    while True:
        try:
            msg = conn.recv()
        except (EOFError, KeyboardInterrupt):
            return
        if msg is None:
            return
        task, cfg, force, log_file = msg
        result = run_task(task, cfg, force, log_file)
        try:
            conn.send(result)
        except (BrokenPipeError, OSError):
            return
        if result.status == "interrupted":
            return


@dataclass
class _Worker:
    proc: mp.process.BaseProcess
    conn: Connection
    task: Task | None = None
    started: float = field(default_factory=time.perf_counter)


class LocalPool:
    """Run tasks on ``workers`` local processes (see the module docstring)."""

    name = "local"

    def __init__(self, workers: int, cfg: PipelineConfig, force: bool = False) -> None:
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.capacity = workers
        self.cfg, self.force = cfg, force
        self._ctx = mp.get_context("spawn")
        self._workers: list[_Worker] = []

    def _start_worker(self) -> _Worker:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=_worker_main, args=(child,), daemon=True, name="embodmocap-batch-worker")
        proc.start()
        child.close()
        w = _Worker(proc, parent)
        self._workers.append(w)
        return w

    @property
    def running(self) -> list[Task]:
        return [w.task for w in self._workers if w.task is not None]

    def submit(self, task: Task, log_file: Path | None) -> None:
        """Hand ``task`` to an idle worker (starting one when needed)."""
        idle = [w for w in self._workers if w.task is None and w.proc.is_alive()]
        if not idle and len(self.running) >= self.capacity:
            raise RuntimeError("no idle worker: the batch submitted more tasks than the pool holds")
        w = idle[0] if idle else self._start_worker()
        w.task, w.started = task, time.perf_counter()
        w.conn.send((task, self.cfg, self.force, str(log_file) if log_file else None))

    def wait(self, timeout: float) -> list[TaskResult]:
        """Results of the tasks that ended within ``timeout`` seconds (possibly none). A worker that
        died gives its task a ``failed`` result naming the exit code, and is replaced on demand."""
        busy = [w for w in self._workers if w.task is not None]
        if not busy:
            time.sleep(min(timeout, 0.05))
            return []
        ready = wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], timeout)
        out: list[TaskResult] = []
        for w in busy:
            if w.conn in ready or w.proc.sentinel in ready:
                res = self._collect(w)
                if res is not None:
                    out.append(res)
        return out

    def _collect(self, w: _Worker) -> TaskResult | None:
        assert w.task is not None
        task = w.task
        try:
            if w.conn.poll():
                res = w.conn.recv()
                w.task = None
                if res.status == "interrupted" or not w.proc.is_alive():
                    self._drop(w)
                return res
        except (EOFError, OSError):
            pass
        if w.proc.is_alive():
            return None  # woke up for nothing (e.g. a partial message): wait again
        w.proc.join(1.0)
        code = w.proc.exitcode
        seconds = round(time.perf_counter() - w.started, 3)
        self._drop(w)
        why = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        return TaskResult(task.key, "failed", seconds, f"worker process died ({why}) while running the task",
                          f"local:{w.proc.pid}")

    def _drop(self, w: _Worker) -> None:
        w.task = None
        try:
            w.conn.close()
        except OSError:
            pass
        if w in self._workers:
            self._workers.remove(w)

    def interrupt(self, grace_s: float = 60.0) -> list[TaskResult]:
        """Ctrl-C: forward one SIGINT to every busy worker and collect how their tasks ended (the
        stages record ``interrupted``); workers still busy after ``grace_s`` are killed."""
        busy = [w for w in self._workers if w.task is not None]
        for w in busy:
            if w.proc.is_alive() and w.proc.pid is not None:
                try:
                    os.kill(w.proc.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        out: list[TaskResult] = []
        deadline = time.perf_counter() + grace_s
        while any(w.task is not None for w in self._workers) and time.perf_counter() < deadline:
            try:
                out += self.wait(0.5)
            except KeyboardInterrupt:  # a second Ctrl-C: stop waiting
                break
        for w in list(self._workers):
            if w.task is not None:
                out.append(TaskResult(w.task.key, "interrupted", round(time.perf_counter() - w.started, 3),
                                      "interrupted (worker stopped)", f"local:{w.proc.pid}"))
                w.proc.kill()
                self._drop(w)
        return out

    def close(self) -> None:
        """Stop every worker (idle ones exit at once)."""
        for w in self._workers:
            try:
                w.conn.send(None)
            except (OSError, BrokenPipeError):
                pass
        for w in self._workers:
            w.proc.join(5.0)
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join(1.0)
            try:
                w.conn.close()
            except OSError:
                pass
        self._workers.clear()

    def worker_pids(self) -> dict[str, int]:
        """key of the task -> pid of the worker running it (for fault-injection tests)."""
        return {w.task.key: w.proc.pid for w in self._workers if w.task is not None and w.proc.pid is not None}
