"""``embodmocap run`` on several cores: a session's stages as jobs on worker processes.

What each job needs (``pipeline.py`` runs the same stages one after the other with one worker):

    job            what it runs                                   starts once
    scene/S        Stage I of scene S                             -
    sequence/Q     Stage II of sequence Q                         - (Stage II reads nothing of Stage I)
    register/Q     Stage III's registration of Q's views          sequence/Q is done and S's ``sfm``
                   (``calibrate.stage.run(only_register=True)``)  step is (it reads only that step's
                                                                  model: REGISTER_AFTER)
    calibrate/Q    Stage III (its registration already current)   register/Q is done and S's ``mesh``
                   (``run(scene_running=True)``)                  step is (CALIBRATE_AFTER: Stage III
                                                                  reads the raw mesh, not what
                                                                  ``floor`` and ``simplify`` make)
    motion/Q       Stage IV                                       scene/S and calibrate/Q are done (the
                                                                  fit's floor is the simplified mesh)

At most ``workers`` jobs run at once; a free worker takes the ready job that comes first in
:data:`PRIORITY`: Stage I, then Stage III and IV (the chain after Stage I is the run's critical
path), then the registration and Stage II, which fit beside Stage I. On the 60 s session the second
core runs Stage II while Stage I builds its sparse model, then the registration while Stage I fuses
its mesh (about as long: :data:`REGISTER_AFTER`), then the rest of Stage III beside Stage I's
``floor`` and ``simplify`` (:data:`CALIBRATE_AFTER`), so the run's wall time is about Stage I's
key frames, sparse model and mesh + the rest of Stage III + Stage IV.

After Stage I and II the chain (registration, the rest of Stage III, Stage IV) is all that is left
of a one-sequence session, and the second worker would idle: a job that starts when no other job
runs and every job left waits for it is lent every worker's core (:func:`cores_for`; the worker
runs it inside :func:`embodmocap.parallel.lend_cores`). Stage IV then fits its windows in two
processes (:mod:`embodmocap.motion.smplify`: the windows are independent, the answer is the one
process's), the second started as the Stage IV job begins (:data:`FIT_PRELOAD`), so that its
imports overlap the triangulation on the idle core; the registration already uses both cores (its
frames on a thread pool, the views' frames decoded beside the scene index:
:mod:`embodmocap.calibrate.stage`).

Workers are processes started with ``spawn`` (a fresh interpreter: no OpenMP or torch thread pool
copied half-initialised through ``fork``); a worker takes the next job when one is ready as it ends
(its imports are paid once), preferably the next job of its own scene or sequence; it waits idle
when that job waits only on running ones (the registration's worker for Stage I's mesh), else it is
stopped, so no idle process holds memory next to a peak (a worker told to stop ends at once, without
the interpreter's teardown of its modules). A worker tells the scheduler which steps it finished (through
:data:`embodmocap.io.stage_manifest.STEP_LISTENERS`), forwards its log records to this process's
handlers, and returns the memory a job freed to the system before the next one.

The house rules of the sequential run hold: a job that fails is reported with its cause and the
jobs that need it are not run (a failed scene's sequences are reported failed), the others go on;
Ctrl-C interrupts every worker's stage (each records ``interrupted`` in its manifest) and is
raised here; a worker that dies fails its job. Every stage keeps its fingerprints, so the outputs
are the sequential run's and a rerun resumes.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
import traceback
import types
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)

#: Which ready job a free worker takes first (job kinds, see the module docstring).
PRIORITY = ("scene", "calibrate", "motion", "register", "sequence")
#: The stage each job kind runs, as progress lines and :class:`~embodmocap.pipeline.StageRun` name it.
STAGE_OF = {"scene": "scene", "sequence": "sequence", "register": "register", "calibrate": "calibrate",
            "motion": "motion"}
#: The step of Stage I after which the registration starts: the one whose sparse model it reads.
#: It then runs beside Stage I's ``mesh`` (on the 60 s session both take ~28 CPU s), off the run's
#: critical path. Memory: Stage I's mesh peaks at ~2.9 GB on a 15 s scan and a registration of
#: 60 s views at ~0.75 GB; with the scheduler at ~0.1 GB (it imports no stage) the sum stays below
#: the sequential run's peak (~4.1 GB, reached in Stage I). Session 10 waited for ``mesh`` when the
#: scheduler held ~0.3 GB: the registration's 29 s were then on the critical path.
REGISTER_AFTER = "sfm"
#: The step of Stage I after which the rest of Stage III may start: it reads the sparse model and
#: the raw mesh, not what Stage I's ``floor`` and ``simplify`` steps make, so those two run beside it.
CALIBRATE_AFTER = "mesh"
#: Lend a job every worker's core when no other job runs and every job left waits for it (the
#: chain's last jobs, Stage III and IV of a session's last sequence): its stage may then split work
#: whose answer does not depend on the split over the idle cores (:func:`embodmocap.parallel.lent_cores`:
#: Stage IV's fit windows in two processes, :mod:`embodmocap.motion.smplify`).
LEND_IDLE_CORES = True
#: The module Stage IV's fit workers preload (what :mod:`embodmocap.motion.smplify` passes to
#: :func:`embodmocap.motion.fit_workers.start_workers`). A Stage IV job starts them as it begins
#: (:func:`embodmocap.motion.fit_workers.prestarted`), so that their imports (torch, the body model
#: and the fit: seconds in a fresh interpreter) overlap the triangulation and the fit's start on
#: the idle core; the fit takes them when it splits its windows.
FIT_PRELOAD = ("embodmocap.motion.smplify",)
#: Seconds a worker gets after Ctrl-C to record ``interrupted`` before it is killed.
INTERRUPT_GRACE_S = 30.0


def default_workers() -> int:
    """Usable cores (the process's CPU affinity), at most 2: the stages beside each other fill two
    cores; a third worker would find nothing ready on a one-sequence session."""
    from embodmocap.parallel import usable_cores

    return min(2, usable_cores())


@dataclass(frozen=True)
class Job:
    """One stage (or Stage III's registration) of one scene or sequence."""

    kind: str
    """``scene``, ``sequence``, ``register``, ``calibrate`` or ``motion``."""
    name: str
    """The scene's or the sequence's name."""
    needs: tuple[str, ...] = ()
    """Keys of the jobs that must be done, or ``key#step`` for a step of a job that is running."""
    scene: str = ""
    """The scene a sequence's job belongs to."""

    @property
    def key(self) -> str:
        return f"{self.kind}/{self.name}"

    @property
    def target(self) -> str:
        return f"scene {self.name}" if self.kind == "scene" else f"sequence {self.name}"


def plan_jobs(scenes, sequences) -> list[Job]:
    """The jobs of a session (see the module docstring). ``scenes``: scene names; ``sequences``:
    (sequence name, scene name) of the sequences to run."""
    jobs = [Job("scene", s) for s in scenes]
    for q, s in sequences:
        jobs += [Job("sequence", q, scene=s),
                 Job("register", q, (f"sequence/{q}", f"scene/{s}#{REGISTER_AFTER}"), s),
                 Job("calibrate", q, (f"scene/{s}#{CALIBRATE_AFTER}", f"register/{q}"), s),
                 Job("motion", q, (f"scene/{s}", f"calibrate/{q}"), s)]
    return jobs


def _upstream(key: str, by_key: dict[str, Job]) -> set[str]:
    """The keys of the jobs that job ``key`` waits for, directly or not."""
    seen: set[str] = set()
    todo = [n.split("#")[0] for n in by_key[key].needs]
    while todo:
        k = todo.pop()
        if k not in seen:
            seen.add(k)
            todo += [n.split("#")[0] for n in by_key[k].needs]
    return seen


def cores_for(key: str, jobs: list[Job], state: dict[str, str], workers: int) -> int:
    """The cores job ``key`` may use as it starts: every worker's when no other job runs and every
    job left (``pending``) waits for it, directly or not (the other workers would idle until it
    ends), else one. ``state``: each job's key -> ``pending``, ``running``, ``ok``, ``failed``, ...
    (see :data:`LEND_IDLE_CORES`)."""
    others = [k for k, s in state.items() if k != key and s in ("pending", "running")]
    if not LEND_IDLE_CORES or any(state[k] == "running" for k in others):
        return 1
    by_key = {j.key: j for j in jobs}
    return workers if all(key in _upstream(k, by_key) for k in others) else 1


def _call(job: Job, cfg, session: Path, force: bool) -> None:
    """Run ``job``'s stage function (in a worker). ``cfg``: the PipelineConfig, device resolved."""
    if job.kind == "scene":
        from embodmocap.scene.stage import run

        run(cfg.scene, session, job.name, force=force)
    elif job.kind == "sequence":
        from embodmocap.sequence.stage import run

        run(cfg.sequence, session, job.name, force=force)
    elif job.kind in ("register", "calibrate"):
        from embodmocap.calibrate.stage import run

        run(cfg.calibrate, session, job.name, force=force, only_register=job.kind == "register",
            scene_running=job.kind == "calibrate")
    elif job.kind == "motion":
        from embodmocap.motion.fit_workers import prestarted
        from embodmocap.motion.stage import run

        with prestarted(fit_helpers(cfg.motion), FIT_PRELOAD, cfg.motion.smplify.threads):
            run(cfg.motion, session, job.name, force=force)
    else:  # pragma: no cover - plan_jobs makes only these
        raise ValueError(f"unknown job {job.kind}")


def fit_helpers(motion_cfg) -> int:
    """The fit worker processes Stage IV's fit will start besides its own (``motion_cfg``: the
    MotionConfig, device resolved): one per core it may use beyond the first
    (:func:`embodmocap.parallel.lent_cores`, ``smplify.workers``), none on a CUDA device. As
    :mod:`embodmocap.motion.smplify` counts them for a sequence of more than one window."""
    from embodmocap.device import resolve_device
    from embodmocap.errors import InputError
    from embodmocap.parallel import cores_to_use

    sm = motion_cfg.smplify
    try:
        if sm.device != "cpu" and resolve_device(sm.device) != "cpu":
            return 0
    except InputError:  # the stage says so itself
        return 0
    return cores_to_use(sm.workers) - 1


class _LogToPipe(logging.Handler):
    """A worker's log records, sent to the scheduler, whose handlers print or file them."""

    def __init__(self, send: Callable[[tuple], None]) -> None:
        super().__init__()
        self.send = send

    def emit(self, record: logging.LogRecord) -> None:
        try:
            d = dict(record.__dict__)
            d["msg"] = record.getMessage() + (f"\n{self.formatter_exc(record)}" if record.exc_info else "")
            d["args"], d["exc_info"], d["exc_text"] = None, None, None
            self.send(("log", {k: v for k, v in d.items() if v is None or isinstance(v, (str, int, float, bool))}))
        except Exception:  # noqa: BLE001 (logging must never break the stage)
            self.handleError(record)

    @staticmethod
    def formatter_exc(record: logging.LogRecord) -> str:
        return "".join(traceback.format_exception(*record.exc_info))


def _received(conn: Connection):
    """The jobs the scheduler sends, until it sends None or goes away (or Ctrl-C while idle)."""
    try:
        for msg in iter(conn.recv, None):
            yield msg
    except (EOFError, KeyboardInterrupt):
        return


def _worker_main(conn: Connection, log_level: int, quiet: bool) -> None:
    """A worker's loop: receive ``(job, cfg, session, force)``, run it, send back what happened:
    ``("step", key, stage, step)`` as steps finish, ``("log", record)``, and at the end
    ``("done", key, status, seconds, message, digests)`` with status ``ok``, ``failed`` (an expected
    failure of the target), ``error`` (a bug: the traceback) or ``interrupted`` (Ctrl-C; the worker
    exits), and the file digests it knows (:func:`~embodmocap.io.stage_manifest.known_digests`), which
    the scheduler hands to the next jobs: a fresh worker then need not hash a capture's frame files
    again to check its upstream (2-4 CPU s on the 60 s session)."""
    from embodmocap import errors
    from embodmocap.io import stage_manifest
    from embodmocap.memory import map_large_blocks, release_freed_memory, trim_heaps
    from embodmocap.parallel import lend_cores
    from embodmocap.progress import set_quiet

    lock = threading.Lock()  # a stage's own threads log too

    def send(msg: tuple) -> None:
        with lock:
            conn.send(msg)

    pkg = logging.getLogger("embodmocap")
    pkg.setLevel(log_level)
    pkg.addHandler(_LogToPipe(send))
    pkg.propagate = False
    set_quiet(quiet)
    map_large_blocks()  # as the sequential run does (embodmocap.memory)
    current = [""]

    def step_done(stage: str, step: str) -> None:
        send(("step", current[0], stage, step))
        # What the step freed goes back now, not at the job's end: Stage I's worker kept its mesh
        # step's ~2 GB through floor and simplify, beside Stage III's refinement (embodmocap.memory).
        trim_heaps()

    stage_manifest.STEP_LISTENERS.append(step_done)
    errors.interrupt_once()  # the first Ctrl-C interrupts the stage; the one forwarded after it must not
    for job, cfg, session, force, digests, cores in _received(conn):
        current[0] = job.key
        stage_manifest.remember_digests(digests)
        t0 = time.perf_counter()
        status, text = "ok", ""
        try:
            with lend_cores(cores):
                _call(job, cfg, Path(session), force)
        except BaseException as err:  # noqa: BLE001 (sorted below, as pipeline.run_session sorts them)
            if errors.interrupted(err):
                status, text = "interrupted", "interrupted"
            elif isinstance(err, (errors.EmbodMocapError, RuntimeError, ValueError, OSError)):
                log.debug("%s failed:\n%s", job.key, traceback.format_exc())
                status, text = "failed", errors.failure_message(err)
            else:
                status, text = "error", traceback.format_exc()
        release_freed_memory()
        try:
            send(("done", job.key, status, time.perf_counter() - t0, text, stage_manifest.known_digests()))
        except (BrokenPipeError, OSError):
            return
        if status == "interrupted":
            return
    # Told to stop (or the scheduler went away) between jobs: every file is written and every log
    # record sent, so the process ends here without the interpreter's teardown of its modules and
    # heap (torch, a fit's GBs: 0.75-2 s of one core on the 2-core box against 0.2 s), which the
    # run's end waits for and which Stage I's worker spent beside the registration.
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    os._exit(0)


@contextlib.contextmanager
def _main_module_not_rerun():
    """Inside: a process started with ``spawn`` does not import this process's ``__main__`` again.

    ``spawn`` re-imports the parent's main module in the child (as ``__mp_main__``) for targets
    defined there; ``embodmocap run``'s is the CLI (the ``embodmocap`` script, or ``python -m
    embodmocap.cli``), whose imports (every command's config, tyro) are 0.1-0.4 s of a worker's
    start-up for nothing: the worker's target lives in this module. ``multiprocessing`` reads the
    main module while ``start()`` prepares the child, in this thread; a placeholder without a
    file or a spec stands in for it meanwhile (the scheduler starts workers from one thread)."""
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if main is not None:
            sys.modules["__main__"] = main


@dataclass
class _Worker:
    proc: mp.process.BaseProcess
    conn: Connection
    job: Job | None = None
    started: float = 0.0
    last: str = ""  # the scene or sequence of the last job it ran


class WorkerPool:
    """``size`` worker processes running :class:`Job` s (see the module docstring)."""

    def __init__(self, size: int, cfg, session: Path, force: bool) -> None:
        self.size, self.cfg, self.session, self.force = size, cfg, session, force
        self._ctx = mp.get_context("spawn")
        self.workers: list[_Worker] = []
        self.stopping: list[mp.process.BaseProcess] = []  # told to stop, not reaped yet

    def idle(self) -> int:
        return self.size - sum(1 for w in self.workers if w.job is not None)

    def start(self, job: Job, digests: dict, cores: int = 1) -> None:
        """Send ``job`` to an idle worker, preferably one whose last job was of the same scene or
        sequence (its imports and caches are that target's), else start a worker. ``cores``: what
        the job may use (:func:`embodmocap.parallel.lent_cores` in the worker)."""
        idle = [w for w in self.workers if w.job is None and w.proc.is_alive()]
        w = next((w for w in idle if w.last == job.name), idle[0] if idle else None)
        if w is None:
            parent, child = self._ctx.Pipe()
            pkg = logging.getLogger("embodmocap")
            from embodmocap.progress import is_quiet

            proc = self._ctx.Process(target=_worker_main, args=(child, pkg.getEffectiveLevel(), is_quiet()),
                                     daemon=True, name="embodmocap-run-worker")
            with _main_module_not_rerun():
                proc.start()
            child.close()
            w = _Worker(proc, parent)
            self.workers.append(w)
        w.job, w.started, w.last = job, time.perf_counter(), job.name
        w.conn.send((job, self.cfg, str(self.session), self.force, digests, cores))

    def messages(self, timeout: float) -> list[tuple]:
        """What the busy workers sent within ``timeout`` s; a worker that died gives its job
        ``("done", key, "failed", seconds, why)`` and is dropped."""
        busy = [w for w in self.workers if w.job is not None]
        if not busy:
            return []
        ready = wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], timeout)
        out: list[tuple] = []
        for w in busy:
            if w.conn not in ready and w.proc.sentinel not in ready:
                continue
            try:
                while w.conn.poll():
                    msg = w.conn.recv()
                    out.append(msg)
                    if msg[0] == "done":
                        w.job = None
                        break
            except (EOFError, OSError):
                pass
            if w.job is not None and not w.proc.is_alive():
                w.proc.join(1.0)
                code = w.proc.exitcode
                why = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                out.append(("done", w.job.key, "failed", time.perf_counter() - w.started,
                            f"its worker process died ({why})", {}))
                w.job = None
            if w.job is None and not w.proc.is_alive():
                self.workers.remove(w)
        return out

    def interrupt(self, on_message: Callable[[tuple], None]) -> None:
        """Ctrl-C: one SIGINT to every busy worker (the terminal's may not have reached them), then
        their last messages until they end, at most :data:`INTERRUPT_GRACE_S`; the rest are killed."""
        for w in self.workers:
            if w.job is not None and w.proc.is_alive():
                try:
                    os.kill(w.proc.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        deadline = time.perf_counter() + INTERRUPT_GRACE_S
        while any(w.job is not None for w in self.workers) and time.perf_counter() < deadline:
            try:
                for msg in self.messages(0.5):
                    on_message(msg)
            except KeyboardInterrupt:  # a second Ctrl-C: stop waiting
                break

    def stop_idle(self, keep: set[str] = frozenset()) -> None:
        """Stop the idle workers (called when no job is ready for them) but those whose last job was
        of a target in ``keep`` (a job of it will be ready when a running job gets on): an idle
        worker's imports and heap are hundreds of MB next to a running stage's peak (Stage I's mesh,
        Stage IV's fit), while a fresh worker costs seconds of start-up (spawn, imports, caches) on
        the run's critical path when the job it waits for is the next step of the chain (Stage
        III's refinement after its registration, waiting for Stage I's mesh)."""
        for w in [w for w in self.workers if w.job is None and w.last not in keep]:
            try:
                w.conn.send(None)
            except (OSError, BrokenPipeError):
                w.proc.kill()
            w.conn.close()
            self.workers.remove(w)
            self.stopping.append(w.proc)
        # Reaped without waiting: a loaded machine may take seconds to end a process.
        self.stopping = [p for p in self.stopping if p.exitcode is None]

    def close(self) -> None:
        """Stop every worker (idle ones exit at once, busy ones are killed)."""
        for w in self.workers:
            if w.job is None:
                try:
                    w.conn.send(None)
                except (OSError, BrokenPipeError):
                    pass
        for w in self.workers:
            w.proc.join(5.0 if w.job is None else 0.0)
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join(1.0)
            w.conn.close()
        for p in self.stopping:
            p.join(5.0)
            if p.is_alive():
                p.kill()
                p.join(1.0)
        self.workers.clear()
        self.stopping.clear()


def run_jobs(cfg, session: Path, jobs: list[Job], workers: int, force: bool, say: Callable[[str], None],
             record: Callable[[str, str, str, float, str], None]) -> None:
    """Run ``jobs`` on ``workers`` processes (see the module docstring).

    Args:
        cfg: the PipelineConfig (Stage IV's device already resolved).
        say: where progress lines go.
        record: called as ``record(target, stage, status, seconds, error)`` for every job that
            ended and every sequence left out because its scene failed.

    Raises:
        KeyboardInterrupt: Ctrl-C (after every worker stopped).
        RuntimeError: a job failed with a programming error (its traceback), after the workers stopped.
    """
    by_key = {j.key: j for j in jobs}
    state = {j.key: "pending" for j in jobs}
    steps: set[str] = set()  # "key#step" of the steps running jobs reported
    digests: dict = {}  # the file digests the workers computed (stage_manifest.known_digests)
    pool = WorkerPool(workers, cfg, session, force)

    def met(need: str) -> bool:
        key = need.split("#")[0]
        return state[key] == "ok" or need in steps

    def drop_after(key: str) -> None:
        """The jobs that need ``key`` (directly or not) will not run; a failed scene's sequences
        are reported failed, as the sequential run reports them."""
        failed = by_key[key]
        left = {j.name for j in jobs if failed.kind == "scene" and j.kind != "scene" and j.scene == failed.name
                and state[j.key] == "pending"}
        changed = True
        while changed:
            changed = False
            for j in jobs:
                if state[j.key] == "pending" and any(state[n.split("#")[0]] in ("failed", "dropped") for n in j.needs):
                    state[j.key], changed = "dropped", True
        for q in sorted(left):
            say(f"sequence {q}: skipped because its scene {failed.name} failed")
            record(f"sequence {q}", "all", "failed", 0.0, f"its scene {failed.name} failed")

    bug = ""

    def handle(msg: tuple) -> None:
        nonlocal bug
        if msg[0] == "log":
            rec = logging.makeLogRecord(msg[1])
            logging.getLogger(rec.name).handle(rec)
        elif msg[0] == "step":
            steps.add(f"{msg[1]}#{msg[3]}")
        elif msg[0] == "done":
            _, key, status, seconds, text, known = msg
            digests.update(known)
            job = by_key[key]
            stage = STAGE_OF[job.kind]
            if status == "ok":
                say(f"{job.target}: {stage} done in {seconds:.0f} s")
            elif status == "interrupted":
                state[key] = "interrupted"
                return
            else:
                if status == "error":
                    bug = bug or f"{job.target}: {stage}: {text}"
                    text = text.strip().splitlines()[-1]
                say(f"{job.target}: {stage} FAILED after {seconds:.0f} s: {text}")
            state[key] = "ok" if status == "ok" else "failed"
            record(job.target, stage, state[key], round(seconds, 2), "" if status == "ok" else text)
            if state[key] == "failed":
                drop_after(key)

    try:
        while not bug:
            for kind in PRIORITY:
                for j in jobs:
                    if pool.idle() > 0 and j.kind == kind and state[j.key] == "pending" and all(map(met, j.needs)):
                        cores = cores_for(j.key, jobs, state, workers)
                        state[j.key] = "running"
                        say(f"{j.target}: {STAGE_OF[j.kind]} ...")
                        pool.start(j, digests, cores)
            if not any(s == "running" for s in state.values()):
                break
            # Kept: a worker of a target whose next job waits only on running ones (see stop_idle).
            pool.stop_idle({j.name for j in jobs if state[j.key] == "pending" and all(
                met(n) or state[n.split("#")[0]] == "running" for n in j.needs)})
            for msg in pool.messages(0.5):
                handle(msg)
            if any(s == "interrupted" for s in state.values()):
                raise KeyboardInterrupt
    except KeyboardInterrupt:
        pool.interrupt(handle)
        raise
    finally:
        pool.close()
    if bug:
        raise RuntimeError(f"a worker of `embodmocap run` failed with a programming error:\n{bug}")

