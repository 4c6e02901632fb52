"""The Ray executor: each task a Ray task with the resources of its stage (extra ``cluster``).

``ray.init()`` starts a local Ray instance by default (``num_cpus`` = the batch's workers); with
``--address auto`` or ``HOST:PORT`` the batch joins an existing cluster. Ray's own retries are off
(``max_retries=0``): the batch retries failed tasks itself, so every attempt and its cause is
recorded in the catalog whatever ended it (an exception, a crashed or killed worker, a lost node).
Session folders must be on storage every node sees at the same path (NFS, a shared disk).

Ctrl-C: the batch never calls ``ray.cancel``. Ray 2.60's cancel of a task that is ending at that
moment can abort the driver inside Ray (a check failure in its task manager), and a cancel reaches
a task asynchronously anyway. Instead a small actor (:class:`StopFlag`, no CPU) holds the batch's
stop request; every task polls it from a thread and, once it is set, interrupts its own stage as a
terminal's Ctrl-C would (:class:`embodmocap.batch.task.StopGate`): the stage records
``interrupted`` in its manifest and the task returns normally. The batch waits for every task to
come back, then shuts Ray down. Ray's worker processes never see the terminal's SIGINT (Ray
blocks it in them), so this is the only way a stop reaches them, on any node.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from embodmocap.batch.config import BatchConfig, TaskResources
from embodmocap.batch.plan import Task
from embodmocap.batch.task import StopGate, TaskResult, error_line
from embodmocap.errors import require
from embodmocap.pipeline import PipelineConfig


#: Seconds between two looks of a task at the batch's stop flag.
STOP_POLL_S = 0.5


class StopFlag:
    """A Ray actor holding the batch's stop request (set by the driver on Ctrl-C, read by tasks)."""

    def __init__(self) -> None:
        self._stop = False

    def stop(self) -> bool:
        self._stop = True
        return True

    def stopped(self) -> bool:
        return self._stop


def _watch(flag, gate: StopGate, done: threading.Event) -> None:
    """In a task's worker, beside the task: pass the batch's stop request on to ``gate``."""
    import ray

    while True:  # a first look at once: a task submitted just before Ctrl-C does not start
        try:
            if ray.get(flag.stopped.remote(), timeout=5.0):
                gate.request()
                return
        except ray.exceptions.GetTimeoutError:
            pass
        except Exception:  # noqa: BLE001 - the flag is gone (its driver ended): nothing can ask to stop
            return
        if done.wait(STOP_POLL_S):
            return


def _remote_run(task: Task, cfg: PipelineConfig, force: bool, log_file: str | None, flag=None) -> TaskResult:
    from embodmocap.batch.task import run_task, stop_handler

    gate = StopGate()
    done = threading.Event()
    watcher = threading.Thread(target=_watch, args=(flag, gate, done), daemon=True, name="embodmocap-stop-watch")
    with stop_handler(gate):
        if flag is not None:
            watcher.start()
        try:
            return run_task(task, cfg, force, log_file, gate=gate)
        finally:
            # Not joined: a look at the flag in flight (the actor may still be starting) must not
            # delay the result. The thread ends after that look; a request it makes then finds
            # this task's gate closed and does nothing.
            done.set()


