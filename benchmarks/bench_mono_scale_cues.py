"""Metric scale cues of ``embodmocap mono`` on the same precomputed (Pi3-like, noisy) inputs:
``body`` (body depth / point-map depth inside the person mask) vs ``feet`` (the feet in contact
on the scene's floor plane), with the realistic body prior. Per seed: a copy of the studio session
reused by ``bench_mono.py`` (``--work``/mono_s<seed>_<seconds>s), the same noisy inputs as its
``noisy`` row (``write_mono_inputs``, seed 100 + seed), ``mono`` once per cue; the scale error is
``v1_mono_scale_err_pct`` against the ground truth.

    OMP_NUM_THREADS=1 nice -n 19 python benchmarks/bench_mono_scale_cues.py --seeds 0 1 2 --seconds 20 \\
        --out /work/bench/15/s5/scale_cues_20s.json
"""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path


def main() -> None:
    from embodmocap.io.layout import SessionLayout
    from embodmocap.mono import stage
    from embodmocap.mono.config import MonoConfig
    from embodmocap.mono.evaluate import mono_metrics
    from embodmocap.synth.mono_inputs import MonoInputConfig, write_mono_inputs

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--work", type=Path, default=Path("/work/bench/15"))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        base = args.work / f"mono_s{seed}_{args.seconds:g}s"
        work = args.work / "s5" / f"cues_s{seed}_{args.seconds:g}s"
        if not (work / "perception" / "seq0" / "v1" / "mono_human.npz").is_file():
            if work.exists():
                shutil.rmtree(work)
            shutil.copytree(base, work, symlinks=True, ignore=shutil.ignore_patterns("mono"))
            write_mono_inputs(work, cfg=MonoInputConfig(), seed=100 + seed)
        for cue in ("body", "feet"):
            cfg = MonoConfig(scene_model="precomputed", human_model="precomputed")
            out = stage.run(replace(cfg, scale=replace(cfg.scale, cue=cue)), work, force=True)
            mm = mono_metrics(SessionLayout(work), "scene0", "seq0")
            row = {"seed": seed, "seconds": args.seconds, "cue": cue, **out.figures["metric_scale"]["0"],
                   "scale_err_pct": mm["v1_mono_scale_err_pct"], "camera_err_cm": mm["v1_mono_camera_err_cm"],
                   "w_mpjpe_mm": mm["v1_mono_w_mpjpe_mm"], "segments": out.figures["segments"]}
            rows.append(row)
            print(json.dumps(row), flush=True)
    args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
