"""Independent pieces of Stage IV's fit in forked worker processes (issue 30).

The windows of a long sequence are independent once the shape is fitted (each window's loss and
Adam state are its own), and Stage IV runs alone at the end of ``embodmocap run``: a second
process on the second core halves the wall time of the windows' fit. Workers are forked (they
inherit the model, the data and the settings; nothing is pickled on the way in) and send back
numpy arrays. Where the platform cannot fork (Windows, or a CUDA device that must not be forked)
the pieces run one after another in this process. The answer does not depend on the number of
processes: a window's arithmetic is the same whether it is fitted alone or in a batch with others
(``tests/test_fit_workers.py``).
"""

from __future__ import annotations

import multiprocessing as mp
import sys
import traceback
from typing import Callable, Sequence, TypeVar

R = TypeVar("R")


def can_fork() -> bool:
    """Whether worker processes can be forked here."""
    return "fork" in mp.get_all_start_methods()


def run_pieces(pieces: Sequence[Callable[[], R]], workers: int) -> list[R]:
    """``[piece() for piece in pieces]``, the first in this process and each other one in a forked
    child when ``workers`` > 1 (at most ``workers`` processes at a time, this one included).

    The pieces' results must be picklable (send numpy arrays, not tensors). A child that fails
    raises :class:`RuntimeError` here with its traceback.
    """
    if workers <= 1 or len(pieces) <= 1 or not can_fork():
        return [p() for p in pieces]
    ctx = mp.get_context("fork")
    out: list = [None] * len(pieces)
    todo = list(range(1, len(pieces)))
    running: list[tuple[int, object, object]] = []
    sys.stdout.flush()
    sys.stderr.flush()  # a child must not write the parent's buffered output again

    def start(i: int) -> None:
        recv, send = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_child, args=(pieces[i], send), daemon=True)
        proc.start()
        send.close()
        running.append((i, proc, recv))

    while todo and len(running) < workers - 1:
        start(todo.pop(0))
    out[0] = pieces[0]()
    while running:
        i, proc, recv = running.pop(0)
        try:
            ok, value = recv.recv()
        except EOFError:
            ok, value = False, "the worker process ended without a result (killed, or out of memory?)"
        proc.join()
        recv.close()
        if not ok:
            raise RuntimeError(f"Stage IV fit worker {i} failed:\n{value}")
        out[i] = value
        if todo:
            start(todo.pop(0))
    return out


def _child(piece: Callable[[], object], send) -> None:
    try:
        result = (True, piece())
    except BaseException:  # noqa: BLE001 (the parent re-raises it with the traceback)
        result = (False, traceback.format_exc())
    send.send(result)
    send.close()
