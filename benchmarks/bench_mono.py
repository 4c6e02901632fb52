"""Monocular pipeline (issue 15): stitching and metric scale on studio sessions with the studio's
precomputed scene-model (Pi3-like chunks) and human inputs.

Per seed, one studio session (Stage II run once, reused under --work), then ``embodmocap mono`` on
view v1 with --chunk/--overlap (default 64/16) for these inputs:

- ``exact``: noise-free point maps, cameras and body; only each chunk's random similarity;
- ``noisy``: depth-dependent noise, pose noise, missing regions, confidence; the realistic body
  prior's errors (depth 10 % off with 0.5 s correlation, 7 deg per joint);
- ``noisy, true body (oracle)``: the same noisy scene inputs with the exact camera-space body
  (isolates the stitching from the body's depth error: not something a real input has);
- ``vio``: the phone's own poses and LiDAR depth (ablation).

Figures: metric scale error ``100 |s - 1|`` (s: similarity between the output camera centres and
the true ones), camera-centre error after one rigid alignment (mean and max, mm and % of the path
length), after a similarity (stitching alone), the overlap residuals, the mono_* evaluation keys
and the seconds mono took.

    OMP_NUM_THREADS=1 nice -n 19 python benchmarks/bench_mono.py --seeds 0 1 2 --seconds 20

Each row runs once per ``--human-depth`` (``model``: the human model's own translation, the code
before the keypoint refinement, and what exact recovery needs: the studio's Stage II keypoints
carry detector noise; ``keypoints``: refined against them, the default). ``--copies`` puts the
per-variant session copies elsewhere than ``--work`` (the reused studio sessions stay read-only).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def centre_figures(P, G) -> dict:
    from embodmocap.evaluate.metrics import umeyama

    L = float(np.linalg.norm(np.diff(G, axis=0), axis=1).sum())
    s, R, t = umeyama(P, G)
    _, R1, t1 = umeyama(P, G, with_scale=False)
    rigid = np.linalg.norm(P @ R1.T + t1 - G, axis=1)
    sim = np.linalg.norm(s * P @ R.T + t - G, axis=1)
    return {"path_m": round(L, 3), "scale_err_pct": round(100 * abs(float(s) - 1), 4),
            "centre_mean_mm": round(1000 * rigid.mean(), 3), "centre_max_mm": round(1000 * rigid.max(), 3),
            "centre_mean_pct_path": round(100 * rigid.mean() / L, 4), "centre_max_pct_path": round(100 * rigid.max() / L, 4),
            "sim_centre_mean_pct_path": round(100 * sim.mean() / L, 4)}


def main() -> None:
    from embodmocap.io.layout import SessionLayout
    from embodmocap.mono import stage
    from embodmocap.mono.config import MonoConfig
    from embodmocap.evaluate.mono import mono_metrics
    from embodmocap.mono.files import read_mono_cameras
    from embodmocap.sequence import stage as sequence_stage
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.mono_inputs import MonoInputConfig, write_mono_inputs
    from embodmocap.synth.perception import PriorNoiseConfig
    from embodmocap.synth.studio import synthesize

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--chunk", type=int, default=64)
    ap.add_argument("--overlap", type=int, default=16)
    ap.add_argument("--work", type=Path, default=Path("/work/bench/15"))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--copies", type=Path, default=None, help="folder of the per-variant copies (default --work)")
    ap.add_argument("--human-depth", nargs="+", default=["model", "keypoints"], choices=["model", "keypoints"])
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        base = args.work / f"mono_s{seed}_{args.seconds:g}s"
        if not (base / "sequences").is_dir():
            synthesize(SynthConfig(seed=seed, seconds=args.seconds, scene_seconds=1.0, width=320, height=240,
                                   depth_width=128, depth_height=96), base)
            sequence_stage.run(SequenceConfig(), base)
        variants = {
            "exact": MonoInputConfig(chunk=args.chunk, overlap=args.overlap, noise=False),
            "noisy": MonoInputConfig(chunk=args.chunk, overlap=args.overlap),
            "noisy, true body (oracle)": MonoInputConfig(chunk=args.chunk, overlap=args.overlap,
                                                         prior=PriorNoiseConfig(0, 0, 0, 0, 0)),
        }
        for name, icfg in variants.items():
            work = (args.copies or args.work) / f"mono_s{seed}_{args.seconds:g}s_{name.split(',')[0]}{'_oracle' if 'oracle' in name else ''}"
            if work.exists():
                shutil.rmtree(work)
            shutil.copytree(base, work, symlinks=True)
            truth = write_mono_inputs(work, cfg=icfg, seed=100 + seed)
            for depth in args.human_depth:
                rows += _run(stage, mono_metrics, read_mono_cameras, SessionLayout, MonoConfig, args, seed, name, depth,
                             work, truth)
            shutil.rmtree(work)
    out_path = args.out or args.work / f"bench_mono_{args.seconds:g}s.json"
    out_path.write_text(json.dumps(rows, indent=1))
    print(f"wrote {out_path}")


def _run(stage, mono_metrics, read_mono_cameras, SessionLayout, MonoConfig, args, seed, name, depth, work, truth):
    """mono on ``work`` with ``--human-depth depth`` (and, on the noisy inputs, the vio ablation): rows."""
    rows = []
    cfg = MonoConfig(scene_model="precomputed", chunk=args.chunk, overlap=args.overlap, human_model="precomputed",
                     human_depth=depth)
    name = f"{name}, human depth {depth}"
    t0 = time.perf_counter()
    out = stage.run(cfg, work, force=True)
    secs = time.perf_counter() - t0
    P = read_mono_cameras(out.layout.cameras_world)["T_world_cam"][:, :3, 3]
    row = {"seed": seed, "inputs": name, "frames": out.figures["frames"], "mono_s": round(secs, 2),
           "segments": out.figures["segments"],
           "overlap_residual_rel_median": out.figures["overlap_residual_rel_median"],
           "scale_mad_rel": out.figures["metric_scale"]["0"]["mad_rel"],
           "human_depth": out.figures.get("human_depth"),
           **centre_figures(P, truth["T_scene_cam"][:, :3, 3]),
           **{k: v for k, v in mono_metrics(SessionLayout(work), "scene0", "seq0").items() if k.startswith("v1_mono_")}}
    rows.append(row)
    print(json.dumps(row), flush=True)
    if name.startswith("noisy, human"):  # the vio ablation on the same session
        t0 = time.perf_counter()
        out = stage.run(replace(cfg, scene_model="vio", human_model="prior"), work, force=True)
        secs = time.perf_counter() - t0
        P = read_mono_cameras(out.layout.cameras_world)["T_world_cam"][:, :3, 3]
        row = {"seed": seed, "inputs": f"vio (phone poses + LiDAR), Stage II prior, human depth {depth}",
               "frames": out.figures["frames"],
               "mono_s": round(secs, 2), "segments": out.figures["segments"],
               "overlap_residual_rel_median": out.figures["overlap_residual_rel_median"],
               "body_scale_check": out.figures["metric_scale"]["0"]["scale"],
               **centre_figures(P, truth["T_scene_cam"][:, :3, 3]),
               **{k: v for k, v in mono_metrics(SessionLayout(work), "scene0", "seq0").items() if k.startswith("v1_mono_")}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


if __name__ == "__main__":
    main()
