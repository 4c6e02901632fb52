"""Monocular vs dual view (issue 15) on the same studio sessions: the capture-methods figures
(W-MPJPE / WA-MPJPE at chunks 100 / 500 / 1000, RTE) of ``embodmocap mono`` on view v1 beside the
dual-view pipeline's result.

Per seed the session of ``bench_mono.py`` (20 s, Stage II done, under --work) is copied once and
run through every stage (``embodmocap run``; reused when already there), then ``embodmocap mono``
with:

- ``mono-precomputed``: the studio's noisy Pi3-like chunks and the realistic camera-space body
  (what a real user with Pi3 + VIMO output has);
- ``mono-vio``: the phone's own poses and LiDAR depth with Stage II's body prior (ablation);
- ``dual``: the full dual-view pipeline (Stage IV's ``smpl_world.npz``).

The monocular ``colmap`` scene model does not exist yet, so it has no row. Errors come from
``evaluate.session.motion_errors`` against the truth (the same function as ``embodmocap
evaluate``'s dual-view keys).

    OMP_NUM_THREADS=1 nice -n 19 python benchmarks/bench_mono_vs_dual.py --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

KEYS = ("w_mpjpe_mm", "wa_mpjpe_mm", "w_mpjpe_mm_c500", "wa_mpjpe_mm_c500", "w_mpjpe_mm_c1000", "wa_mpjpe_mm_c1000",
        "rte_pct")


def main() -> None:
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate.session import motion_errors, sequence_truth
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid
    from embodmocap.mono import stage
    from embodmocap.mono.config import MonoConfig
    from embodmocap.pipeline import PipelineConfig, run_session
    from embodmocap.synth.mono_inputs import MonoInputConfig, write_mono_inputs

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--work", type=Path, default=Path("/work/bench/15"))
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        base = args.work / f"mono_s{seed}_{args.seconds:g}s"
        if not (base / "sequences").is_dir():
            raise SystemExit(f"{base} missing: run bench_mono.py --seeds {seed} --seconds {args.seconds:g} first")
        work = args.work / f"dual_s{seed}_{args.seconds:g}s"
        if not work.exists():
            shutil.copytree(base, work, symlinks=True)
        run_session(PipelineConfig(), work)
        lay = SessionLayout(work)
        model = load_body_model(lay.body_model if lay.body_model.is_file() else None)
        truth = sequence_truth(lay, "scene0", "seq0")

        def errors(path):
            params, frames = read_smpl_npz(path)
            with torch.no_grad():
                joints = model.from_params(params, dtype=torch.float64).joints.numpy()
            return motion_errors(joints, frames, truth, read_smpl_valid(path))

        methods = {"dual": errors(lay.sequence("seq0").smpl_world)}
        write_mono_inputs(work, cfg=MonoInputConfig(), seed=100 + seed)
        cfg = MonoConfig(human_model="precomputed")
        methods["mono-precomputed"] = errors(stage.run(cfg, work, force=True).layout.smpl_world)
        methods["mono-vio"] = errors(stage.run(replace(cfg, scene_model="vio", human_model="prior"), work,
                                               force=True).layout.smpl_world)
        for name, e in methods.items():
            row = {"seed": seed, "method": name, **{k: e.get(k) for k in KEYS}}
            rows.append(row)
            print(json.dumps(row), flush=True)
    (args.work / "bench_mono_vs_dual.json").write_text(json.dumps(rows, indent=1))
    print("| method | " + " | ".join(KEYS) + " |")
    print("|---" * (len(KEYS) + 1) + "|")
    for m in ("mono-precomputed", "mono-vio", "dual"):
        vals = [np.nanmean([r[k] for r in rows if r["method"] == m]) for k in KEYS]
        print(f"| {m} | " + " | ".join(f"{v:.2f}" for v in vals) + " |")


if __name__ == "__main__":
    main()
