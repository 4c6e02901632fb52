"""Independent pieces of Stage IV's fit in forked worker processes (issue 30).

The windows of a long sequence are independent once the shape is fitted (each window's loss and
Adam state are its own), and Stage IV runs alone at the end of ``embodmocap run``: a second
process on the second core halves the wall time of the windows' fit. Workers are forked (``os.fork``:
they inherit the model, the data and the settings; nothing is pickled on the way in; it works from
``embodmocap run``'s own daemonic worker processes, where ``multiprocessing`` may not start
children) and send back a pickle of numpy arrays through a pipe. A worker logs nothing (its parent's
log handlers may write to a pipe of their own) and dies on Ctrl-C; the parent reaps every worker
before it returns or raises. Where the platform cannot fork (Windows), or on a CUDA device (the
caller's choice), the pieces run one after another in this process. The answer does
not depend on the number of processes: a window's arithmetic is the same whether it is fitted
alone or in a batch with others (``tests/test_fit_workers.py``).
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import sys
import traceback
from typing import Callable, Sequence, TypeVar

R = TypeVar("R")


def can_fork() -> bool:
    """Whether worker processes can be forked here."""
    return hasattr(os, "fork")


def run_pieces(pieces: Sequence[Callable[[], R]], workers: int) -> list[R]:
    """``[piece() for piece in pieces]``, the first in this process and each other one in a forked
    child when ``workers`` > 1 (at most ``workers`` processes at a time, this one included).

    The pieces' results must be picklable (send numpy arrays, not tensors). A child that fails
    raises :class:`RuntimeError` here with its traceback.
    """
    if workers <= 1 or len(pieces) <= 1 or not can_fork():
        return [p() for p in pieces]
    out: list = [None] * len(pieces)
    todo = list(range(1, len(pieces)))
    running: list[tuple[int, int, int]] = []  # (piece, pid, read end of its pipe)

    def start(i: int) -> None:
        sys.stdout.flush()
        sys.stderr.flush()  # a child must not write the parent's buffered output again
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the worker: compute, send, and leave without running the parent's exit code
            code = 1
            try:
                os.close(r)
                signal.signal(signal.SIGINT, signal.SIG_DFL)
                logging.disable(logging.CRITICAL)
                from embodmocap.progress import set_quiet

                set_quiet(True)
                try:
                    result = (True, pieces[i]())
                except BaseException:  # noqa: BLE001 (the parent raises it with the traceback)
                    result = (False, traceback.format_exc())
                with os.fdopen(w, "wb") as f:
                    pickle.dump(result, f, protocol=pickle.HIGHEST_PROTOCOL)
                code = 0
            finally:
                os._exit(code)
        os.close(w)
        running.append((i, pid, r))

    try:
        while todo and len(running) < workers - 1:
            start(todo.pop(0))
        out[0] = pieces[0]()
        while running:
            i, pid, r = running[0]
            with os.fdopen(r, "rb") as f:
                data = f.read()
            _, status = os.waitpid(pid, 0)
            running.pop(0)
            if not data:
                raise RuntimeError(f"Stage IV fit worker {i} ended without a result (exit status {status}: "
                                   "killed, or out of memory?)")
            ok, value = pickle.loads(data)
            if not ok:
                raise RuntimeError(f"Stage IV fit worker {i} failed:\n{value}")
            out[i] = value
            if todo:
                start(todo.pop(0))
    finally:
        for _, pid, r in running:  # this process failed or was interrupted: stop and reap the workers
            try:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
            except OSError:
                pass
            try:
                os.close(r)
            except OSError:
                pass
    return out
