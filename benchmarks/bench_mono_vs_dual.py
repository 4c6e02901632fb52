"""Monocular vs dual view (issue 15): the capture-methods rows of ``embodmocap benchmark`` on
sessions that already went through every stage, without re-running the pipeline.

Per session (mirrored under ``--work`` with symlinked files, so the source sessions are never
written): ``dual`` (the session's Stage IV result), ``single_v1`` / ``single_v2`` (that view
calibrated and fitted alone), ``monocular`` (v1's prior through v1's calibrated cameras),
``mono_colmap`` and ``mono_vio`` (``embodmocap mono`` on v1: SfM per chunk + feet scale, or the
phone's VIO + depth; the body from the realistic prior), all scored by
``evaluate.benchmark`` on the frames the dual fit placed: W-/WA-MPJPE at chunks 100 / 500 / 1000
and RTE against the truth. Writes the rows (JSON) and the benchmark's Markdown table.

    OMP_NUM_THREADS=1 nice -n 19 python benchmarks/bench_mono_vs_dual.py \\
        /work/bench/11/sessions/hard_{0..9} --work /work/bench/15/s5/sessions --out /work/bench/15/s5/vsdual.json

``--redo-mono SESSIONS`` reruns only the mono rows of those sessions (e.g. after a change to mono).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main() -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_mono_colmap import mirror

    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate import benchmark as B
    from embodmocap.evaluate.session import motion_errors, sequence_truth
    from embodmocap.io.layout import VIEWS, SessionLayout
    from embodmocap.io.manifest import load_manifest

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", type=Path, nargs="+")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--no-single", action="store_true", help="skip the single-view fits (slow)")
    ap.add_argument("--redo-mono", action="store_true",
                    help="for the given sessions already in --out (matched by folder name), run only the mono rows "
                         "again (after a change to mono); the others are left as they are")
    args = ap.parse_args()
    rows = json.loads(args.out.read_text()) if args.out.is_file() else []
    rows = [r for r in rows if "error" not in r]  # sessions that could not be scored are tried again
    done = {r["session"] for r in rows}
    if args.redo_mono:
        names = {s.name for s in args.sessions}
        for r in rows:
            if r["session"] not in names:
                continue
            session = args.work / r["session"]
            lay = SessionLayout(session)
            man = load_manifest(lay.manifest)
            seq = next(iter(man.sequences))
            scene = man.sequences[seq].scene
            ctx = B._Context(lay, seq, scene, load_body_model(man.body_model))
            truth = sequence_truth(lay, scene, seq)
            _, frames = ctx.final_params()
            for name in B.MONO_METHODS:
                t1 = time.perf_counter()
                r["methods"][name] = B.mono_errors(session, seq, name.split("_", 1)[1], truth, frames, ctx.final_valid(), ctx)
                r["methods"][name]["mono_wall_s"] = round(time.perf_counter() - t1, 1)
            print(json.dumps({"session": r["session"], **{m: r["methods"][m].get("w_mpjpe_mm") for m in B.MONO_METHODS}}),
                  flush=True)
            args.out.write_text(json.dumps(rows, indent=1))
    for src in args.sessions:
        if src.name in done:
            continue
        if not (src / "sequences" / "seq0" / "smpl_world.npz").is_file():  # e.g. Stage IV being rerun there
            rows.append({"session": src.name, "seed": int(src.name.split("_")[-1]), "preset": "indoor",
                         "perception": "hard", "error": "no Stage IV result (smpl_world.npz) in the source session"})
            print(json.dumps(rows[-1]), flush=True)
            continue
        t0 = time.perf_counter()
        session = mirror(src, args.work / src.name)
        lay = SessionLayout(session)
        man = load_manifest(lay.manifest)
        seq = next(iter(man.sequences))
        scene = man.sequences[seq].scene
        model = load_body_model(man.body_model)
        truth = sequence_truth(lay, scene, seq)
        ctx = B._Context(lay, seq, scene, model)
        dual_params, frames = ctx.final_params()
        dual_valid = ctx.final_valid()
        methods = {"dual": motion_errors(ctx.joints(dual_params), frames, truth, dual_valid)}
        mono = ctx.prior_in_world("v1", ctx.cameras("v1"))
        methods["monocular"] = motion_errors(ctx.joints(mono), __import__("numpy").arange(len(mono)), truth,
                                             B.same_frames(frames, dual_valid, len(mono)))
        if not args.no_single:
            for v in VIEWS:
                try:
                    params = ctx.fit(single_view=v, cameras={v: ctx.single_view_cameras(v)})
                    methods[f"single_{v}"] = motion_errors(ctx.joints(params), __import__("numpy").arange(len(params)),
                                                           truth, B.same_frames(frames, dual_valid, len(params)))
                except Exception as err:  # noqa: BLE001
                    methods[f"single_{v}"] = {"error": f"{type(err).__name__}: {err}"}
        for name in B.MONO_METHODS:
            t1 = time.perf_counter()
            methods[name] = B.mono_errors(session, seq, name.split("_", 1)[1], truth, frames, dual_valid, ctx)
            methods[name]["mono_wall_s"] = round(time.perf_counter() - t1, 1)
        row = {"session": src.name, "seed": int(src.name.split("_")[-1]), "preset": "indoor", "perception": "hard",
               "methods": methods, "seconds": round(time.perf_counter() - t0, 1)}
        rows.append(row)
        print(json.dumps({"session": src.name, **{m: {k: v.get(k) for k in ("w_mpjpe_mm", "w_mpjpe_mm_c1000", "rte_pct",
                                                                            "error")} for m, v in methods.items()}}),
              flush=True)
        args.out.write_text(json.dumps(rows, indent=1))
    ok = [r for r in rows if "error" not in r
          and all("error" not in r["methods"].get(m, {}) for m in B.CAPTURE_METHODS)]
    md = B.summary({"rows": ok}) if ok else ""
    args.out.with_suffix(".md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
