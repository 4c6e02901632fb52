"""The Ray executor: each task a Ray task with the resources of its stage (extra ``cluster``).

``ray.init()`` starts a local Ray instance by default (``num_cpus`` = the batch's workers); with
``--address auto`` or ``HOST:PORT`` the batch joins an existing cluster. Ray's own retries are off
(``max_retries=0``): the batch retries failed tasks itself, so every attempt and its cause is
recorded in the catalog whatever ended it (an exception, a crashed or killed worker, a lost node).
Session folders must be on storage every node sees at the same path (NFS, a shared disk).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from embodmocap.batch.config import BatchConfig, TaskResources
from embodmocap.batch.plan import Task
from embodmocap.batch.task import TaskResult, error_line
from embodmocap.errors import require
from embodmocap.pipeline import PipelineConfig


def _remote_run(task: Task, cfg: PipelineConfig, force: bool, log_file: str | None) -> TaskResult:
    from embodmocap.batch.task import run_task

    return run_task(task, cfg, force, log_file)


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
        ref = self._fn.options(**opts).remote(task, self.pipeline, self.force, str(log_file) if log_file else None)
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
                if "Cancelled" in name:
                    out.append(TaskResult(task.key, "interrupted", seconds, "interrupted (task cancelled)", "ray"))
                else:
                    first = error_line(err).split("\n")[0]
                    out.append(TaskResult(task.key, "failed", seconds, f"ray: {first}", "ray"))
        return out

    def interrupt(self, grace_s: float = 60.0) -> list[TaskResult]:
        """Ctrl-C: cancel the running tasks (Ray raises KeyboardInterrupt inside each, so the stage
        records ``interrupted``), then collect how they ended."""
        for ref in list(self._refs):
            try:
                self.ray.cancel(ref)
            except Exception:  # noqa: BLE001 - already finished
                pass
        out: list[TaskResult] = []
        deadline = time.perf_counter() + grace_s
        while self._refs and time.perf_counter() < deadline:
            try:
                out += self.wait(0.5)
            except KeyboardInterrupt:
                break
        for ref, (task, t0) in list(self._refs.items()):
            self.ray.cancel(ref, force=True)
            out.append(TaskResult(task.key, "interrupted", round(time.perf_counter() - t0, 3), "interrupted", "ray"))
        self._refs.clear()
        return out

    def close(self) -> None:
        if self._started_here:
            self.ray.shutdown()
