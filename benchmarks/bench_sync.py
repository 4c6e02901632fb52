"""Benchmark: automatic laser-dot sync against the synthetic studio's ground truth.

Target (issue 4): the sync frame is found exactly on at least 95% of views over 20 synthetic seeds
(10 indoor, 10 outdoor), and within 1 frame on all. Sessions are short (1.5 s after the event, a
1 s scene capture that is not used) at the default resolution (640x480 RGB).

    .venv/bin/python benchmarks/bench_sync.py [--seeds 0 1 ... 9] [--presets indoor outdoor]
        [--out bench_out/sync] [--json bench_out/sync.json] [--keep]

Prints a per-view table, the fraction exact and the max abs error, then the JSON summary.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from embodmocap.io.captures import open_capture
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.sequence.sync import SyncConfig, detect_laser_event
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize


def run_seed(root: Path, seed: int, preset: str, keep: bool) -> list[dict]:
    out = root / f"{preset}_{seed}"
    if out.exists():
        shutil.rmtree(out)
    synthesize(SynthConfig(seed=seed, preset=preset, seconds=1.5, scene_seconds=1.0), out)
    truth = json.loads((out / "ground_truth" / "ground_truth.json").read_text())["sync_frames"]
    lay = SessionLayout(out)
    rows = []
    for v in VIEWS:
        cap = open_capture(lay.view_capture("seq0", v))
        t0 = time.perf_counter()
        ev = detect_laser_event(cap, SyncConfig())
        took = time.perf_counter() - t0
        found = None if ev is None else ev.frame
        rows.append({
            "preset": preset, "seed": seed, "view": v, "truth": int(truth[v]), "found": found,
            "error": None if found is None else found - int(truth[v]),
            "confidence": None if ev is None else ev.confidence, "frames": cap.num_frames,
            "detect_s": round(took, 2),
        })
    if not keep:
        shutil.rmtree(out)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--presets", nargs="+", default=["indoor", "outdoor"])
    ap.add_argument("--out", type=Path, default=Path("bench_out/sync"))
    ap.add_argument("--json", type=Path, default=None, help="also write the summary here")
    ap.add_argument("--keep", action="store_true", help="keep the synthetic sessions")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    t0 = time.perf_counter()
    print(f"{'preset':8} {'seed':>4} {'view':4} {'truth':>5} {'found':>5} {'err':>4} {'conf':>5} {'detect_s':>8}")
    for preset in args.presets:
        for seed in args.seeds:
            for r in run_seed(args.out, seed, preset, args.keep):
                rows.append(r)
                err = "-" if r["error"] is None else str(r["error"])
                conf = "-" if r["confidence"] is None else f"{r['confidence']:.2f}"
                print(f"{r['preset']:8} {r['seed']:>4} {r['view']:4} {r['truth']:>5} {str(r['found']):>5} "
                      f"{err:>4} {conf:>5} {r['detect_s']:>8.2f}", flush=True)
    errs = [abs(r["error"]) for r in rows if r["error"] is not None]
    missed = sum(r["error"] is None for r in rows)
    summary = {
        "views": len(rows), "exact": sum(e == 0 for e in errs), "missed": missed,
        "fraction_exact": round(sum(e == 0 for e in errs) / max(len(rows), 1), 4),
        "max_abs_error": None if missed else max(errs, default=0),
        "within_1_frame_all": missed == 0 and all(e <= 1 for e in errs),
        "mean_detect_s": round(sum(r["detect_s"] for r in rows) / max(len(rows), 1), 3),
        "wall_s": round(time.perf_counter() - t0, 1), "rows": rows,
    }
    print(f"exact on {summary['exact']}/{summary['views']} views ({100 * summary['fraction_exact']:.1f}%), "
          f"max abs error {summary['max_abs_error']} frames, missed {missed}")
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    ok = summary["fraction_exact"] >= 0.95 and summary["within_1_frame_all"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
