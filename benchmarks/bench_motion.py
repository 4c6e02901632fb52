"""Benchmark Stage IV (`embodmocap motion`) against ground truth over synthetic seeds.

For each seed: synthesise a session (or reuse one in OUT), run Stages I-III (resumed: skipped when
already done, e.g. by bench_calibrate.py into the same OUT), then Stage IV (timed, forced), and
compare the world joints with the truth in Stage I's world: W-MPJPE and WA-MPJPE at chunk sizes
100, 500 and 1000 (GVHMR's definitions, :mod:`embodmocap.evaluate.metrics`), PA-MPJPE and RTE.

Targets (issue 6, dual view, default noise): W-MPJPE <= 60 mm, WA-MPJPE <= 45 mm, RTE <= 1 %.

    .venv/bin/python benchmarks/bench_motion.py --seeds 0 1 2 3 4 5 6 7 8 9 --out /tmp/bench_calib
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from _seeds import run_seeds, seed_arguments

KEYS = ("w_mpjpe_mm", "wa_mpjpe_mm", "w_mpjpe_mm_c500", "wa_mpjpe_mm_c500", "w_mpjpe_mm_c1000",
        "wa_mpjpe_mm_c1000", "pa_mpjpe_mm", "rte_pct")


def one_seed(root: Path, seed: int, preset: str, seconds: float, scene_seconds: float) -> dict:
    from embodmocap.calibrate import stage as stage3
    from embodmocap.evaluate.session import sequence_errors
    from embodmocap.io.layout import SessionLayout
    from embodmocap.motion import stage as stage4
    from embodmocap.scene import stage as stage1
    from embodmocap.scene.config import SceneConfig
    from embodmocap.sequence import stage as stage2
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = root / f"{preset}_{seed}"
    if not (session / "ground_truth" / "ground_truth.json").is_file():
        synthesize(SynthConfig(seed=seed, preset=preset, seconds=seconds, scene_seconds=scene_seconds), session)
    stage1.run(SceneConfig(), session)
    stage2.run(SequenceConfig(), session)
    stage3.run(stage3.CalibrateConfig(), session)
    t0 = time.perf_counter()
    out = stage4.run(stage4.MotionConfig(), session, force=True)
    wall = time.perf_counter() - t0
    errs = sequence_errors(SessionLayout(session), "scene0", "seq0")
    row = {"preset": preset, "seed": seed, "frames": int(np.load(out.layout.joints_world)["joints"].shape[0]),
           "motion_s": round(wall, 1), **{k: errs[k] for k in KEYS}}
    row["reproj_px"] = {v: out.figures.get(f"{v}_reproj_px") for v in ("v1", "v2")}
    return row


def main() -> None:
    args = seed_arguments(__doc__.splitlines()[0], "bench_out/calibrate")
    ok = run_seeds(one_seed, args, "bench_motion")
    print("| metric | median | p95 | max |")
    print("|---|---|---|---|")
    for k in KEYS:
        a = np.array([r[k] for r in ok], dtype=float)
        if len(a):
            print(f"| {k} | {np.median(a):.2f} | {np.percentile(a, 95):.2f} | {a.max():.2f} |")


if __name__ == "__main__":
    main()
