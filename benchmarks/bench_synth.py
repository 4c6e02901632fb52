"""Benchmark: how long the synthetic studio takes to write a 10 s two-view session.

Target (issue 2): a 10 s two-view session at default resolution (640x480 RGB, 256x192 depth)
generates in under 2 minutes on this machine's 2 cores. Each run is a separate process so that
its peak resident memory (ru_maxrss of the child) is measured alone.

    .venv/bin/python benchmarks/bench_synth.py [--seeds 0 1] [--presets indoor outdoor] [--out bench_out]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from _child import run_cli


def run_one(out: Path, seed: int, preset: str, seconds: float) -> dict:
    if out.exists():
        shutil.rmtree(out)
    wall, peak_mb = run_cli("synth", str(out), "--seed", str(seed), "--preset", preset, "--seconds", str(seconds))
    info = json.loads((out / "ground_truth" / "ground_truth.json").read_text())
    size_mb = sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) / 1e6
    return {
        "seed": seed, "preset": preset, "seconds": seconds, "wall_s": round(wall, 1),
        "peak_rss_mb": peak_mb,
        "motion_frames": info["motion_frames"], "size_mb": round(size_mb, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--presets", nargs="+", default=["indoor", "outdoor"])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--out", type=Path, default=Path("bench_out"))
    args = ap.parse_args()
    rows = []
    for preset in args.presets:
        for seed in args.seeds:
            row = run_one(args.out / f"synth_{preset}_{seed}", seed, preset, args.seconds)
            rows.append(row)
            print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_synth.json").write_text(json.dumps(rows, indent=2))
    print("\n| preset | seed | seconds | wall (s) | peak RSS (MB) | output (MB) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['preset']} | {r['seed']} | {r['seconds']} | {r['wall_s']} | {r['peak_rss_mb']} | {r['size_mb']} |")


if __name__ == "__main__":
    main()
