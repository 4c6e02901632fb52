"""Every stage of a session in order: the recipe ``embodmocap run`` follows.

    for each scene:     Stage I   (scene mesh, sparse model)
    for each sequence:  Stage II  (sync, slicing, perception)
                        Stage III (both views in the scene's world)
                        Stage IV  (world SMPL motion, contact alignment)

With ``workers`` >= 2 (the default on two cores) the same stages run as jobs on worker processes,
each as soon as what it reads exists (Stage II beside Stage I, ...: :mod:`embodmocap.schedule`);
with 1, one after the other in this process as below. The outputs are the same.

Every stage is resumable (its steps are fingerprinted), so running the same command again after an
interruption or a fix redoes only what is missing or out of date. A sequence that fails is reported
with its cause and does not stop the others; the sequences of a scene that failed are not run and
count as failed.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

from embodmocap.calibrate.config import CalibrateConfig
from embodmocap.device import Device, motion_on_device
from embodmocap.errors import EmbodMocapError, failure_message, interrupted
from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.memory import map_large_blocks, release_freed_memory
from embodmocap.motion.config import MotionConfig
from embodmocap.scene.config import SceneConfig
from embodmocap.sequence.config import SequenceConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of every stage (each as its own stage command takes them)."""

    scene: SceneConfig = field(default_factory=SceneConfig)
    """Stage I."""
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    """Stage II."""
    calibrate: CalibrateConfig = field(default_factory=CalibrateConfig)
    """Stage III."""
    motion: MotionConfig = field(default_factory=MotionConfig)
    """Stage IV."""
    include_failed: bool = False
    """Also process sequences the manifest marks ``failed = true``."""
    device: Device | None = None
    """Where the torch work runs (Stage IV's fit): ``auto``, ``cpu`` or ``cuda``; replaces
    ``motion.smplify.device`` when given. ``cuda`` without a CUDA device is an error before any
    stage runs."""


@dataclass(frozen=True)
class StageRun:
    """One stage of one scene or sequence: ``ok``, ``failed`` (with ``error``) or ``skipped``."""

    target: str
    stage: str
    status: str
    seconds: float
    error: str = ""


@dataclass(frozen=True)
class PipelineResult:
    """What ``run_session`` did, stage by stage."""

    session: Path
    runs: tuple[StageRun, ...]

    @property
    def ok(self) -> bool:
        return all(r.status != "failed" for r in self.runs)

    def failed(self) -> list[StageRun]:
        return [r for r in self.runs if r.status == "failed"]


def run_session(cfg: PipelineConfig, session: str | Path, *, force: bool = False,
                on_progress: Callable[[str], None] | None = None, workers: int = 0) -> PipelineResult:
    """Run every stage for every scene and sequence of ``session`` (see the module docstring).

    ``workers``: stages run at once, each in a worker process (:mod:`embodmocap.schedule`); 0 = the
    usable cores, at most 2; 1 = one after the other in this process (the outputs are the same).
    """
    from embodmocap.schedule import default_workers, plan_jobs, run_jobs

    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    motion_cfg = motion_on_device(cfg.motion, cfg.device)
    say = on_progress or log.info
    runs: list[StageRun] = []
    workers = workers if workers > 0 else default_workers()
    if workers > 1:
        todo = []
        for name, entry in manifest.sequences.items():
            if entry.failed and not cfg.include_failed:
                say(f"sequence {name}: marked failed in the manifest; skipped")
                runs.append(StageRun(f"sequence {name}", "all", "skipped", 0.0, "marked failed in the manifest"))
            else:
                todo.append((name, entry.scene))
        run_jobs(replace(cfg, motion=motion_cfg, device=None), lay.root, plan_jobs(manifest.scenes, todo), workers,
                 force, say, lambda *r: runs.append(StageRun(*r)))
        return PipelineResult(lay.root, tuple(runs))
    # The stages are imported here, not above: with workers the scheduler only waits, and their
    # imports (torch among them, ~190 MB) would sit in its memory beside the workers' peaks.
    from embodmocap.calibrate import stage as stage3
    from embodmocap.motion import stage as stage4
    from embodmocap.scene import stage as stage1
    from embodmocap.sequence import stage as stage2

    map_large_blocks()  # one process runs every stage: keep its heap from holding a stage's peak (embodmocap.memory)

    def attempt(target: str, stage: str, fn: Callable[[], object]) -> bool:
        say(f"{target}: {stage} ...")
        t0 = time.perf_counter()
        try:
            fn()
        except (EmbodMocapError, RuntimeError, ValueError, OSError) as err:
            # Expected failures of one target (bad capture, too few registered frames, ...): report
            # and go on with the others. Programming errors (TypeError, KeyError, ...) propagate.
            if interrupted(err):  # Ctrl-C cut an import short: stop the whole run, as Ctrl-C does
                raise
            seconds = time.perf_counter() - t0
            msg = failure_message(err)
            log.debug("%s %s failed:\n%s", target, stage, traceback.format_exc())
            say(f"{target}: {stage} FAILED after {seconds:.0f} s: {msg}")
            runs.append(StageRun(target, stage, "failed", round(seconds, 2), msg))
            return False
        finally:
            # What the stage freed goes back to the system before the next one allocates next to
            # it: otherwise one process's peak is the next stage's on top of Stage I's (embodmocap.memory).
            release_freed_memory()
        seconds = time.perf_counter() - t0
        say(f"{target}: {stage} done in {seconds:.0f} s")
        runs.append(StageRun(target, stage, "ok", round(seconds, 2)))
        return True

    scenes_ok = {}
    for name in manifest.scenes:
        scenes_ok[name] = attempt(f"scene {name}", "scene", lambda n=name: stage1.run(cfg.scene, lay.root, n, force=force))
    for name, entry in manifest.sequences.items():
        target = f"sequence {name}"
        if entry.failed and not cfg.include_failed:
            say(f"{target}: marked failed in the manifest; skipped")
            runs.append(StageRun(target, "all", "skipped", 0.0, "marked failed in the manifest"))
            continue
        if not scenes_ok.get(entry.scene, False):
            runs.append(StageRun(target, "all", "failed", 0.0, f"its scene {entry.scene} failed"))
            say(f"{target}: skipped because its scene {entry.scene} failed")
            continue
        steps = (("sequence", lambda: stage2.run(cfg.sequence, lay.root, name, force=force)),
                 ("calibrate", lambda: stage3.run(cfg.calibrate, lay.root, name, force=force)),
                 ("motion", lambda: stage4.run(motion_cfg, lay.root, name, force=force)))
        for stage, fn in steps:
            if not attempt(target, stage, fn):
                break
    return PipelineResult(lay.root, tuple(runs))
