"""Stage IV wall and CPU time, old code vs this tree, interleaved on prepared sessions.

On a shared machine the load changes from minute to minute, so ``bench_motion_stage4.py``'s order
(old then new for each setting) can put all of a load spike on one side. This script runs, per
session, old / new then new / old (each Stage IV forced in its own process, the given prior
setting), and reports the sum and the median of the per-pair ratios, of wall time and of CPU
seconds (user + system of the child, all threads: the figure that holds on a loaded machine), with
each run's evaluation against the truth (W-/WA-/PA-MPJPE, the dual row of the capture-methods
table) and the fit step's own seconds from the stage manifest.

    python benchmarks/time_stage4_interleaved.py --old-src /tmp/old/src --sessions /work/bench/11/sessions \\
        --work /tmp/bench_s4 --seeds 0 1 2
    python benchmarks/time_stage4_interleaved.py --old-src /work/base-src/src --session-dirs S1 S2 --work /tmp/s4 \\
        --pairs 1 --prior none
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench_motion_stage4 import work_copy

_RUN = """
import json, resource, sys, time
from pathlib import Path
from embodmocap.motion import stage as stage4
c0 = resource.getrusage(resource.RUSAGE_SELF)
t0 = time.perf_counter()
stage4.run(stage4.MotionConfig(use_body_prior=sys.argv[2] == '1'), Path(sys.argv[1]), force=True)
c1 = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime}))
"""


def stage4(session: Path, prior: str, src: Path) -> tuple[dict, dict]:
    """(times: wall, cpu, fit step seconds; the evaluation's errors) of one forced Stage IV."""
    from embodmocap.evaluate.session import sequence_errors
    from embodmocap.io.layout import SessionLayout

    env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    res = subprocess.run([sys.executable, "-c", _RUN, str(session), "0" if prior == "none" else "1"], env=env,
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"Stage IV failed on {session} ({src}):\n{res.stderr[-3000:]}")
    t = json.loads(res.stdout.strip().splitlines()[-1])
    lay = SessionLayout(session)
    steps = json.loads(lay.sequence("seq0").motion_manifest.read_text())["steps"]
    t["fit_step"] = steps["fit"]["seconds"]
    t["load"] = os.getloadavg()[0]
    return t, sequence_errors(lay, "scene0", "seq0")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-src", type=Path, required=True)
    ap.add_argument("--sessions", type=Path, help="folder of prepared <perception>_<seed> sessions (with --seeds)")
    ap.add_argument("--perception", default="hard")
    ap.add_argument("--seeds", type=int, nargs="+", default=[])
    ap.add_argument("--session-dirs", type=Path, nargs="+", default=[], help="prepared sessions, given by path")
    ap.add_argument("--pairs", type=int, default=2, help="old/new orders per session (1: old, new; 2: and new, old)")
    ap.add_argument("--prior", default="realistic", choices=("none", "realistic"))
    ap.add_argument("--work", type=Path, required=True, help="work folder (copies of the sessions)")
    args = ap.parse_args()
    new = Path(__file__).resolve().parents[1] / "src"
    sys.path.insert(0, str(new))
    srcs = [args.sessions / f"{args.perception}_{seed}" for seed in args.seeds] + list(args.session_dirs)
    print(f"load average at start: {os.getloadavg()}", flush=True)
    t: dict[str, list[dict]] = {"old": [], "new": []}
    errs: dict[str, list[dict]] = {"old": [], "new": []}
    orders = ((("old", args.old_src), ("new", new)), (("new", new), ("old", args.old_src)))[: args.pairs]
    for src in srcs:
        dst = work_copy(src, args.work / src.name)
        for order in orders:
            for code, s in order:
                times, e = stage4(dst, args.prior, s)
                t[code].append(times)
                errs[code].append(e)
                print(f"{src.name} {code}: {json.dumps(times)} W-MPJPE {e['w_mpjpe_mm']:.2f} WA {e['wa_mpjpe_mm']:.2f} "
                      f"PA {e['pa_mpjpe_mm']:.2f} mm", flush=True)
    print(f"load average at the end: {os.getloadavg()}\n")
    print("| code | Stage IV wall s (sum) | CPU s (sum) | fit step s (sum) | W-MPJPE mm (mean) | WA-MPJPE | PA-MPJPE |")
    print("|---|---|---|---|---|---|---|")
    for c in ("old", "new"):
        print(f"| {c} | {sum(x['wall'] for x in t[c]):.1f} | {sum(x['cpu'] for x in t[c]):.1f} | "
              f"{sum(x['fit_step'] for x in t[c]):.1f} | " + " | ".join(
                  f"{np.mean([e[k] for e in errs[c]]):.2f}" for k in ("w_mpjpe_mm", "wa_mpjpe_mm", "pa_mpjpe_mm")) + " |")
    for k in ("wall", "cpu", "fit_step"):
        ratio = np.array([x[k] for x in t["new"]]) / np.array([x[k] for x in t["old"]])
        print(f"new / old {k}: {sum(x[k] for x in t['new']) / sum(x[k] for x in t['old']):.3f} (sum); "
              f"median of the per-pair ratios {np.median(ratio):.3f}")


if __name__ == "__main__":
    main()
