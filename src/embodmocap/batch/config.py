"""Settings of ``embodmocap batch`` (no heavy import here: ``embodmocap --help`` reads this)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Literal

StageChoice = Literal["scene", "sequence", "calibrate", "motion"]


@dataclass(frozen=True)
class TaskResources:
    """What one task of a stage asks the scheduler for (Ray uses all three; the local pool runs one
    task per worker whatever they say)."""

    cpus: float = 1.0
    """CPU cores the task holds (Ray ``num_cpus``); capped at the cluster's total."""
    memory_gb: float = 0.0
    """Memory the task reserves, GiB (Ray ``memory``; 0 = no reservation)."""
    gpus: float = 0.0
    """GPUs the task holds (Ray ``num_gpus``; fractions share a GPU). Only for a stage whose
    backends use one (learned perception in Stage II, SMPLify in Stage IV on a CUDA build)."""


@dataclass(frozen=True)
class StageResources:
    """Resources of each stage's tasks. Defaults follow what the stages use on CPU: Stage I fuses
    depth and builds a sparse model (the heaviest), the others one core each."""

    scene: TaskResources = TaskResources(cpus=2.0, memory_gb=4.0)
    """Stage I (TSDF fusion, SfM)."""
    sequence: TaskResources = TaskResources(cpus=1.0, memory_gb=2.0)
    """Stage II (sync, slicing, perception)."""
    calibrate: TaskResources = TaskResources(cpus=1.0, memory_gb=2.0)
    """Stage III (registration, refinement)."""
    motion: TaskResources = TaskResources(cpus=1.0, memory_gb=2.0)
    """Stage IV (triangulation, SMPLify)."""
    evaluate: TaskResources = TaskResources(cpus=1.0, memory_gb=2.0)
    """``--evaluate``: one session's metrics."""

    def of(self, stage: str) -> TaskResources:
        return getattr(self, stage)


@dataclass(frozen=True)
class BatchConfig:
    """How ``embodmocap batch`` schedules the tasks."""

    address: str = ""
    """Ray cluster to join: ``auto`` (the cluster this machine belongs to) or ``HOST:PORT``. Empty:
    a local Ray instance started for this batch (or the local process pool without Ray)."""
    executor: Literal["auto", "ray", "local"] = "auto"
    """``ray``; ``local`` (a pool of worker processes on this machine); ``auto``: Ray when it is
    installed (extra ``cluster``), else the local pool."""
    workers: int = 0
    """Tasks run at once on this machine (local pool, local Ray); 0 = one per CPU core. With
    ``--address`` it caps the tasks in flight (0 = the cluster's CPUs)."""
    retries: int = 2
    """A failed task is tried again up to this many times, then recorded as failed with its cause
    (the tasks that need it are not run; everything else goes on)."""
    only: tuple[StageChoice, ...] = ()
    """Run only these stages (e.g. ``--only scene``); the stages left out must be done already.
    Empty: every stage."""
    force: bool = False
    """Redo every step even when its outputs are up to date."""
    evaluate: bool = False
    """Once every sequence of a session is fitted, evaluate the session (``embodmocap evaluate``:
    ``evaluation.json``), so its metrics reach the catalog. A session with a failed sequence is
    not evaluated (``blocked``): run ``embodmocap evaluate SESSION`` by hand."""
    catalog: bool = True
    """Update ``DATASET/catalog.sqlite`` as tasks end."""
    dry_run: bool = False
    """Print the plan (tasks in order, with their dependencies) and stop."""
    resources: StageResources = field(default_factory=StageResources)
    """Resources of each stage's tasks."""
    ray_object_store_gb: float = 1.0
    """Object store of a local Ray instance, GiB (the batch moves only small results through it;
    Ray's default reserves 30% of memory). 0 = Ray's default. Ignored with ``--address``."""
    interrupt_grace_s: float = 60.0
    """After Ctrl-C, how long running tasks get to record ``interrupted`` before they are killed."""

    def worker_count(self) -> int:
        return self.workers if self.workers > 0 else max(1, os.cpu_count() or 1)
