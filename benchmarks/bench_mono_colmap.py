"""Monocular pipeline (issue 15) with the scene models that need no precomputed inputs: ``colmap``
(SfM per chunk, metric scale from the feet on the SfM floor) and ``vio`` (the phone's poses and
depth; ablation), both with Stage II's realistic body prior, on sessions with Stage II done.

Per session and scene model: ``embodmocap mono`` on view v1 (``--force``), its wall and CPU
seconds (this process and COLMAP's threads), the segments, the metric scale's cue / spread /
voting frames, and the ``v1_mono_*`` evaluation keys against the ground truth (W-/WA-MPJPE at
chunks 100 / 500 / 1000, RTE, camera error, scale error). Sessions are used in place when
``--copy`` is not given (mono writes only ``sequences/<seq>/mono/``); with ``--copy DIR`` each
session is mirrored under DIR with symlinked files first (the original is never written).

    OMP_NUM_THREADS=1 nice -n 19 python benchmarks/bench_mono_colmap.py /work/bench/15/mono_s0_60s \\
        --out /work/bench/15/s5/colmap_60s.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def mirror(src: Path, dst: Path) -> Path:
    """A copy of ``src`` whose files are symlinks (folders real): new outputs land in ``dst`` only."""
    if not dst.exists():
        shutil.copytree(src, dst, copy_function=os.symlink, symlinks=True,
                        ignore=shutil.ignore_patterns("mono"))
    return dst


def joint_errors(session: Path, seq: str, scene: str) -> dict:
    """W-/WA-MPJPE at chunks 500 and 1000 of the mono result (``mono_metrics`` gives chunk 100)."""
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate import metrics as M
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid

    lay = SessionLayout(session)
    model = load_body_model(load_manifest(lay.manifest).body_model)
    truth = sequence_truth(lay, scene, seq)
    ml = lay.sequence(seq).mono("v1")
    params, frames = read_smpl_npz(ml.smpl_world)
    valid = read_smpl_valid(ml.smpl_world)
    with torch.no_grad():
        j = model.from_params(params, dtype=torch.float64).joints.numpy()
    n = min(len(frames), len(truth.joints))
    ok = truth.valid[frames[:n]] & valid[:n]
    pred, gt = j[:n][ok], truth.joints[frames[:n]][ok]
    out = {}
    for c in (500, 1000):
        out[f"w_mpjpe_mm_c{c}"] = round(float(M.w_mpjpe(pred, gt, chunk=c)), 2)
        out[f"wa_mpjpe_mm_c{c}"] = round(float(M.wa_mpjpe(pred, gt, chunk=c)), 2)
    out["valid_frames"] = int(ok.sum())
    out["frames"] = int(n)
    return out


def run_one(session: Path, scene_model: str, threads: int) -> dict:
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.mono import stage
    from embodmocap.mono.config import MonoConfig
    from embodmocap.evaluate.mono import mono_metrics

    lay = SessionLayout(session)
    man = load_manifest(lay.manifest)
    seq = next(iter(man.sequences))
    scene = man.sequences[seq].scene
    cfg = MonoConfig(scene_model=scene_model, human_model="prior")
    cfg = replace(cfg, colmap=replace(cfg.colmap, num_threads=threads))
    t0, c0 = time.perf_counter(), time.process_time()
    out = stage.run(cfg, session, force=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    ms = out.figures["metric_scale"]
    row = {"session": session.name, "scene_model": scene_model, "frames": out.figures["frames"],
           "mono_wall_s": round(wall, 1), "mono_cpu_s": round(cpu, 1), "colmap_threads": threads,
           "segments": out.figures["segments"], "warnings": len(out.figures["warnings"]),
           "scale_cue": {g: s.get("cue") for g, s in ms.items()},
           "scale_mad_rel": {g: s.get("mad_rel") for g, s in ms.items()},
           "scale_frames": {g: s.get("frames") for g, s in ms.items()},
           **{k: v for k, v in mono_metrics(lay, scene, seq).items() if k.startswith("v1_mono_")},
           **joint_errors(session, seq, scene)}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", type=Path, nargs="+")
    ap.add_argument("--models", nargs="+", default=["colmap", "vio"])
    ap.add_argument("--threads", type=int, default=1, help="COLMAP threads")
    ap.add_argument("--copy", type=Path, default=None, help="mirror each session here first (symlinked files)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rows = json.loads(args.out.read_text()) if args.out.is_file() else []
    done = {(r["session"], r["scene_model"]) for r in rows}
    for s in args.sessions:
        session = mirror(s, args.copy / s.name) if args.copy else s
        for m in args.models:
            if (session.name, m) in done:
                continue
            try:
                row = run_one(session, m, args.threads)
            except Exception as err:  # noqa: BLE001 - a failed run is a row of the table, not hidden
                row = {"session": session.name, "scene_model": m, "error": f"{type(err).__name__}: {err}"}
            rows.append(row)
            print(json.dumps(row), flush=True)
            args.out.write_text(json.dumps(rows, indent=1))
    keys = ("v1_mono_w_mpjpe_mm", "v1_mono_wa_mpjpe_mm", "w_mpjpe_mm_c500", "wa_mpjpe_mm_c500", "w_mpjpe_mm_c1000",
            "wa_mpjpe_mm_c1000", "v1_mono_rte_pct", "v1_mono_camera_err_cm", "v1_mono_scale_err_pct")
    for m in args.models:
        sel = [r for r in rows if r["scene_model"] == m and "error" not in r]
        if sel:
            print(m, len(sel), {k: round(float(np.mean([r[k] for r in sel])), 3) for k in keys})


if __name__ == "__main__":
    main()
