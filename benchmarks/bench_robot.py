"""Retargeting to the Unitree G1: speed on a 60 s sequence and quality on studio seeds.

Run from the repository root (one process, one thread, as the figures in BENCHMARKS.md were made):

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_robot.py --seeds 0 1 2 3 4 --out /work/bench/18

Motions are the synthetic studio's scripted performer (its ground-truth SMPL, i.e. a perfect
Stage IV: an oracle input, as the row names say) in its own room; the scene height map is made from
the studio's mesh as `embodmocap robot retarget` makes it from Stage I's. Figures:

- speed: frames/s of the IK alone (``retarget``) and of the whole job (height map + IK + report)
  for a 60 s, 30 fps sequence that walks and uses every piece of furniture it reaches;
- quality: the walk-to-the-chair-and-sit script (9 s) of each seed: ``robot_report.json``'s
  keypoint residual, joint-limit violations, peak joint speed over its limit, foot skating during
  contacts, foot penetration, self-collision frames.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from embodmocap.body.model import load_body_model
from embodmocap.robot.config import RetargetConfig
from embodmocap.robot.g1 import G1
from embodmocap.robot.model import RobotModel
from embodmocap.robot.report import robot_report
from embodmocap.robot.retarget import HumanRest, ground_heightmap, retarget
from embodmocap.synth.motion import MotionScriptConfig, script_motion
from embodmocap.synth.scene import build_scene


def run(seed: int, seconds: float, interactions: tuple[str, ...], idle_s: float) -> dict:
    body = load_body_model(None)
    built = build_scene("indoor", np.random.default_rng(seed))
    betas = np.zeros(10)
    betas[:4] = np.random.default_rng(seed).normal(0, [0.8, 0.6, 0.5, 0.5])
    script = script_motion(built.spec, body, betas, seconds, 30.0, np.random.default_rng(seed),
                           MotionScriptConfig(idle_s=idle_s, interactions=interactions))
    with torch.no_grad():
        joints = body.from_params(script.params, dtype=torch.float64).joints.numpy()
    t0 = time.perf_counter()
    hm = ground_heightmap(built.vertices, built.faces, joints)
    t1 = time.perf_counter()
    robot = RobotModel.load(G1)
    q, ht = retarget(robot, script.params, joints, HumanRest.of(body, betas), hm, RetargetConfig())
    t2 = time.perf_counter()
    rep = robot_report(robot, q, ht, 30.0, hm)
    t3 = time.perf_counter()
    return {"seed": seed, "frames": len(q), "segments": sorted({n for n, _, _ in script.segments}),
            "heightmap_s": t1 - t0, "ik_s": t2 - t1, "report_s": t3 - t2,
            "ik_frames_per_s": len(q) / (t2 - t1), "total_frames_per_s": len(q) / (t3 - t0), **rep}


KEYS = ("scale", "keypoint_residual_mean_m", "keypoint_residual_max_m", "joint_limit_violations", "joint_speed_max_ratio",
        "foot_skating_max_m", "foot_penetration_max_m", "self_collision_frames", "frames")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--speed-seconds", type=float, default=60.0)
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_robot"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for s in args.seeds:
        r = run(s, 9.0, ("chair",), 0.5)
        rows.append(r)
        print(f"seed {s}: " + ", ".join(f"{k}={r[k]:.4g}" if isinstance(r[k], float) else f"{k}={r[k]}" for k in KEYS), flush=True)
    speed = None
    if not args.skip_speed:
        speed = run(0, args.speed_seconds, ("chair", "box", "table", "sofa"), 1.5)
        print(f"speed ({speed['frames']} frames): IK {speed['ik_frames_per_s']:.1f} frames/s, whole job "
              f"{speed['total_frames_per_s']:.1f} frames/s (height map {speed['heightmap_s']:.1f} s, IK {speed['ik_s']:.1f} s, "
              f"report {speed['report_s']:.1f} s); quality: " + ", ".join(f"{k}={speed[k]}" for k in KEYS), flush=True)
    summary = {k: {"mean": float(np.mean([r[k] for r in rows])), "max": float(np.max([r[k] for r in rows]))}
               for k in KEYS if k != "frames"}
    (args.out / "bench_robot.json").write_text(json.dumps({"rows": rows, "speed": speed, "summary": summary}, indent=1, default=str))
    print("| seed | residual mean (mm) | residual max (mm) | limit violations | peak speed / limit | skating max (mm) "
          "| penetration max (mm) | self-collision frames |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seed']} | {1000 * r['keypoint_residual_mean_m']:.1f} | {1000 * r['keypoint_residual_max_m']:.1f} | "
              f"{r['joint_limit_violations']} | {r['joint_speed_max_ratio']:.2f} | {1000 * r['foot_skating_max_m']:.2f} | "
              f"{1000 * r['foot_penetration_max_m']:.2f} | {r['self_collision_frames']} / {r['frames']} |")


if __name__ == "__main__":
    main()
