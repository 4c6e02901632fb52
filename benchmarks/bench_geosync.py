"""Benchmark geometric sync, sub-frame sync and `embodmocap check` (issue 12, items 2-5).

Sessions are synthesised once under OUT and reused (``--prepare`` writes them and runs Stage I):

- ``normal_<seed>``: 6 s indoor/outdoor sessions whose second phone runs a random fraction of a
  frame off the first (``phone_offset_frames``, the truth is in ground_truth.json);
- ``fail_sep20``, ``fail_away``, ``fail_scene``: "built to fail" variants of ``normal_0`` (views 20
  degrees apart; performer out of view 2 for the second half; view 2 filmed in another room). They
  share seed 0's scene capture byte for byte, so Stage I's outputs are copied from ``normal_0``;
- ``long_60``: a 60 s session for the speed of `embodmocap check`.

Modes (each prints JSON rows and writes OUT/<mode>.json):

    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py prepare --out /work/bench/12b
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py geosync --out /work/bench/12b
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py subframe --out /work/bench/12b --seeds 0 1 2 3
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py check --out /work/bench/12b
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

SEEDS = list(range(8))
OUTDOOR = {6, 7}


def phone_offset(seed: int) -> float:
    """The studio's sub-frame phone offset of session ``normal_<seed>`` (frames)."""
    return float(np.round(np.random.default_rng([12, seed]).uniform(-0.45, 0.45), 3))


def _synth(path: Path, **kw) -> None:
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    if (path / "ground_truth" / "ground_truth.json").is_file():
        return
    if path.exists():
        shutil.rmtree(path)
    t0 = time.perf_counter()
    synthesize(SynthConfig(**kw), path)
    print(json.dumps({"synth": path.name, "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


def _scene(path: Path) -> None:
    from embodmocap.scene import stage as scene_stage
    from embodmocap.scene.config import SceneConfig

    t0 = time.perf_counter()
    scene_stage.run(SceneConfig(), path)
    print(json.dumps({"scene": path.name, "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


def prepare(out: Path, seeds: list[int]) -> None:
    for s in seeds:
        _synth(out / f"normal_{s}", seed=s, preset="outdoor" if s in OUTDOOR else "indoor", seconds=6.0,
               scene_seconds=15.0, phone_offset_frames=phone_offset(s))
    base = dict(seed=0, preset="indoor", seconds=6.0, scene_seconds=15.0, phone_offset_frames=phone_offset(0))
    _synth(out / "fail_sep20", **base, view_separation_deg=20.0)
    _synth(out / "fail_away", **base, view2_away_fraction=0.5)
    _synth(out / "fail_scene", **base, view2_other_scene=True)
    _synth(out / "long_60", seed=100, preset="indoor", seconds=60.0, scene_seconds=15.0, phone_offset_frames=0.2)
    for s in seeds:
        _scene(out / f"normal_{s}")
    _scene(out / "long_60")
    for name in ("fail_sep20", "fail_away", "fail_scene"):
        src, dst = out / "normal_0" / "scenes", out / name / "scenes"
        if src.is_dir() and not dst.is_dir():
            shutil.copytree(src, dst)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=["prepare", "geosync", "subframe", "check"])
    ap.add_argument("--out", type=Path, default=Path("/work/bench/12b"))
    ap.add_argument("--seeds", type=int, nargs="*", default=SEEDS)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.mode == "prepare":
        prepare(args.out, args.seeds)
        return
    mod = sys.modules[__name__]
    rows = getattr(mod, f"run_{args.mode}")(args.out, args.seeds)
    (args.out / f"{args.mode}.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