class RayExecutor:
    """Submit tasks to Ray (see the module docstring)."""

    name = "ray"

    def __init__(self, cfg: BatchConfig, pipeline: PipelineConfig, force: bool = False) -> None:
        ray = require("ray", "cluster")
        self.ray = ray
        self.cfg, self.pipeline, self.force = cfg, pipeline, force
        self._started_here = False
        if not ray.is_initialized():
            kw: dict = {"include_dashboard": False, "log_to_driver": False,
                        "runtime_env": {"env_vars": {"OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}}}
            if cfg.address:
                kw["address"] = cfg.address
            else:
                kw["num_cpus"] = cfg.worker_count()
                if cfg.ray_object_store_gb > 0:
                    kw["object_store_memory"] = int(cfg.ray_object_store_gb * (1 << 30))
            ray.init(**kw)
            self._started_here = True
        total = ray.cluster_resources().get("CPU", 1.0)
        # A task asking for more CPUs than the whole cluster has would wait forever.
        self._max_cpus = float(total)
        self.capacity = max(1, int(total)) if not cfg.address else max(1, cfg.workers or int(total))
        self._fn = ray.remote(max_retries=0)(_remote_run)
        self._refs: dict = {}  # ObjectRef -> (task, t0)
        # The stop flag lives as long as this driver (an actor it owns); it asks for no CPU, so it
        # never takes a task's place.
        self._flag = ray.remote(num_cpus=0)(StopFlag).remote()

    def _options(self, res: TaskResources) -> dict:
        opts = {"num_cpus": min(float(res.cpus), self._max_cpus), "name": "embodmocap"}
        if res.memory_gb > 0:
            opts["memory"] = int(res.memory_gb * (1 << 30))
        if res.gpus > 0:
            opts["num_gpus"] = res.gpus
        return opts

    @property
    def running(self) -> list[Task]:
        return [t for t, _ in self._refs.values()]

    def submit(self, task: Task, log_file: Path | None) -> None:
        res = self.cfg.resources.of(task.stage)
        opts = self._options(res)
        opts["name"] = task.key
        ref = self._fn.options(**opts).remote(task, self.pipeline, self.force, str(log_file) if log_file else None,
                                              self._flag)
        self._refs[ref] = (task, time.perf_counter())

    def wait(self, timeout: float) -> list[TaskResult]:
        if not self._refs:
            time.sleep(min(timeout, 0.05))
            return []
        ready, _ = self.ray.wait(list(self._refs), num_returns=1, timeout=timeout)
        out = []
        for ref in ready:
            task, t0 = self._refs.pop(ref)
            try:
                out.append(self.ray.get(ref))
            except Exception as err:  # noqa: BLE001 - a crashed worker, a lost node, a cancelled task
                seconds = round(time.perf_counter() - t0, 3)
                name = type(err).__name__
                if name in ("WorkerCrashedError", "NodeDiedError", "OutOfMemoryError"):
                    # The worker process (or its node) died under the task: killed, out of memory.
                    first = error_line(err).split("\n")[0]
                    out.append(TaskResult(task.key, "failed", seconds,
                                          f"worker process died while running the task (ray: {first})", "ray"))
                else:
                    first = error_line(err).split("\n")[0]
                    out.append(TaskResult(task.key, "failed", seconds, f"ray: {first}", "ray"))
        return out

    def interrupt(self, grace_s: float = 60.0) -> list[TaskResult]:
        """Ctrl-C: set the stop flag (each running task interrupts its stage, which records
        ``interrupted``; a task about to start does not start), then collect how every task ended.
        Tasks still running after ``grace_s`` (or after a second Ctrl-C) are left to :meth:`close`:
        shutting Ray down ends them (their stage manifests say ``running``, which a rerun resumes)."""
        try:
            self.ray.get(self._flag.stop.remote(), timeout=30.0)
        except Exception:  # noqa: BLE001 - the flag actor is gone: only the shutdown can stop the tasks
            pass
        out: list[TaskResult] = []
        deadline = time.perf_counter() + grace_s
        while self._refs and time.perf_counter() < deadline:
            try:
                out += self.wait(0.5)
            except KeyboardInterrupt:  # a second Ctrl-C: stop waiting
                break
        for task, t0 in self._refs.values():
            out.append(TaskResult(task.key, "interrupted", round(time.perf_counter() - t0, 3),
                                  f"interrupted (did not stop within {grace_s:.0f} s; ended by Ray's shutdown)", "ray"))
        self._refs.clear()
        return out

    def close(self) -> None:
        if self._started_here:
            self.ray.shutdown()
