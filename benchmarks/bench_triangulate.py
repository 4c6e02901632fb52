"""Benchmark: batched triangulation against the per-point reference loop (issue 6).

Synthetic input: 1800 frames (a minute at 30 fps) x 17 COCO joints, seen by 2 hand-held cameras
90 degrees apart and by 4 on a ring, 4 m from the performer, 2 px pixel noise, confidences
uniform in [0.5, 1].
Both functions run on the same input in the same process. The "max diff" column compares them on
the unweighted case (all confidences 1, rejection and gap filling off), where they solve the same
problem; the time columns use the weighted input with the default configuration (rejection on)
for ``triangulate`` and the unweighted loop, as the paper's release does.

    .venv/bin/python benchmarks/bench_triangulate.py [--frames 1800] [--joints 17] [--views 2 4]
        [--repeat 3] [--json bench_out/triangulate.json]

Prints a Markdown table (times are the best of ``--repeat`` runs), then the JSON summary.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from embodmocap.geometry.transforms import make_T
from embodmocap.geometry.triangulation import (
    TriangulationConfig,
    projection_matrices,
    triangulate,
    triangulate_loop,
)

K = np.array([[900.0, 0.0, 360.0], [0.0, 900.0, 480.0], [0.0, 0.0, 1.0]])


def synthetic(frames: int, joints: int, views: int, seed: int = 0):
    """Moving cameras P (T, V, 3, 4), true points (T, J, 3), noisy pixels (T, V, J, 2), conf."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None]
    # 90 degrees apart (the paper asks for 60-120 degrees between the two phones); 4 views: a ring
    ang = np.arange(views)[None] * np.pi / 2 + 0.002 * t
    centres = np.stack([4 * np.cos(ang), 4 * np.sin(ang), 1.6 + 0.1 * np.sin(0.05 * t + ang)], -1)
    z = np.array([0.0, 0.0, 1.0]) - centres
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    P = projection_matrices(K, make_T(np.stack([x, np.cross(z, x), z], -1), centres))
    X = rng.uniform(-0.5, 0.5, size=(frames, joints, 3)) + [0.0, 0.0, 1.0]
    h = np.einsum("tvij,tkj->tvki", P[..., :3], X) + P[:, :, None, :, 3]
    xy = h[..., :2] / h[..., 2:] + rng.normal(size=(frames, views, joints, 2)) * 2.0
    conf = rng.uniform(0.5, 1.0, size=(frames, views, joints))
    return P, X, xy, conf


def best_time(fn, repeat: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run(frames: int, joints: int, views: int, repeat: int) -> dict:
    P, X, xy, conf = synthetic(frames, joints, views)
    t_fast, res = best_time(lambda: triangulate(P, xy, conf), repeat)
    t_loop, ref = best_time(lambda: triangulate_loop(P, xy, conf, min_conf=0.3), 1)
    ones = np.ones_like(conf)
    plain = triangulate(P, xy, ones, TriangulationConfig(reject_px=np.inf, max_gap_frames=0)).points
    diff = float(np.nanmax(np.abs(plain - triangulate_loop(P, xy, ones, min_conf=0.3))))
    rmse = lambda p: float(np.sqrt(np.nanmean(np.sum((p - X) ** 2, -1))))  # noqa: E731
    return {
        "frames": frames, "joints": joints, "views": views,
        "triangulate_s": round(t_fast, 4), "loop_s": round(t_loop, 3),
        "speedup": round(t_loop / t_fast, 1), "max_diff_unweighted_m": diff,
        "rmse_triangulate_mm": round(1000 * rmse(res.points), 2), "rmse_loop_mm": round(1000 * rmse(ref), 2),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1800)
    ap.add_argument("--joints", type=int, default=17)
    ap.add_argument("--views", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--repeat", type=int, default=3, help="runs of triangulate; the best is kept")
    ap.add_argument("--json", type=Path, default=None, help="also write the summary here")
    args = ap.parse_args()
    rows = [run(args.frames, args.joints, v, args.repeat) for v in args.views]
    print("| frames x joints x views | triangulate (s) | loop (s) | speed-up | max diff, unweighted (m) "
          "| RMSE triangulate (mm) | RMSE loop (mm) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['frames']} x {r['joints']} x {r['views']} | {r['triangulate_s']:.4f} | {r['loop_s']:.3f} "
              f"| {r['speedup']:.0f}x | {r['max_diff_unweighted_m']:.1e} | {r['rmse_triangulate_mm']:.2f} "
              f"| {r['rmse_loop_mm']:.2f} |")
    text = json.dumps({"rows": rows}, indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 0 if all(r["max_diff_unweighted_m"] < 1e-6 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
