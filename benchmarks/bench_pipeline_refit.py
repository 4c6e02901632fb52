"""Stage IV's fit re-run in memory on processed sessions under config variants, scored against the truth.

For each session (Stages I-III done, e.g. the sessions of ``embodmocap benchmark``) and each variant,
the dual-view fit exactly as Stage IV makes it (sub-frame sync, triangulation, body priors, fit:
``embodmocap.motion.solve``; nothing is written), scored as the benchmark scores ``dual``
(W-MPJPE at chunks 100 and 1000, WA-, PA-MPJPE, the unaligned world error, flagged frames). With
the default config and the prior it reproduces the session's own ``smpl_fit.npz`` figures.

    PYTHONPATH=src python benchmarks/bench_pipeline_refit.py '{"default": {}, "no prior": {"_prior": false}, \
        "all held": {"edge_hold": "all"}}' SESSION [SESSION ...]

A variant is a JSON object of ``SmplifyConfig`` fields to change, plus ``"_prior": false`` for no
body prior (``MotionConfig.use_body_prior``).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def main() -> None:
    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate.benchmark import _Context, scored
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.io.layout import VIEWS, SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.stage_files import read_cameras, read_keypoints2d, sequence_fps
    from embodmocap.motion import solve as s4
    from embodmocap.motion.config import MotionConfig
    from embodmocap.motion.stage import keypoint_layout
    from embodmocap.sequence.subframe import synced_views

    variants = json.loads(sys.argv[1])
    for s in sys.argv[2:]:
        lay = SessionLayout(Path(s))
        man = load_manifest(lay.manifest)
        seq = next(iter(man.sequences))
        scene = man.sequences[seq].scene
        model = load_body_model(man.body_model)
        truth = sequence_truth(lay, scene, seq)
        ctx = _Context(lay, seq, scene, model)
        sl = ctx.sl
        # As Stage IV: view 2 resampled at view 1's instants (sub-frame sync).
        cams, kps = synced_views(sl, {v: read_cameras(sl.view(v).cameras_world) for v in VIEWS},
                                 {v: read_keypoints2d(sl.view(v).keypoints).keypoints for v in VIEWS})
        T = min(len(kps[v]) for v in VIEWS)
        layout = keypoint_layout(sl, seq)
        for name, over in variants.items():
            over = dict(over)
            use_prior = over.pop("_prior", True)
            mcfg = MotionConfig()
            mcfg = replace(mcfg, smplify=replace(mcfg.smplify, **over), use_body_prior=use_prior)
            t0 = time.perf_counter()
            tri = s4.triangulate_views(mcfg, cams, kps, T, seq)
            priors = ctx._priors(mcfg.min_prior_fraction, T) if use_prior else {}
            fitted = s4.fit_motion(mcfg, model, tri.file, cams, kps, T, sequence_fps(sl), priors, layout,
                                   man.gender, label=seq)
            e = scored(ctx.joints(fitted.params), np.arange(len(fitted.params)), truth, fitted.valid)
            print(f"RESULT {Path(s).name} {name}: W100 {e['w_mpjpe_mm']:.1f} W1000 {e['w_mpjpe_mm_c1000']:.1f} "
                  f"WA {e['wa_mpjpe_mm']:.1f} PA {e['pa_mpjpe_mm']:.1f} world {e['world_mpjpe_mm']:.1f} "
                  f"invalid {e['invalid_frames']} ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
