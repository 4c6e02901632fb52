"""Independent pieces of Stage IV's fit in worker processes on the second core (issue 30).

The windows of a long sequence are independent once the shape is fitted (each window's loss and
Adam state are its own), and Stage IV runs alone at the end of ``embodmocap run``: a second
process on the second core cuts the wall time of the windows' fit.

A worker is a fresh Python interpreter (``subprocess``: fork and exec at once, nothing of this
process's state survives), never a fork of this one. A fork copies every lock of every thread the
process holds in the state it had: session 10's forked workers deadlocked in the test suite on a
PyAV decoder's slice-thread lock left by an earlier video read, and torch's OpenMP pool is not
fork-safe either. It works from ``embodmocap run``'s daemonic stage processes (where
``multiprocessing`` may not start children) and on every platform.

A worker is started early (:func:`start_workers`: it imports torch and the fit while this process
still fits the shape, so the import costs the idle core's time; or before the stage, by
:func:`prestarted`: ``embodmocap run``'s scheduler starts it as Stage IV begins, so that the import
overlaps the triangulation too) and then waits for one job: a
module-level function and its arguments, pickled to a file in a private temporary folder; the result
(or the worker's traceback) comes back the same way. A worker logs nothing; the parent kills and
reaps every worker before it returns or raises, and a worker whose parent died before sending a job
leaves (end of file on its stdin). The answer does not depend on the number of processes: a
window's arithmetic is the same whether it is fitted alone or in a batch with others
(``tests/test_fit_workers.py``).
"""

from __future__ import annotations

import contextlib
import importlib
import os
import pickle
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path
from typing import Any, Callable, Sequence

#: Started in a fresh interpreter: import the modules named on the command line (the fit's, while
#: the parent is busy), then serve one job whose file paths come on stdin.
_BOOT = "from embodmocap.motion.fit_workers import _serve; _serve()"


class Workers:
    """Worker processes started by :func:`start_workers`, each waiting for one job.

    Use as a context manager (or call :meth:`close`): workers that got no job, or whose job is
    still running when the parent fails, are killed and reaped."""

    def __init__(self, procs: list[subprocess.Popen], folder: tempfile.TemporaryDirectory,
                 errs: list[str] | None = None) -> None:
        self.procs = procs
        self.folder = folder
        #: Each worker's stderr file (what a worker that failed to start said).
        self.errs = errs if errs is not None else [os.path.join(folder.name, f"worker{k}.err") for k in range(len(procs))]

    def _spawn(self, preload: Sequence[str], threads: int) -> None:
        """Start one more worker (see :func:`start_workers`)."""
        import embodmocap

        env = dict(os.environ)
        root = str(Path(embodmocap.__file__).resolve().parents[1])  # the folder that holds the package
        env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        if threads > 0:
            for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
                env[k] = str(threads)
        path = os.path.join(self.folder.name, f"worker{len(self.errs)}.err")
        # stderr to a file, not a pipe: a worker that warns a lot must not block on a full pipe.
        with open(path, "wb") as err:
            self.procs.append(subprocess.Popen([sys.executable, "-c", _BOOT, *preload], stdin=subprocess.PIPE,
                                               stdout=subprocess.DEVNULL, stderr=err, env=env, close_fds=True))
        self.errs.append(path)

    def _drop(self, keep) -> None:
        """Kill and reap the workers for which ``keep(index, process)`` is false."""
        kept = [(p, e) for k, (p, e) in enumerate(zip(self.procs, self.errs)) if keep(k, p)]
        for p in self.procs:
            if all(p is not q for q, _ in kept):
                _end(p)
        self.procs, self.errs = [p for p, _ in kept], [e for _, e in kept]

    def __len__(self) -> int:
        return len(self.procs)

    def __enter__(self) -> "Workers":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for p in self.procs:
            _end(p)
        self.procs, self.errs = [], []
        self.folder.cleanup()


def _end(p: subprocess.Popen) -> None:
    """Kill (if still running) and reap one worker."""
    if p.poll() is None:
        p.kill()
    p.wait()
    if p.stdin is not None:
        p.stdin.close()


#: Workers started ahead of the stage (:func:`prestarted`): (preload, threads) and the pool, which
#: the next :func:`start_workers` asking for the same modules and threads takes.
_AHEAD: list[tuple[tuple[tuple[str, ...], int], Workers]] = []


