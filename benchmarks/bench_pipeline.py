"""Speed of every stage on one synthetic session (default 60 s of two-view capture).

Synthesises the session (indoor, 640x480, 15 s scene capture) unless OUT already holds it, then runs
each stage from scratch in its own child process (`embodmocap <stage> SESSION --force`): wall time,
peak RSS of that process, frames/s (sequence frames per second of wall time, per view where the
stage works per view), and the split of each stage into its steps from the stage manifests.

Targets: Stage III on a 60 s two-view sequence <= 3 min (issue 5, split between feature work =
registration and optimisation = refinement); Stage IV fit of 1800 frames <= 2 min (issue 6).

    .venv/bin/python benchmarks/bench_pipeline.py --seconds 60 --out /tmp/bench_pipeline
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _child import run_cli

STAGES = (("scene", "scenes/scene0/manifest.json"), ("sequence", "sequences/seq0/manifest.json"),
          ("calibrate", "sequences/seq0/calibrate_manifest.json"), ("motion", "sequences/seq0/motion_manifest.json"),
          ("evaluate", None))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/pipeline"))
    args = ap.parse_args()
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = args.out / f"indoor_{int(args.seconds)}s"
    if not (session / "ground_truth" / "ground_truth.json").is_file():
        synthesize(SynthConfig(seed=args.seed, seconds=args.seconds, scene_seconds=15.0), session)
    frames = None
    print("| stage | wall s | peak RSS MB | frames/s | steps (s) |")
    print("|---|---|---|---|---|")
    for stage, manifest in STAGES:
        extra = [] if stage == "evaluate" else ["--force"]
        wall, rss = run_cli(stage, str(session), *extra)
        steps = {}
        if manifest is not None:
            man = json.loads((session / manifest).read_text())
            steps = {k: v["seconds"] for k, v in man["steps"].items()}
            if stage == "sequence":
                frames = man["figures"]["frames"]
        fps = f"{frames / wall:.1f}" if frames and stage != "scene" else "-"
        print(f"| {stage} | {wall:.1f} | {rss} | {fps} | {', '.join(f'{k} {v:.1f}' for k, v in steps.items())} |",
              flush=True)
    print(f"\n{frames} sequence frames per view ({args.seconds:.0f} s at 30 fps)")


if __name__ == "__main__":
    main()
