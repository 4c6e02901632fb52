"""Per-session view of ``embodmocap benchmark`` results (its ``benchmark.json`` files).

Prints, per perception setting, each session's W-MPJPE at chunk 1000 for every capture method
(as the 2026-11-23 per-session table in BENCHMARKS.md), the dual / better-single ratio of the means,
and, with ``--evaluate``, each session's per-stage figures from its ``evaluation.json`` (written by
``embodmocap evaluate SESSION``): sync error, Stage III view errors, 3D keypoint errors, Stage I mesh.

    python benchmarks/bench_pipeline_tables.py OUT/benchmark.json [OUT2/benchmark.json ...] [--evaluate]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

METHODS = ("monocular", "single_v1", "single_v2", "dual", "mono_colmap", "mono_vio")
_STAGE_KEYS = ("v1_sync_err_frames", "v2_sync_err_frames", "sync_subframe_err_frames", "v1_view_translation_err_cm",
               "v2_view_translation_err_cm", "v1_view_yaw_err_deg", "v2_view_yaw_err_deg",
               "kp3d_triangulation_err_mm", "kp3d_fit_err_mm", "invalid_frames")


def _session_name(row: dict) -> str:
    return f"{row['preset']}_{row['seed']}" + ("_hard" if row.get("perception") == "hard" else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+", type=Path)
    ap.add_argument("--evaluate", action="store_true", help="also print each session's evaluation.json figures")
    args = ap.parse_args()
    rows = [(path.parent, r) for path in args.results for r in json.loads(path.read_text())["rows"]]
    for perception in ("clean", "hard"):
        sel = [(d, r) for d, r in rows if r.get("perception", "clean") == perception and "error" not in r]
        if not sel:
            continue
        print(f"\n{perception}: W-MPJPE at chunk 1000 per session, mm (dual without prior last)\n")
        print("| seed | preset | " + " | ".join(METHODS) + " | dual, prior none | seconds |")
        print("|---|---|" + "---|" * (len(METHODS) + 2))
        for _, r in sel:
            vals = [r["methods"].get(m, {}).get("w_mpjpe_mm_c1000") for m in METHODS]
            nop = r.get("methods_no_prior", {}).get("dual", {}).get("w_mpjpe_mm_c1000")
            print(f"| {r['seed']} | {r['preset']} | " + " | ".join("-" if v is None else f"{v:.0f}" for v in [*vals, nop])
                  + f" | {r['seconds']:.0f} |")
        mean = {m: np.mean([r["methods"][m]["w_mpjpe_mm_c1000"] for _, r in sel]) for m in ("single_v1", "single_v2", "dual")}
        print(f"\nbetter single / dual, means at chunk 1000: {min(mean['single_v1'], mean['single_v2']) / mean['dual']:.2f}x; "
              f"per session (better single of that session / dual): " + ", ".join(
                  f"{min(r['methods']['single_v1']['w_mpjpe_mm_c1000'], r['methods']['single_v2']['w_mpjpe_mm_c1000']) / r['methods']['dual']['w_mpjpe_mm_c1000']:.1f}"
                  for _, r in sel))
        if args.evaluate:
            print(f"\n{perception}: per-stage figures from each session's evaluation.json\n")
            print("| session | mesh acc cm | mesh compl % | " + " | ".join(_STAGE_KEYS) + " |")
            print("|---|---|---|" + "---|" * len(_STAGE_KEYS))
            for d, r in sel:
                ev_path = d / _session_name(r) / "evaluation.json"
                if not ev_path.is_file():
                    print(f"| {_session_name(r)} | (no evaluation.json) |")
                    continue
                ev = json.loads(ev_path.read_text())
                scene = next(iter(ev["scene"].values()), {})
                seq = next(iter(ev["sequences"].values()), {})
                print(f"| {_session_name(r)} | {scene.get('mesh_accuracy_cm', '-')} | {scene.get('mesh_completeness_pct', '-')} | "
                      + " | ".join(str(seq.get(k, "-")) for k in _STAGE_KEYS) + " |")


if __name__ == "__main__":
    main()
