"""Stage IV re-run in memory on processed sessions under MotionConfig variants, as Stage IV runs it
(Stage I floor term, body priors, sub-frame sync), scored like ``evaluate``; sessions in parallel.

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_motion_yaw.py '{"main": {}, "x": {"smplify.w_joint_acc": 45}}' SESSION ...

NPROC (default 2) worker processes; SAVE=DIR writes each fit's joints and parameters. Prints one
RESULT line per session and variant, then a table of the medians (issue 29: W c100, the anchors)."""
import json
import os
import sys
import time
from pathlib import Path
from multiprocessing import Pool
import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parent))
KEYS = ("w_mpjpe_mm", "w_mpjpe_mm_all_starts_median", "w_mpjpe_mm_all_starts_worst", "first5_frame_mm",
        "median_frame_mm", "wa_mpjpe_mm", "pa_mpjpe_mm", "rte_pct", "world_mpjpe_mm", "wrong_unflagged_pct")

def run(job):
    s, variants = job
    import torch; torch.set_num_threads(1)
    from bench_motion_edges import motion_config
    from _stage4 import stage4_session
    from embodmocap.evaluate.benchmark import scored
    from embodmocap.io.stage_files import sequence_fps
    from embodmocap.motion import solve as s4
    from embodmocap.motion.floor import scene_floor_z
    from embodmocap.motion.stage import _depth_tests, quality_depth, scene_mesh
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    ss = stage4_session(s)
    ctx = ss.ctx
    lay = SessionLayout(Path(s)); man = load_manifest(lay.manifest)
    scene = man.sequences[ss.seq].scene
    rows = []
    for name, over in variants.items():
        mcfg = motion_config(over)
        t0 = time.process_time()
        tri = s4.triangulate_views(mcfg, ss.cams, ss.kps, ss.T, ss.seq)
        priors = ctx._priors(mcfg.min_prior_fraction, ss.T) if mcfg.use_body_prior else {}
        floor = scene_floor_z(scene_mesh(mcfg, lay, scene), mcfg.smplify.floor_max_tilt_deg, ss.seq)
        fit = s4.fit_motion(mcfg, ss.model, tri.file, ss.cams, ss.kps, ss.T, sequence_fps(ctx.sl), priors, ss.layout,
                            ss.gender, label=ss.seq, floor_z=floor,
                            # as Stage IV: the views' depth for the one-view joints and the quality's tests
                            depth=quality_depth(ctx.sl, list(ss.cams)) if _depth_tests(mcfg) else None)
        took = time.process_time() - t0
        J = ctx.joints(fit.params)
        e = scored(J, np.arange(len(fit.params)), ss.truth, fit.valid, fit.quality.suspect)
        row = {"session": Path(s).name, "variant": name, "cpu_s": round(took, 1), **{k: e.get(k) for k in KEYS}}
        out = os.environ.get("SAVE")
        if out:
            np.savez(f"{out}/{Path(s).name}__{name}.npz", joints=J, valid=fit.valid, go=fit.params.global_orient,
                     pose=fit.params.body_pose, transl=fit.params.transl)
        print("RESULT " + json.dumps(row), flush=True)
        rows.append(row)
    return rows

if __name__ == "__main__":
    variants = json.loads(sys.argv[1])
    sessions = sys.argv[2:]
    with Pool(int(os.environ.get("NPROC", "2"))) as p:
        allrows = sum(p.map(run, [(s, variants) for s in sessions], chunksize=1), [])
    names = list(variants)
    print("| variant | W c100 per seed | W med | W worst | allst med | WA med | PA med | RTE med | first5 med | cpu |")
    for n in names:
        r = [x for x in allrows if x["variant"] == n]
        f = lambda k: np.median([x[k] for x in r])
        print(f"| {n} | " + " ".join(f"{x['w_mpjpe_mm']:.1f}" for x in r) + f" | {f('w_mpjpe_mm'):.1f} | {max(x['w_mpjpe_mm'] for x in r):.1f} | {f('w_mpjpe_mm_all_starts_median'):.1f} | {f('wa_mpjpe_mm'):.2f} | {f('pa_mpjpe_mm'):.2f} | {f('rte_pct'):.3f} | {f('first5_frame_mm'):.1f} | {sum(x['cpu_s'] for x in r):.0f} |")
