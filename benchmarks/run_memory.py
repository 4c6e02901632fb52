"""Resident memory of one ``embodmocap run`` process, stage by stage (Linux).

Runs :func:`embodmocap.pipeline.run_session` with ``force`` on SESSION (work on a ``cp -al`` copy:
the outputs are rewritten) and prints, at every stage boundary, the resident memory then (VmRSS)
and its peak since the previous boundary (VmHWM, reset through ``/proc/self/clear_refs``). The
largest peak is the whole run's; the RSS at a stage's start is what the earlier stages left.

    PYTHONPATH=src python benchmarks/run_memory.py /tmp/copy_of_a_session
"""

from __future__ import annotations

import sys
import time

from embodmocap.pipeline import PipelineConfig, run_session


def _mb(key: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) // 1024
    raise RuntimeError(f"no {key} in /proc/self/status (Linux only)")


def main() -> None:
    t0 = time.perf_counter()
    peaks = []

    def say(msg: str) -> None:
        hwm = _mb("VmHWM")
        peaks.append(hwm)
        print(f"{time.perf_counter() - t0:7.1f} s  RSS {_mb('VmRSS'):5d} MB  peak since last {hwm:5d} MB  | {msg}", flush=True)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # resets VmHWM to the current RSS

    res = run_session(PipelineConfig(), sys.argv[1], force=True, on_progress=say)
    say(f"end, ok={res.ok}")
    print(f"whole-run peak RSS: {max(peaks)} MB")


if __name__ == "__main__":
    main()
