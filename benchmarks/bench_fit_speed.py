"""Stage IV's fit, old code vs this tree, interleaved on one synthetic problem: wall and CPU time.

The problem is ``gpu_check.py``'s (the studio's scripted motion, two views with 2 px keypoint noise,
3D keypoints with 2 cm noise, a perturbed start; needs only numpy, scipy and torch), fitted with the
product's settings (windows of 300 frames). Each fit runs in its own child process (old / new, then
new / old, ...); the child reports its own wall and CPU seconds (user + system, all threads) for the
fit alone, the fitted COCO-17 keypoints' error against the truth, and the parent the largest distance
between the two codes' fits. CPU seconds are the figure to read on a shared machine (wall time there
depends on the other processes).

    python benchmarks/bench_fit_speed.py --old-src /tmp/main-src/src --seconds 20 --pairs 1
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

_CHILD = """
import json, sys, time, resource
import numpy as np
sys.path.insert(0, {here!r})
from gpu_check import _problem, _fit
problem = _problem({seconds})
c0 = resource.getrusage(resource.RUSAGE_SELF)
wall, coco, res = _fit(problem, "cpu", "float64")
c1 = resource.getrusage(resource.RUSAGE_SELF)
np.save({out!r}, coco)
err = np.linalg.norm(coco - problem[5], axis=-1)
print(json.dumps({{"wall": wall, "cpu": (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime),
                  "mpjpe_mm": float(err.mean()) * 1000, "windows": len(res.windows), "frames": len(coco)}}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-src", type=Path, required=True)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--pairs", type=int, default=1, help="old/new pairs (the order alternates)")
    args = ap.parse_args()
    new_src = str(HERE.parent / "src")
    codes = {"old": str(args.old_src.resolve()), "new": new_src}
    rows: dict[str, list[dict]] = {"old": [], "new": []}
    fits = {}
    print(f"load average at start: {os.getloadavg()}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for p in range(args.pairs):
            for code in (("old", "new") if p % 2 == 0 else ("new", "old")):
                out = str(Path(tmp) / f"{code}_{p}.npy")
                proc = subprocess.run([sys.executable, "-c", _CHILD.format(here=str(HERE), seconds=args.seconds, out=out)],
                                      capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=codes[code]), check=True)
                r = json.loads(proc.stdout.strip().splitlines()[-1])
                rows[code].append(r)
                fits[code] = np.load(out)
                print(f"pair {p} {code}: " + json.dumps(r), flush=True)
    d = np.linalg.norm(fits["new"] - fits["old"], axis=-1)
    w = {c: sum(r["wall"] for r in rows[c]) for c in rows}
    cpu = {c: sum(r["cpu"] for r in rows[c]) for c in rows}
    print(f"\n{rows['new'][0]['frames']} frames, {rows['new'][0]['windows']} windows; load average at the end: {os.getloadavg()}")
    print("| code | fit wall s | fit CPU s | MPJPE vs truth mm |")
    print("|---|---|---|---|")
    for c in ("old", "new"):
        print(f"| {c} | {w[c]:.1f} | {cpu[c]:.1f} | {np.mean([r['mpjpe_mm'] for r in rows[c]]):.2f} |")
    print(f"| new / old | {w['new'] / w['old']:.3f} | {cpu['new'] / cpu['old']:.3f} | |")
    print(f"old vs new fit: max {d.max() * 1000:.3f} mm, mean {d.mean() * 1000:.3f} mm (keypoints)")


if __name__ == "__main__":
    main()
