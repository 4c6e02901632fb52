"""Where a finished ``embodmocap mono`` run's metric scale error comes from, on a studio session
(ground truth used for the diagnosis only; nothing here feeds the pipeline):

- ``global_signed_err_pct``: ``s - 1`` with ``s`` the similarity scale from the mono camera
  centres onto the true ones (``|s - 1|`` = ``v1_mono_scale_err_pct``; positive: world too small);
- ``drift_pct_p10_50_90``: the stitching's scale drift, per 64-frame window (step 48) the
  window's similarity scale over the global one, minus 1 (%);
- ``prior_depth_err_median_pct``: the human model's own depth error, median over frames of
  ``|pelvis_model_cam| / |pelvis_true_cam| - 1`` (%), for ``--human-model precomputed`` runs
  (``mono_human.npz``) or the body prior with ``--human-model prior``.

    OMP_NUM_THREADS=1 python benchmarks/bench_mono_scale_diag.py /work/bench/15/s5b/cues_s{0,1,2}_20s \\
        /work/bench/15/s5b/cues_s0_60s
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate.metrics import umeyama
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.geometry.transforms import invert_T
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.mono.files import read_mono_cameras
    from embodmocap.mono.roles import PrecomputedHuman, PriorHuman

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", type=Path, nargs="+")
    ap.add_argument("--seq", default="seq0")
    ap.add_argument("--scene", default="scene0")
    ap.add_argument("--view", default="v1")
    ap.add_argument("--human-model", choices=["precomputed", "prior"], default="precomputed")
    args = ap.parse_args()
    for w in args.sessions:
        lay = SessionLayout(w)
        mc = read_mono_cameras(lay.sequence(args.seq).mono(args.view).cameras_world)
        truth = sequence_truth(lay, args.scene, args.seq)
        ref = truth.T_world_cam[args.view]
        n = min(len(ref), len(mc["T_world_cam"]))
        C, G = mc["T_world_cam"][:n, :3, 3], ref[:n, :3, 3]
        ok = np.isfinite(mc["metric_scale"][:n])
        s, _, _ = umeyama(C[ok], G[ok])
        loc = [umeyama(C[a:a + 64], G[a:a + 64])[0] / s - 1 for a in range(0, n - 63, 48) if ok[a:a + 64].all()]
        human = (PrecomputedHuman(lay.perception(args.seq, args.view).mono_human) if args.human_model == "precomputed"
                 else PriorHuman(lay.sequence(args.seq).view(args.view).body_prior)).estimate(n)
        model = load_body_model(load_manifest(lay.manifest).body_model)
        p_model = model.pelvis_offset(human.betas) + human.transl
        T_cw = invert_T(ref)
        p_true = np.einsum("tij,tj->ti", T_cw[:, :3, :3], truth.joints[:n, 0]) + T_cw[:, :3, 3]
        e = np.linalg.norm(p_model, axis=1) / np.linalg.norm(p_true, axis=1)
        good = human.valid[:n] & np.asarray(truth.valid[:n], bool)
        print(json.dumps({"session": str(w), "global_signed_err_pct": round(100 * (float(s) - 1), 3),
                          "drift_pct_p10_50_90": np.round(100 * np.percentile(loc, [10, 50, 90]), 2).tolist() if loc else None,
                          "prior_depth_err_median_pct": round(100 * (float(np.median(e[good])) - 1), 3),
                          "frames": int(good.sum())}), flush=True)


if __name__ == "__main__":
    main()
