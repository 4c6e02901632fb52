"""Metric scale cues of ``embodmocap mono`` on the same precomputed (Pi3-like, noisy) inputs:
``body`` (body depth / point-map depth inside the person mask) vs ``feet`` (the feet in contact
on the scene's floor plane), with the realistic body prior. Per seed: a copy of the studio session
reused by ``bench_mono.py`` (``--work``/mono_s<seed>_<seconds>s), the same noisy inputs as its
``noisy`` row (``write_mono_inputs``, seed 100 + seed), ``mono`` once per cue; the scale error is
``v1_mono_scale_err_pct`` against the ground truth. ``--cues combined`` runs ``mono`` once with
``--scale.cue combined`` (both cues, inverse-variance weighted by their block standard errors) and
also reports each cue's own signed scale error (same stitch: the cue's scale over the combined one
times the combined run's signed similarity scale to the true camera centres).

    OMP_NUM_THREADS=1 nice -n 19 python benchmarks/bench_mono_scale_cues.py --seeds 0 1 2 --seconds 20 \\
        --out /work/bench/15/s5/scale_cues_20s.json
    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/bench_mono_scale_cues.py --seeds 0 1 2 --seconds 20 \\
        --cues combined --copies /work/bench/15/s5b --out /work/bench/15/s5b/combined_20s.json
    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/bench_mono_scale_cues.py --seeds 0 1 2 --seconds 20 --cues feet \\
        --feet-max-speed 0.5 1.0 --feet-max-height 0.08 0.15 --copies /work/bench/15/s5b --out /work/bench/15/s5b/feet_20s.json

``--prior hard`` gives the body the studio's ``hard`` prior ("realistic+shape bias": a per-session
shape error, height ~3 % off, with a size-consistent depth) on the same scene inputs (copies
``cues_hard_s<seed>_<seconds>s``; only ``mono_human.npz`` differs, written with the same seed).
``--human-depth model keypoints`` runs ``mono`` with each ``--human-depth`` (``model`` = the code
before the keypoint refinement); ``--height oracle`` adds rows that give ``--scale.height-m`` the
studio's TRUE stature (a simulated oracle: the row's name says so).
"""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path


