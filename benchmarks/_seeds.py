"""The seed loop shared by the per-seed benchmarks: arguments, one row per seed, failures kept."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Callable


def seed_arguments(description: str, default_out: str) -> argparse.Namespace:
    """--seeds, --preset, --seconds, --scene-seconds, --out."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--preset", default="indoor")
    ap.add_argument("--presets", nargs="+", default=None,
                    help="one studio preset per seed (see _studio.py: e.g. large, repetitive+light); overrides --preset")
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--scene-seconds", type=float, default=15.0)
    ap.add_argument("--out", type=Path, default=Path(default_out))
    return ap.parse_args()


def run_seeds(one_seed: Callable[..., dict], args: argparse.Namespace, name: str) -> list[dict]:
    """``one_seed(out, seed, preset, seconds, scene_seconds)`` for every seed; a failed seed becomes a
    row with ``error`` (reported, not hidden). Rows are printed as JSON lines and saved to
    ``OUT/<name>.json``; returns the rows that succeeded."""
    rows = []
    presets = getattr(args, "presets", None) or [args.preset] * len(args.seeds)
    if len(presets) != len(args.seeds):
        raise SystemExit(f"--presets needs one preset per seed ({len(args.seeds)}), got {len(presets)}")
    for seed, preset in zip(args.seeds, presets):
        try:
            row = one_seed(args.out, seed, preset, args.seconds, args.scene_seconds)
        except Exception as err:  # noqa: BLE001
            row = {"preset": preset, "seed": seed, "error": f"{type(err).__name__}: {err}"}
        rows.append(row)
        print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{name}.json").write_text(json.dumps(rows, indent=2))
    ok = [r for r in rows if "error" not in r]
    print(f"\n{len(ok)} of {len(rows)} seeds done")
    return ok
