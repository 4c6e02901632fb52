"""Threads: the native libraries' own thread pools, and a module imported in the background.

Why limit the libraries: Open3D's TSDF (OpenMP) and NumPy/SciPy's BLAS start one thread per core
for every small parallel loop and spin while they wait for each other. On a machine whose cores
are busy with other work (a shared box, a batch of sessions) a waiting thread spins on a core the
other needs: Stage I's TSDF integration took 10-20x the CPU time of one thread at a load average of
20 on 2 cores. The stages use the cores explicitly instead (a reader thread next to the fusion, the
floor check and the simplification next to the mesh's write), with each library on one thread.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import threading

log = logging.getLogger(__name__)


def library_threads(n: int, apis: tuple[str, ...] = ("blas", "openmp")):
    """Context manager: the thread pools of the native libraries already loaded (``apis`` of
    ``threadpoolctl``: ``"blas"``, ``"openmp"``) limited to ``n`` threads inside, restored after.

    OpenMP's limit holds for parallel loops started by the calling thread. Only libraries loaded
    before the call are limited, so import the library first. Without ``threadpoolctl`` (installed
    with Open3D's scikit-learn) nothing changes: only the CPU time differs, never a result.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    stack = contextlib.ExitStack()
    for api in apis:
        stack.enter_context(threadpool_limits(int(n), user_api=api))
    return stack


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity; the machine's count where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


#: Cores the job in progress may use (see :func:`lent_cores`); set by :func:`lend_cores`.
_LENT = 1


def lent_cores() -> int:
    """Cores the stage in progress may use for work it can split into independent pieces whose
    answer does not depend on the split (Stage IV's fit windows): 1, unless ``embodmocap run``'s
    scheduler lent the job its idle workers' cores (:mod:`embodmocap.schedule`: no other job runs
    and every job left waits for this one)."""
    return _LENT


def cores_to_use(requested: int) -> int:
    """Cores a stage's independent pieces may take: ``requested`` (a setting such as
    ``smplify.workers``) or the cores :func:`lent_cores` lends the job, whichever is more, at most
    the :func:`usable_cores`, at least 1. Stage IV's fit windows, its per-frame quality and the
    scheduler's count of the fit's helper processes all use this one rule."""
    return max(1, min(max(int(requested), lent_cores()), usable_cores()))


@contextlib.contextmanager
def lend_cores(n: int):
    """Context manager: :func:`lent_cores` is ``n`` (at least 1) inside, restored after."""
    global _LENT
    old, _LENT = _LENT, max(1, int(n))
    try:
        yield
    finally:
        _LENT = old


def import_in_background(name: str) -> threading.Thread:
    """Start importing module ``name`` in a thread and return it (joined at exit, not a daemon).

    For a heavy import (Open3D: about 7 s of CPU, most of it its ML package's scikit-learn) that a
    later step needs while an earlier one runs native code that releases the GIL (COLMAP): the
    import then costs the other core's time, not the stage's. A later ``import name`` in any thread
    waits for this one to finish (the import lock) and gets the same module. A failed import is
    only logged here: the step that needs the module imports it again and raises there.
    """

    def work() -> None:
        try:
            importlib.import_module(name)
        except Exception as err:  # noqa: BLE001 (the importing step reports it)
            log.debug("background import of %s failed: %s", name, err)

    th = threading.Thread(target=work, name=f"import-{name}")
    th.start()
    return th


def map_in_threads(fn, items, threads: int | None = None) -> list:
    """``[fn(x) for x in items]`` on up to ``threads`` threads (:func:`lent_cores` when None), in
    the items' order: for independent pieces of NumPy / SciPy / torch work, which release the GIL;
    each piece is computed as it would be alone, so the answer does not depend on the threads."""
    items = list(items)
    n = min(lent_cores() if threads is None else max(1, int(threads)), len(items))
    if n <= 1:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(n, thread_name_prefix="map") as pool:
        return list(pool.map(fn, items))
