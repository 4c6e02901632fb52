"""Run an `embodmocap` command in a child process and measure it (wall time, peak RSS).

Each benchmark run gets its own process so that its peak resident memory (ru_maxrss, KiB on
Linux) is its own; the child prints that figure on its last line.
"""

from __future__ import annotations

import subprocess
import sys
import time

_CODE = ("import resource, sys; from embodmocap.cli import main; rc = main(sys.argv[1:]); "
         "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss); sys.exit(rc)")


def run_cli(*args: str, src: str | None = None) -> tuple[float, int]:
    """Run ``embodmocap ARGS`` in a child; returns (wall seconds, peak RSS in MB). ``src``: put
    this ``src`` folder (another checkout, e.g. the code before a change) first on the child's path."""
    import os

    env = None if src is None else dict(os.environ, PYTHONPATH=src)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CODE, *args], check=True, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    return wall, int(proc.stdout.strip().splitlines()[-1]) // 1024
