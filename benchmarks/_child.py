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

import os
import subprocess
import sys
import threading
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


def _tree(pid: int) -> list[int]:
    """``pid`` and every process below it (Linux ``/proc``)."""
    parent: dict[int, int] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = open(f"/proc/{d}/stat").read()
                parent[int(d)] = int(stat[stat.rindex(")") + 2:].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += [c for c, pp in parent.items() if pp == p]
    return out


def _kb(path: str, key: str) -> int:
    try:
        for line in open(path):
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def communicate_sampling(proc: subprocess.Popen, sample, every_s: float) -> tuple:
    """``proc.communicate()`` while a thread calls ``sample()`` every ``every_s`` seconds until the
    child has exited (the child's process tree is only visible while it runs, so the benchmarks
    that measure memory or CPU per process poll it from beside the wait)."""
    done = threading.Event()

    def loop() -> None:
        while not done.is_set():
            sample()
            done.wait(every_s)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    try:
        return proc.communicate()
    finally:
        done.set()
        th.join()


def run_cli_tree(*args: str, src: str | None = None, every_s: float = 0.2) -> dict:
    """:func:`run_cli_usage` for a command that may start worker processes (``embodmocap run``
    with ``--workers``): besides the child's own peak, the peak over time of the sum of the resident
    memory (VmRSS; and of the proportional set size, Pss, which counts a page two processes share
    once) of the child and every process below it, sampled every ``every_s`` seconds. For one
    process the RSS sum's peak is its VmHWM up to what falls between two samples.

    Returns ``wall_s``, ``cpu_s`` (the child and its waited-for workers), ``peak_mb`` (the child's
    own VmHWM), ``tree_rss_mb``, ``tree_pss_mb`` and ``processes`` (the most alive at one sample).
    """
    import resource

    env = None if src is None else dict(os.environ, PYTHONPATH=src)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", _CODE, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    peak = {"rss": 0, "pss": 0, "n": 0}

    def sample() -> None:
        pids = _tree(proc.pid)
        rss = sum(_kb(f"/proc/{p}/status", "VmRSS") for p in pids)
        pss = sum(_kb(f"/proc/{p}/smaps_rollup", "Pss") for p in pids)
        peak["rss"], peak["pss"] = max(peak["rss"], rss), max(peak["pss"], pss)
        peak["n"] = max(peak["n"], len(pids))

    out, err = communicate_sampling(proc, sample, every_s)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"embodmocap {' '.join(args)} failed ({proc.returncode}):\n{out[-2000:]}{err[-4000:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu, "peak_mb": int(out.strip().splitlines()[-1]) // 1024,
            "tree_rss_mb": peak["rss"] // 1024, "tree_pss_mb": peak["pss"] // 1024, "processes": peak["n"]}


def sequence_figures(session, names) -> dict[str, float]:
    """The numeric figures of the first sequence in ``session/evaluation.json`` whose last key part
    is in ``names`` (nested keys joined with dots)."""
    import json
    from pathlib import Path

    ev = json.loads((Path(session) / "evaluation.json").read_text())
    flat: dict[str, float] = {}

    def walk(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                flat[f"{prefix}{k}"] = v
    walk(next(iter(ev["sequences"].values())))
    return {k: v for k, v in flat.items() if k.split(".")[-1] in names}
