"""Per-frame cost of the synthetic studio's renderer (RGB 640x480 + depth 256x192) and LiDAR model.

Renders an empty-scene walk and a two-view follow of a moving stand-in body (a ~14k-triangle
capsule, about an SMPL mesh's size) and prints per-frame timings. Not a test: run it by hand.

    .venv/bin/python benchmarks/bench_render.py [--preset indoor|outdoor] [--frames 120]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh

from embodmocap.synth import lidar, trajectory
from embodmocap.synth.render import Renderer
from embodmocap.synth.scene import build_scene
from embodmocap.types import Intrinsics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="indoor", choices=["indoor", "outdoor"])
    ap.add_argument("--frames", type=int, default=120, help="frames per capture")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    fps = 30.0
    fx = 320 / np.tan(np.deg2rad(67.0) / 2)
    K = Intrinsics(fx, fx, 319.5, 239.5, 640, 480)
    K_depth = K.scaled(256, 192)
    t0 = time.perf_counter()
    built = build_scene(args.preset, np.random.default_rng(args.seed))
    renderer = Renderer(built)
    print(f"scene: {len(built.faces)} triangles, built + BVH in {1e3 * (time.perf_counter() - t0):.0f} ms")

    spec = built.spec
    n = args.frames
    walk = trajectory.scene_walk(spec, n / fps, fps, np.random.default_rng(1))
    t = np.arange(n) / fps
    mid = (spec.walk_area_min_xy + spec.walk_area_max_xy) / 2
    half = (spec.walk_area_max_xy - spec.walk_area_min_xy) / 2 * 0.8
    pelvis = np.column_stack([mid + half * np.column_stack([np.sin(0.5 * t), np.sin(0.31 * t)]), np.full(n, 0.9)])
    v1, v2 = trajectory.follow_views(spec, pelvis, fps, np.random.default_rng(2))
    body = trimesh.creation.capsule(height=1.3, radius=0.22, count=[86, 80])
    verts0 = body.vertices + [0.0, 0.0, 0.87]
    print(f"body stand-in: {len(body.faces)} triangles")

    rng = np.random.default_rng(3)
    for name, poses, with_body in (("scene walk", walk, False), ("view 1", v1, True), ("view 2", v2, True)):
        r_ms, l_ms = [], []
        for i in range(n):
            b = (verts0 + [pelvis[i, 0], pelvis[i, 1], 0.0], body.faces) if with_body else None
            s = time.perf_counter()
            out = renderer.render(K, poses[i], b, laser_on=i < 10, depth_intrinsics=K_depth)
            m = time.perf_counter()
            lidar.simulate_lidar(out.depth_lr_m, rng)
            e = time.perf_counter()
            r_ms.append(1e3 * (m - s))
            l_ms.append(1e3 * (e - m))
        r_ms, l_ms = np.array(r_ms), np.array(l_ms)
        print(
            f"{name:>10}: render mean {r_ms.mean():5.1f} ms  p50 {np.median(r_ms):5.1f}  p95 {np.percentile(r_ms, 95):5.1f}"
            f"  max {r_ms.max():5.1f} | lidar mean {l_ms.mean():4.1f} ms"
        )
    print("budget: ~40 ms per RGB + depth frame (1,300 frames in < 2 min for the whole session)")


if __name__ == "__main__":
    main()