def start_workers(n: int, preload: Sequence[str] = (), threads: int = 1) -> Workers:
    """Start ``n`` worker processes (0 = none) that import the modules ``preload`` now and wait.

    ``threads`` > 0: the workers' OpenMP / BLAS thread count (``OMP_NUM_THREADS``, ...) from the
    start, so that they never spin up a pool of one thread per core. Workers :func:`prestarted`
    with the same ``preload`` and ``threads`` are taken first (those beyond ``n`` are stopped)."""
    n = max(int(n), 0)
    key = (tuple(preload), int(threads))
    pool = next((w for k, w in _AHEAD if k == key), None)
    if pool is not None:
        _AHEAD[:] = [(k, w) for k, w in _AHEAD if w is not pool]
        pool._drop(lambda k, p: k < n and p.poll() is None)  # one that died starting is replaced below
    else:
        pool = Workers([], tempfile.TemporaryDirectory(prefix="embodmocap-fit-"))
    try:
        while len(pool.procs) < n:
            pool._spawn(preload, threads)
    except BaseException:
        pool.close()
        raise
    return pool


@contextlib.contextmanager
def prestarted(n: int, preload: Sequence[str] = (), threads: int = 1):
    """Context manager: ``n`` workers started now, as :func:`start_workers` would start them, for
    the first :func:`start_workers` inside that asks for the same ``preload`` and ``threads``
    (their imports then overlap what this process does before it); those not taken by then are
    stopped at the end. ``embodmocap run``'s scheduler starts Stage IV's fit worker so as the
    stage begins (:mod:`embodmocap.schedule`)."""
    key = (tuple(preload), int(threads))
    pool = Workers([], tempfile.TemporaryDirectory(prefix="embodmocap-fit-"))
    try:
        for _ in range(max(int(n), 0)):
            pool._spawn(preload, threads)
        _AHEAD.append((key, pool))
        yield
    finally:
        if any(w is pool for _, w in _AHEAD):
            _AHEAD[:] = [(k, w) for k, w in _AHEAD if w is not pool]
            pool.close()


def run_pieces(fn: Callable[..., Any], args: Sequence[tuple], workers: int | Workers) -> list:
    """``[fn(*a) for a in args]``: the first in this process, the others in worker processes.

    ``fn`` must be a module-level function (pickled by name) and ``args`` and the results
    picklable. ``workers``: a number of processes in all, this one included (1 = all here; more
    workers are started now and closed after), or :class:`Workers` started earlier (this function
    closes them). At most one piece per worker: pieces beyond ``len(workers) + 1`` run here after
    the first. A worker that fails raises :class:`RuntimeError` here with its traceback.
    """
    pool = workers if isinstance(workers, Workers) else None
    if pool is None:
        n = min(int(workers), len(args)) - 1
        if n <= 0:
            return [fn(*a) for a in args]
        pool = start_workers(n)
    with pool:
        jobs = list(range(1, len(args)))[: len(pool)]
        sent = []
        for k, i in enumerate(jobs):
            p = pool.procs[k]
            src, dst = (os.path.join(pool.folder.name, f"{i}.{x}") for x in ("in", "out"))
            with open(src, "wb") as f:
                pickle.dump((fn, args[i]), f, protocol=pickle.HIGHEST_PROTOCOL)
            try:
                p.stdin.write(f"{src}\n{dst}\n".encode())
                p.stdin.close()
            except OSError:  # it died while importing: reported when its result is missing
                pass
            sent.append((i, p, dst))
        here = [i for i in range(len(args)) if i not in jobs]
        out: list = [None] * len(args)
        for i in here:
            out[i] = fn(*args[i])
        for k, (i, p, dst) in enumerate(sent):
            status = p.wait()
            if not os.path.exists(dst):
                with open(pool.errs[k], "rb") as f:
                    err = f.read().decode(errors="replace")
                raise RuntimeError(f"Stage IV fit worker {i} ended without a result (exit status {status}: "
                                   f"killed, or out of memory?){': ' + err[-2000:] if err else ''}")
            with open(dst, "rb") as f:
                ok, value = pickle.load(f)
            if not ok:
                raise RuntimeError(f"Stage IV fit worker {i} failed:\n{value}")
            out[i] = value
    return out


def _serve() -> None:
    """A worker's life: preload, wait for a job's paths on stdin, run it, write the result."""
    import logging
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the parent, which kills the workers
    logging.disable(logging.CRITICAL)
    from embodmocap.progress import set_quiet

    set_quiet(True)
    for name in sys.argv[1:]:
        importlib.import_module(name)
    lines = sys.stdin.read().split("\n")
    if len(lines) < 2 or not lines[0]:
        return  # the parent closed without a job
    src, dst = lines[0], lines[1]
    try:
        with open(src, "rb") as f:
            fn, args = pickle.load(f)
        result = (True, fn(*args))
    except BaseException:  # noqa: BLE001 (the parent raises it with the traceback)
        result = (False, traceback.format_exc())
    tmp = dst + ".part"
    with open(tmp, "wb") as f:
        pickle.dump(result, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, dst)  # whole or absent: a killed worker leaves no half result
