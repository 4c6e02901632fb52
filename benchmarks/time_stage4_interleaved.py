"""Stage IV wall time, old code vs this tree, interleaved on prepared sessions.

On a shared machine the load changes from minute to minute, so ``bench_motion_stage4.py``'s order
(old then new for each setting) can put all of a load spike on one side. This script runs, per
session, old / new then new / old (each Stage IV forced in its own process, the given prior
setting), and reports the sum and the median of the per-pair ratios.

    python benchmarks/time_stage4_interleaved.py --old-src /tmp/old/src --sessions /work/bench/11/sessions \
        --work /tmp/bench_s4 --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench_motion_stage4 import stage4, work_copy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-src", type=Path, required=True)
    ap.add_argument("--sessions", type=Path, required=True, help="folder of prepared <perception>_<seed> sessions")
    ap.add_argument("--perception", default="hard")
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--prior", default="realistic", choices=("none", "realistic"))
    ap.add_argument("--work", type=Path, required=True, help="work folder (copies of the sessions)")
    args = ap.parse_args()
    new = Path(__file__).resolve().parents[1] / "src"
    sys.path.insert(0, str(new))
    t: dict[str, list[float]] = {"old": [], "new": []}
    for seed in args.seeds:
        dst = work_copy(args.sessions / f"{args.perception}_{seed}", args.work / f"{args.perception}_{seed}")
        for order in ((("old", args.old_src), ("new", new)), (("new", new), ("old", args.old_src))):
            for code, src in order:
                wall, errs = stage4(dst, args.prior, src)
                t[code].append(wall)
                print(f"seed {seed} {code}: {wall:.2f} s, W-MPJPE {errs['w_mpjpe_mm']}", flush=True)
    ratio = np.array(t["new"]) / np.array(t["old"])
    print(f"new / old: {sum(t['new']) / sum(t['old']):.3f} (sum {sum(t['new']):.1f} / {sum(t['old']):.1f} s); "
          f"median of the per-pair ratios {np.median(ratio):.3f}")


if __name__ == "__main__":
    main()