def main() -> None:
    from embodmocap.io.layout import SessionLayout
    from embodmocap.mono import stage
    from embodmocap.mono.config import MonoConfig
    from embodmocap.evaluate.mono import mono_metrics
    from embodmocap.synth.mono_inputs import PRIOR_PRESETS, MonoInputConfig, write_mono_inputs

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--work", type=Path, default=Path("/work/bench/15"))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cues", nargs="+", default=["body", "feet"], choices=["body", "feet", "auto", "combined"])
    ap.add_argument("--copies", type=Path, default=None, help="folder of the session copies (default WORK/s5)")
    ap.add_argument("--feet-max-speed", type=float, nargs="+", default=[None],
                    help="feet contact speed bound(s) to try (m/s; default: FeetScaleConfig's)")
    ap.add_argument("--feet-max-height", type=float, nargs="+", default=[None],
                    help="feet contact height bound(s) to try (m; default: FeetScaleConfig's)")
    ap.add_argument("--prior", choices=["realistic", "hard"], default="realistic",
                    help="the studio's body-prior preset (synth.mono_inputs.PRIOR_PRESETS)")
    ap.add_argument("--human-depth", nargs="+", default=[None], choices=[None, "model", "keypoints"],
                    help="MonoConfig.human_depth value(s) to run (default: the config's default)")
    ap.add_argument("--height", nargs="+", default=["none"], choices=["none", "oracle"],
                    help="oracle: also give --scale.height-m the studio's true stature (simulated oracle)")
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        base = args.work / f"mono_s{seed}_{args.seconds:g}s"
        tag = "cues" if args.prior == "realistic" else f"cues_{args.prior}"
        work = (args.copies or args.work / "s5") / f"{tag}_s{seed}_{args.seconds:g}s"
        if not (base / "sequences").is_dir():  # a new seed: the studio session as bench_mono.py makes it
            from embodmocap.sequence import stage as sequence_stage
            from embodmocap.sequence.config import SequenceConfig
            from embodmocap.synth.config import SynthConfig
            from embodmocap.synth.studio import synthesize

            synthesize(SynthConfig(seed=seed, seconds=args.seconds, scene_seconds=1.0, width=320, height=240,
                                   depth_width=128, depth_height=96), base)
            sequence_stage.run(SequenceConfig(), base)
        if not (work / "perception" / "seq0" / "v1" / "mono_human.npz").is_file():
            if work.exists():
                shutil.rmtree(work)
            shutil.copytree(base, work, symlinks=True, ignore=shutil.ignore_patterns("mono"))
            write_mono_inputs(work, cfg=MonoInputConfig(prior=PRIOR_PRESETS[args.prior]), seed=100 + seed)
            (work / "mono_inputs_prior.txt").write_text(args.prior)
        marker = work / "mono_inputs_prior.txt"
        if (marker.read_text() if marker.is_file() else "realistic") != args.prior:
            # a copy of the realistic inputs: the same scene chunks, the body rewritten with this prior
            write_mono_inputs(work, cfg=MonoInputConfig(prior=PRIOR_PRESETS[args.prior]), seed=100 + seed,
                              human_only=True)
            marker.write_text(args.prior)
        variants = [(cue, v, h, d, o) for cue in args.cues for v in args.feet_max_speed for h in args.feet_max_height
                    for d in args.human_depth for o in args.height]
        for cue, max_speed, max_height, depth, height in variants:
            cfg = MonoConfig(scene_model="precomputed", human_model="precomputed")
            feet = cfg.scale.feet
            feet = replace(feet, max_speed=feet.max_speed if max_speed is None else max_speed,
                           max_height=feet.max_height if max_height is None else max_height)
            scale = replace(cfg.scale, cue=cue, feet=feet)
            if height == "oracle":
                scale = replace(scale, height_m=_true_stature(work))
            if depth is not None:
                cfg = replace(cfg, human_depth=depth)
            out = stage.run(replace(cfg, scale=scale), work, force=True)
            mm = mono_metrics(SessionLayout(work), "scene0", "seq0")
            name = f"{args.prior} prior, human depth {depth or 'default'}" + (
                ", oracle height (true stature)" if height == "oracle" else "")
            row = {"row": name, "prior": args.prior, "human_depth": depth, "height": height,
                   "seed": seed, "seconds": args.seconds, "cue": cue, "feet_max_speed": feet.max_speed,
                   "feet_max_height": feet.max_height, **out.figures["metric_scale"]["0"],
                   "human_depth_stats": out.figures.get("human_depth"),
                   "scale_err_pct": mm["v1_mono_scale_err_pct"], "camera_err_cm": mm["v1_mono_camera_err_cm"],
                   "w_mpjpe_mm": mm["v1_mono_w_mpjpe_mm"], "segments": out.figures["segments"]}
            if cue == "combined" and out.figures["segments"] == 1:
                row.update(_per_cue_errors(work, out, row))
            rows.append(row)
            print(json.dumps(row), flush=True)
    args.out.write_text(json.dumps(rows, indent=1))


def _true_stature(work: Path) -> float:
    """The studio performer's true rest-pose height (ground truth: only for the oracle rows)."""
    import numpy as np

    from embodmocap.body.model import load_body_model
    from embodmocap.body.stature import stature

    betas = np.load(work / "ground_truth" / "seq_seq0.npz")["betas"]
    return float(stature(load_body_model(work / "body_model.npz"), betas))


def _per_cue_errors(work: Path, out, row: dict) -> dict:
    """Signed scale errors (%) of the combined run and of each cue alone on the same stitch: ``s - 1``
    with ``s`` the similarity scale from the mono camera centres onto the true ones (so that
    ``|s - 1|`` is ``v1_mono_scale_err_pct``; positive: the mono world is too small)."""
    import numpy as np

    from embodmocap.evaluate.metrics import umeyama
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.mono.files import read_mono_cameras

    mc = read_mono_cameras(out.layout.cameras_world)
    ref = sequence_truth(__import__("embodmocap.io.layout", fromlist=["SessionLayout"]).SessionLayout(work),
                         "scene0", "seq0").T_world_cam["v1"]
    n = min(len(ref), len(mc["T_world_cam"]))
    ok = np.isfinite(mc["metric_scale"][:n])
    s, _, _ = umeyama(mc["T_world_cam"][:n, :3, 3][ok], ref[:n, :3, 3][ok])
    extra = {"signed_err_pct": round(100 * (float(s) - 1), 3)}
    for cue in ("body", "feet"):
        c = row.get(cue)
        if isinstance(c, dict) and np.isfinite(c.get("scale", np.nan)):
            # the camera centres scale with m, so the similarity onto the truth scales with 1 / m
            extra[f"{cue}_signed_err_pct"] = round(100 * (float(s) * row["scale"] / c["scale"] - 1), 3)
            extra[f"{cue}_se_pct"] = round(100 * c.get("se_rel", np.nan), 3)
    return extra


if __name__ == "__main__":
    main()
