"""Running one task of a batch: one stage of one scene or sequence, through the stage's public ``run``.

This is what a worker (a local process or a Ray worker) executes. It never raises for a failure
of the task itself: every error becomes a :class:`TaskResult` with status ``failed`` and the
error's first line as its cause (the full traceback goes to the task's log file), so the batch
decides about retries. Ctrl-C becomes status ``interrupted`` (the stage has recorded it in its
manifest, so the next run resumes there).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from embodmocap.batch.plan import Task
from embodmocap.errors import EmbodMocapError, interrupted, os_error_line, stop_watching_interrupts, watch_interrupts
from embodmocap.io.layout import SessionLayout
from embodmocap.pipeline import PipelineConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TaskResult:
    """How one attempt at a task ended.

    ``status``: ``ok`` (something was done), ``current`` (every step was already up to date, nothing
    redone), ``failed`` (``error`` says why) or ``interrupted`` (Ctrl-C).
    """

    key: str
    status: str
    seconds: float
    error: str = ""
    worker: str = ""
    """Where it ran: ``host:pid``."""
    log_file: str = ""


def stage_manifest_path(task: Task) -> Path:
    """The stage manifest the task's stage writes (its steps' fingerprints and finish times)."""
    lay = SessionLayout(task.session)
    if task.stage == "evaluate":
        return lay.evaluation
    if task.stage == "scene":
        return lay.scene(task.target).manifest
    seq = lay.sequence(task.target)
    return {"sequence": seq.manifest, "calibrate": seq.calibrate_manifest, "motion": seq.motion_manifest}[task.stage]


def _step_stamps(path: Path) -> dict[str, str] | None:
    """step -> finish time of each step recorded in a stage manifest (None when there is none)."""
    try:
        data = json.loads(path.read_text())
        return {k: str(v.get("finished")) for k, v in (data.get("steps") or {}).items() if isinstance(v, dict)}
    except (OSError, ValueError, AttributeError):
        return None


def _stage_end(path: Path) -> tuple | None:
    """(status, ended, steps' finish times) of a stage manifest (None when there is none)."""
    try:
        data = json.loads(path.read_text())
        return data.get("status"), data.get("ended"), _step_stamps(path)
    except (OSError, ValueError, AttributeError):
        return None


class StopGate:
    """A stop request (Ctrl-C of the batch) made by another thread of the worker, turned into Ctrl-C
    in the worker's main thread, but only while a stage runs.

    Inside the stage a KeyboardInterrupt is what a terminal's Ctrl-C gives: the stage records
    ``interrupted`` in its manifest and stops. Outside it (before the stage starts, after it
    returned) a request must not raise into the batch's own code: a request that arrives first
    keeps the stage from starting (:meth:`__enter__` raises at once), and one that arrives after the
    stage returned is ignored (the task ended anyway). The handler that :func:`stop_handler`
    installs checks :attr:`is_open` again in the main thread, because the interrupt it receives is
    asynchronous: it may run after the stage has returned.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open = False
        self.requested = False

    @property
    def is_open(self) -> bool:
        return self._open

    def request(self) -> None:
        """Stop the task (thread-safe; the first request counts)."""
        import _thread

        with self._lock:
            if self.requested:
                return
            self.requested = True
            if self._open:
                _thread.interrupt_main(signal.SIGINT)

    def __enter__(self) -> "StopGate":
        with self._lock:
            if self.requested:
                raise KeyboardInterrupt
            self._open = True
        return self

    def __exit__(self, *exc) -> None:
        with self._lock:
            self._open = False


@contextlib.contextmanager
def stop_handler(gate: StopGate) -> Iterator[None]:
    """While the task runs: SIGINT (what :meth:`StopGate.request` simulates) raises KeyboardInterrupt
    in the main thread only while ``gate`` is open; the package's record of SIGINT
    (:func:`embodmocap.errors.interrupted`) is kept as the CLI keeps it. Outside the main thread
    nothing is installed (the stop request then cannot interrupt the stage; the task ends on its own)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    watched = watch_interrupts()
    inner = signal.getsignal(signal.SIGINT)
    if not callable(inner):  # pragma: no cover - set just above
        inner = signal.default_int_handler

    def on_sigint(signum, frame):
        if gate.is_open:
            inner(signum, frame)

    signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        stop_watching_interrupts(watched)
        signal.signal(signal.SIGINT, before)


def _call_stage(task: Task, cfg: PipelineConfig, force: bool) -> None:
    if task.stage == "scene":
        from embodmocap.scene.stage import run

        run(cfg.scene, task.session, task.target, force=force)
    elif task.stage == "sequence":
        from embodmocap.sequence.stage import run

        run(cfg.sequence, task.session, task.target, force=force)
    elif task.stage == "calibrate":
        from embodmocap.calibrate.stage import run

        run(cfg.calibrate, task.session, task.target, force=force)
    elif task.stage == "motion":
        from embodmocap.motion.stage import run

        run(cfg.motion, task.session, task.target, force=force)
    elif task.stage == "evaluate":
        from embodmocap.evaluate.session import evaluate_session

        evaluate_session(task.session)
    else:  # pragma: no cover - the plan only makes the four
        raise ValueError(f"unknown stage {task.stage}")


def error_line(err: BaseException) -> str:
    """One line naming the cause, as ``embodmocap run`` reports it."""
    if isinstance(err, EmbodMocapError):
        msg = str(err)
    elif isinstance(err, OSError):
        msg = os_error_line(err)
    else:
        msg = f"{type(err).__name__}: {err}"
    return (msg.splitlines() or [type(err).__name__])[0][:500]


def run_task(task: Task, cfg: PipelineConfig, force: bool = False, log_file: str | Path | None = None,
             gate: StopGate | None = None) -> TaskResult:
    """Run ``task`` and say how it ended (never raises for the task's own failure; see the module
    docstring). ``log_file``: the package's log lines of this attempt are appended there. ``gate``:
    the stage runs inside it, so a stop request interrupts the stage only (see :class:`StopGate`)."""
    import socket

    worker = f"{socket.gethostname()}:{os.getpid()}"
    handler = None
    pkg = logging.getLogger("embodmocap")
    if log_file is not None:
        Path(log_file).parent.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(log_file)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        pkg.addHandler(handler)
        if pkg.level == logging.NOTSET or pkg.level > logging.INFO:
            pkg.setLevel(logging.INFO)
    manifest = stage_manifest_path(task)
    before = _step_stamps(manifest)
    end_before = _stage_end(manifest)
    t0 = time.perf_counter()
    try:
        log.info("%s: start on %s", task.key, worker)
        with gate if gate is not None else contextlib.nullcontext():
            _call_stage(task, cfg, force)
    except BaseException as err:  # noqa: BLE001 - every failure of a task is recorded, not raised
        seconds = round(time.perf_counter() - t0, 3)
        end = _stage_end(manifest) if task.stage != "evaluate" else None
        if interrupted(err) and not (end is not None and end[0] == "ok" and end != end_before):
            log.info("%s: interrupted after %.1f s", task.key, seconds)
            return TaskResult(task.key, "interrupted", seconds, "interrupted", worker, str(log_file or ""))
        if interrupted(err):
            # Ctrl-C came as the stage was returning: it had recorded its run as finished (``ok``),
            # so the task is done and is reported so (the catalog must agree with the manifest).
            log.info("%s: finished as the interrupt came, after %.1f s", task.key, seconds)
            return TaskResult(task.key, "ok", seconds, "", worker, str(log_file or ""))
        log.error("%s: failed after %.1f s:\n%s", task.key, seconds, traceback.format_exc())
        return TaskResult(task.key, "failed", seconds, error_line(err), worker, str(log_file or ""))
    finally:
        if handler is not None:
            pkg.removeHandler(handler)
            handler.close()
    seconds = round(time.perf_counter() - t0, 3)
    after = _step_stamps(stage_manifest_path(task))
    # ``evaluate`` has no steps: it always runs.
    status = "current" if (task.stage != "evaluate" and before is not None and after == before and not force) else "ok"
    if handler is not None:
        with open(log_file, "a") as f:  # type: ignore[arg-type]
            f.write(f"{task.key}: {status} in {seconds:.1f} s\n")
    return TaskResult(task.key, status, seconds, "", worker, str(log_file or ""))
