"""Benchmark the world-space SMPLify (Stage IV) on synthetic motion against the truth.

Per run (one child process each, for its own peak RSS): script ``--seconds`` of motion in a
generated room with the generated test body, observe it from two cameras 4 m away (one static, one
slowly orbiting), make noisy observations (COCO-17 pixel noise ``--noise-px``; 3D keypoints = the
truth plus Gaussian noise ``--noise-m`` per axis, standing in for triangulation), build a camera-space
body prior from the perturbed truth (pose noise 0.15 rad, betas noise 0.5, a 10 cm offset) and
start from :func:`init_from_prior`. Reports the fit's wall time and per-phase times, the peak RSS
of the child, and the MPJPE of COCO-17 and of the limb joints against the truth next to the raw
3D keypoints' error.

Target (issue 6): <= 2 minutes for 1800 frames on a 2-core machine.

    .venv/bin/python benchmarks/bench_smplify.py --seconds 60 --threads 1 2
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

LIMB_JOINTS = [1, 2, 4, 5, 7, 8, 16, 17, 18, 19, 20, 21]


def child(args) -> dict:
    import torch
    from scipy.spatial.transform import Rotation

    from embodmocap.body.model import load_body_model
    from embodmocap.geometry.transforms import invert_T, look_at_T
    from embodmocap.io.body_prior import BodyPriorSeq
    from embodmocap.motion.init import init_from_prior
    from embodmocap.motion.smplify import KeypointBody, SmplifyConfig, ViewObservations, fit_world_smpl
    from embodmocap.synth.motion import script_motion
    from embodmocap.synth.scene import build_scene

    torch.set_num_threads(args.threads)  # the caller's choice; the library never sets it
    rng = np.random.default_rng(args.seed)
    body = load_body_model(None)
    betas = np.array([0.5, -0.3, 0.2, 0.0, 0.1, 0, 0, 0, 0, 0])
    spec = build_scene("indoor", np.random.default_rng(args.seed)).spec
    truth = script_motion(spec, body, betas, args.seconds, 30.0, np.random.default_rng(args.seed)).params
    # KeypointBody gives BodyModel's joints and COCO-17 without skinning every vertex, so the
    # peak RSS below is the fit's, not that of evaluating 1800 full meshes.
    kb = KeypointBody(body)
    pose = lambda p: [torch.as_tensor(np.array(x, dtype=np.float64))  # noqa: E731
                      for x in (p.betas, p.global_orient, p.body_pose, p.transl)]
    joints, coco = (x.numpy() for x in kb(*pose(truth)))
    T = len(truth)

    K = np.array([[700.0, 0.0, 360.0], [0.0, 700.0, 480.0], [0.0, 0.0, 1.0]])
    views = []
    for name, a0, rate in (("v1", 0.3, 0.0), ("v2", 1.9, 0.002)):
        # Cameras follow the performer (as the handheld phones do) from 4 m away.
        cams = np.stack([look_at_T(p + [4 * np.cos(a), 4 * np.sin(a), 0.3], p)
                         for p, a in zip(joints[:, 0], a0 + rate * np.arange(T))])
        Tcw = invert_T(cams)
        pc = np.einsum("tij,tkj->tki", Tcw[:, :3, :3], coco) + Tcw[:, None, :3, 3]
        uv = pc @ K.T
        uv = uv[..., :2] / uv[..., 2:] + rng.normal(size=(T, 17, 2)) * args.noise_px
        views.append(ViewObservations(K, cams, np.concatenate([uv, np.ones((T, 17, 1))], -1), name))
    kp3d = coco + rng.normal(size=coco.shape) * args.noise_m

    # A regressor-like camera-space prior in view 1: perturbed truth.
    R, c = views[0].T_world_cam[:, :3, :3], views[0].T_world_cam[:, :3, 3]
    betas_t = betas + rng.normal(size=(T, 10)) * 0.5
    go_w = Rotation.from_rotvec(np.array(truth.global_orient)) * Rotation.from_rotvec(rng.normal(size=(T, 3)) * 0.1)
    pelvis = truth.transl + body.pelvis_offset(betas) + [0.1, 0.0, 0.0]
    prior = BodyPriorSeq(
        (Rotation.from_matrix(R).inv() * go_w).as_rotvec(),
        truth.body_pose + rng.normal(size=(T, 69)) * 0.15,
        betas_t,
        np.einsum("tji,tj->ti", R, pelvis - c) - body.pelvis_offset(betas_t),
        np.arange(T),
    )
    t0 = time.perf_counter()
    init = init_from_prior(body, prior, views[0].T_world_cam)
    t_init = time.perf_counter() - t0
    cfg = SmplifyConfig(device="cpu", solver=args.solver)
    res = fit_world_smpl(body, kp3d, np.ones((T, 17)), views, init, prior.body_pose, cfg)
    fit_joints, fit_coco = (x.numpy() for x in kb(*pose(res.params)))
    mpjpe = lambda a, b: float(1000 * np.linalg.norm(a - b, axis=-1).mean())  # noqa: E731
    return {
        "frames": T, "threads": args.threads, "solver": args.solver, "windows": len(res.windows),
        "fit_s": round(res.seconds, 1), "init_s": round(t_init, 2), "phase_s": res.phase_seconds,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024,
        "mpjpe_coco_mm": round(mpjpe(fit_coco, coco), 1),
        "mpjpe_limbs_mm": round(mpjpe(fit_joints[:, LIMB_JOINTS], joints[:, LIMB_JOINTS]), 1),
        "init_coco_mm": round(mpjpe(kb(*pose(init))[1].numpy(), coco), 1),
        "raw_kp3d_mm": round(mpjpe(kp3d, coco), 1),
        "reproj_px": {k: round(v, 2) for k, v in res.reproj_px.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--solver", nargs="+", default=["adam"])
    ap.add_argument("--noise-m", type=float, default=0.02)
    ap.add_argument("--noise-px", type=float, default=5.0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/smplify"))
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        args.threads, args.solver = args.threads[0], args.solver[0]
        print(json.dumps(child(args)))
        return
    rows = []
    for solver in args.solver:
        for n in args.threads:
            cmd = [sys.executable, __file__, "--child", "--seconds", str(args.seconds), "--seed", str(args.seed),
                   "--threads", str(n), "--solver", solver, "--noise-m", str(args.noise_m), "--noise-px", str(args.noise_px)]
            t0 = time.perf_counter()
            # Idle OpenMP threads sleep instead of spinning (as in tests/conftest.py): with two
            # threads on a 2-core machine shared with other work, spinning costs minutes.
            env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
            proc = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            row["child_wall_s"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
            print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_smplify.json").write_text(json.dumps(rows, indent=2))
    print("\n| solver | threads | frames | fit (s) | phase 1 (s) | phase 2 (s) | peak RSS (MB) | MPJPE COCO (mm) | limbs (mm) | raw kp3d (mm) | init (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ph = r["phase_s"]
        print(f"| {r['solver']} | {r['threads']} | {r['frames']} | {r['fit_s']} | {ph.get('phase1', 0):.1f} | {ph.get('phase2', 0):.1f} "
              f"| {r['peak_rss_mb']} | {r['mpjpe_coco_mm']} | {r['mpjpe_limbs_mm']} | {r['raw_kp3d_mm']} | {r['init_coco_mm']} |")


if __name__ == "__main__":
    main()
