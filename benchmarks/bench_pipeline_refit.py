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
    from _stage4 import stage4_session

    from embodmocap.evaluate.benchmark import scored
    from embodmocap.io.stage_files import sequence_fps
    from embodmocap.motion import solve as s4
    from embodmocap.motion.config import MotionConfig

    variants = json.loads(sys.argv[1])
    for s in sys.argv[2:]:
        ss = stage4_session(s)
        seq, model, truth, ctx, cams, kps, T, layout = ss.seq, ss.model, ss.truth, ss.ctx, ss.cams, ss.kps, ss.T, ss.layout
        sl = ctx.sl
        for name, over in variants.items():
            over = dict(over)
            use_prior = over.pop("_prior", True)
            mcfg = MotionConfig()
            mcfg = replace(mcfg, smplify=replace(mcfg.smplify, **over), use_body_prior=use_prior)
            t0 = time.perf_counter()
            tri = s4.triangulate_views(mcfg, cams, kps, T, seq)
            priors = ctx._priors(mcfg.min_prior_fraction, T) if use_prior else {}
            fitted = s4.fit_motion(mcfg, model, tri.file, cams, kps, T, sequence_fps(sl), priors, layout,
                                   ss.gender, label=seq)
            e = scored(ctx.joints(fitted.params), np.arange(len(fitted.params)), truth, fitted.valid)
            print(f"RESULT {Path(s).name} {name}: W100 {e['w_mpjpe_mm']:.1f} W1000 {e['w_mpjpe_mm_c1000']:.1f} "
                  f"WA {e['wa_mpjpe_mm']:.1f} PA {e['pa_mpjpe_mm']:.1f} world {e['world_mpjpe_mm']:.1f} "
                  f"invalid {e['invalid_frames']} ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
