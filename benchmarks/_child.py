"""Run an `embodmocap` command in a child process and measure it (wall time, peak RSS).

Each benchmark run gets its own process so that its peak resident memory is its own; the child
prints that figure on its last line. The figure is the child's ``VmHWM`` (``/proc/self/status``),
not ``ru_maxrss``: on Linux a child's ``ru_maxrss`` starts from the *parent's* high-water mark (the
kernel carries the pre-exec memory's peak over exec), so a parent that had synthesised a session
(about 880 MB for a 20 s one) made every child report at least that much. This is what gave Stage II
900 MB in one run and 254 MB in another (BENCHMARKS.md, issue 14 and session 6). ``ru_maxrss`` is
the fallback where ``/proc`` is missing.
"""

from __future__ import annotations

import subprocess
import sys
import time

_CODE = ("import resource, sys; from embodmocap.cli import main; rc = main(sys.argv[1:]); sys.stdout.flush()\n"
         "try:\n"
         "    hwm = int(open('/proc/self/status').read().split('VmHWM:')[1].split()[0])\n"
         "except (OSError, IndexError, ValueError):\n"
         "    hwm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
         "print(hwm); sys.exit(rc)")


def run_cli(*args: str, src: str | None = None) -> tuple[float, int]:
    """Run ``embodmocap ARGS`` in a child; returns (wall seconds, peak RSS in MB: the child's own
    high-water mark). ``src``: put this ``src`` folder (another checkout, e.g. the code before a
    change) first on the child's path."""
    wall, rss, _ = run_cli_usage(*args, src=src)
    return wall, rss


def run_cli_usage(*args: str, src: str | None = None) -> tuple[float, int, float]:
    """:func:`run_cli` plus the child's CPU seconds (user + system, all its threads), from the
    kernel's accounting of the waited-for child (``RUSAGE_CHILDREN`` before and after)."""
    import os
    import resource

    env = None if src is None else dict(os.environ, PYTHONPATH=src)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CODE, *args], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"embodmocap {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-2000:]}{proc.stderr[-4000:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, int(proc.stdout.strip().splitlines()[-1]) // 1024, cpu
