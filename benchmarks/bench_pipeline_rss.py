"""Where a stage's peak resident memory comes from: RSS sampled per step, split anon / file-backed.

Runs one stage (default Stage II, ``embodmocap sequence SESSION --force``) in this process while a
thread samples ``/proc/self/status`` every 10 ms (VmRSS = RssAnon + RssFile + RssShmem). Stage
steps are told apart by the stage manifest's "<step> done" log lines: each step's peak is the highest
sample between the previous step's end and its own. Also prints what was loaded before the stage
started (torch, cv2, av) and the peak before any stage work (imports alone).

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_pipeline_rss.py SESSION [--stage sequence]

Why: ``bench_pipeline.py`` reports ru_maxrss per stage process, which counts file pages a process
maps (memory-mapped reads and writes of the frame stacks) as well as its own allocations.
"""

from __future__ import annotations

import argparse
import logging
import resource
import sys
import threading
import time

_KEYS = ("VmRSS", "RssAnon", "RssFile", "RssShmem", "VmHWM")


def _status() -> dict[str, int]:
    """Current memory figures of this process, MB."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in _KEYS:
                out[k] = int(v.split()[0]) // 1024
    return out


class _Sampler(threading.Thread):
    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.samples: list[tuple[float, dict[str, int]]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            self.samples.append((time.perf_counter(), _status()))
            time.sleep(0.01)


class _Steps(logging.Handler):
    """Times of the stage manifest's "<step> done in" lines."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.ends: list[tuple[float, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        msg = record.getMessage()
        if " done in " in msg and record.name == "embodmocap.io.stage_manifest":
            self.ends.append((time.perf_counter(), msg.split(": ")[1].split(" done in ")[0]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session")
    ap.add_argument("--stage", default="sequence", choices=("scene", "sequence", "calibrate", "motion"))
    ap.add_argument("--no-force", action="store_true", help="resume instead of redoing every step")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    steps = _Steps()
    logging.getLogger().addHandler(steps)
    before = _status()
    from embodmocap.cli import main as cli_main

    after_import = _status()
    sampler = _Sampler()
    t0 = time.perf_counter()
    sampler.start()
    rc = cli_main([args.stage, args.session, *([] if args.no_force else ["--force"])])
    sampler.stop.set()
    sampler.join()
    print(f"\nexit {rc}; wall {time.perf_counter() - t0:.1f} s")
    print(f"RSS at start {before['VmRSS']} MB, after importing the CLI {after_import['VmRSS']} MB; "
          f"loaded: " + ", ".join(m for m in ("torch", "cv2", "av", "scipy", "pycolmap", "open3d") if m in sys.modules))
    print("| step | peak VmRSS MB | RssAnon MB | RssFile MB | RssShmem MB |")
    print("|---|---|---|---|---|")
    start = t0
    for end, name in [*steps.ends, (time.perf_counter(), "(after the last step)")]:
        window = [s for t, s in sampler.samples if start <= t <= end]
        if window:
            top = max(window, key=lambda s: s["VmRSS"])
            print(f"| {name} | {top['VmRSS']} | {top['RssAnon']} | {top['RssFile']} | {top.get('RssShmem', 0)} |")
        start = end
    print(f"\nru_maxrss {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024} MB "
          f"(VmHWM {_status()['VmHWM']} MB)")


if __name__ == "__main__":
    main()
