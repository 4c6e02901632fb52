"""The sequence's edges (issue 29): Stage IV re-run in memory on processed sessions under config
variants, scored at the edges and overall against the truth.

For each session (Stages I-III done, e.g. ``embodmocap benchmark``'s or ``embodmocap synth``'s
after ``embodmocap run``) and each variant: the dual-view fit exactly as Stage IV makes it
(sub-frame sync, triangulation, body priors, fit, the per-frame quality: ``embodmocap.motion.solve``;
nothing is written), scored as ``embodmocap benchmark`` scores ``dual``: W-MPJPE at chunk 100
(fixed chunks, and with a chunk at every start: median and worst), the unaligned error of the first
five frames beside the median frame, WA-, PA-MPJPE, RTE, frames flagged suspect, frames with a joint
more than 15 cm off that no flag marks, and the Stage IV time (triangulation + fit) of each variant,
all in the same run. Variants run interleaved per session, so a load change on the machine hits
them alike.

    PYTHONPATH=src python benchmarks/bench_motion_edges.py '{"main": {}, "x": {"smplify.edge_hold": "all"}}' \\
        SESSION [SESSION ...] [--json OUT.json]

A variant is a JSON object of ``MotionConfig`` fields to change, dotted for nested configs
(``smplify.w_edge_vel``, ``temporal.max_run``, ``quality.suspect_m``). Each variant is fitted once
without the edge repair (row ``<name>, no edge repair``) and, when the variant turns it on
(``quality.repair_frames`` > 0; off by default), repaired as Stage IV repairs it (row ``<name>``). Times: the first row's is the
triangulation and the fit without the per-frame quality figures (what main runs); the second adds the
quality figures and the repair (what Stage IV runs now).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

KEYS = ("w_mpjpe_mm", "w_mpjpe_mm_all_starts_median", "w_mpjpe_mm_all_starts_worst", "first5_frame_mm",
        "last5_frame_mm", "median_frame_mm", "wa_mpjpe_mm", "pa_mpjpe_mm", "rte_pct", "world_mpjpe_mm",
        "invalid_frames", "suspect_frames", "wrong_frames", "wrong_unflagged_pct")


def motion_config(over: dict):
    """``MotionConfig`` with ``over``'s (dotted) fields changed."""
    from embodmocap.motion.config import MotionConfig

    cfg = MotionConfig()
    nested: dict[str, dict] = {}
    top = {}
    for k, v in over.items():
        if "." in k:
            a, b = k.split(".", 1)
            nested.setdefault(a, {})[b] = v
        else:
            top[k] = v
    for a, fields in nested.items():
        top[a] = replace(getattr(cfg, a), **fields)
    return replace(cfg, **top)


def main() -> None:
    from _stage4 import stage4_session

    from embodmocap.evaluate.benchmark import scored
    from embodmocap.io.stage_files import sequence_fps
    from embodmocap.motion import solve as s4

    args = sys.argv[1:]
    out_json = None
    if "--json" in args:
        i = args.index("--json")
        out_json = Path(args[i + 1])
        args = args[:i] + args[i + 2:]
    variants = json.loads(args[0])
    rows = []
    for s in args[1:]:
        ss = stage4_session(s)
        seq, model, truth, ctx, cams, kps, T, layout = ss.seq, ss.model, ss.truth, ss.ctx, ss.cams, ss.kps, ss.T, ss.layout
        sl = ctx.sl
        for name, over in variants.items():
            mcfg = motion_config(over)
            # The fit without the edge repair, then the repair on its result: the same steps as
            # fit_motion with the repair on (solve.repair_run_edges), and both rows from one fit.
            off = replace(mcfg, quality=replace(mcfg.quality, repair_frames=0))
            t0 = time.perf_counter()
            tri = s4.triangulate_views(off, cams, kps, T, seq)
            priors = ctx._priors(off.min_prior_fraction, T) if off.use_body_prior else {}
            fitted = s4.fit_motion(off, model, tri.file, cams, kps, T, sequence_fps(sl), priors, layout,
                                   ss.gender, label=seq)
            # The per-frame quality is new: main's own Stage IV time is the fit's without it.
            took = time.perf_counter() - t0 - fitted.figures["fit_seconds"]["quality"]
            out = [(f"{name}, no edge repair", fitted.params, fitted.quality, took)]
            if mcfg.quality.repair_frames > 0:
                t1 = time.perf_counter()
                params, n = s4.repair_run_edges(mcfg, model, fitted.params, fitted.valid, layout, cams, kps, tri.file, T,
                                                fitted.quality)
                quality = (s4.fit_quality(mcfg, model, params, layout, cams, kps, tri.file["keypoints2d"], tri.file, T)
                           if n else fitted.quality)
                out.append((name, params, quality, took + fitted.figures["fit_seconds"]["quality"]
                            + time.perf_counter() - t1))
            for label, params, quality, sec in out:
                e = scored(ctx.joints(params), np.arange(len(params)), truth, fitted.valid, quality.suspect)
                row = {"session": Path(s).name, "variant": label, "seconds": round(sec, 1), **{k: e.get(k) for k in KEYS}}
                rows.append(row)
                print("RESULT " + " ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    if out_json:
        out_json.write_text(json.dumps(rows, indent=1))
    print(table(rows))


def table(rows: list[dict]) -> str:
    """Per variant: the median and worst over sessions of every figure, the time ratio to the first."""
    names = list(dict.fromkeys(r["variant"] for r in rows))
    lines = ["| variant | figure | median | worst | per session |", "|---|---|---|---|---|"]
    base = {r["session"]: r["seconds"] for r in rows if r["variant"] == names[0]}
    for n in names:
        sel = [r for r in rows if r["variant"] == n]
        for k in KEYS + ("first5_over_median", "time_ratio"):
            if k == "first5_over_median":
                vals = [r["first5_frame_mm"] / r["median_frame_mm"] for r in sel]
            elif k == "time_ratio":
                vals = [r["seconds"] / base[r["session"]] for r in sel]
            else:
                vals = [float(r[k]) for r in sel]
            worst = max(vals) if k not in ("time_ratio",) else max(vals)
            lines.append(f"| {n} | {k} | {np.median(vals):.2f} | {worst:.2f} | " + ", ".join(f"{v:.1f}" for v in vals) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
