"""Benchmark Stage IV (`embodmocap motion`) against ground truth over synthetic seeds.

For each seed: synthesise a session (or reuse one in OUT), run Stages I-III (resumed: skipped when
already done, e.g. by bench_calibrate.py into the same OUT), then Stage IV (timed, forced), and
compare the world joints with the truth in Stage I's world: W-MPJPE and WA-MPJPE at chunk sizes
100, 500 and 1000 (GVHMR's definitions, :mod:`embodmocap.evaluate.metrics`), PA-MPJPE and RTE.

Targets (issue 6, dual view, default noise): W-MPJPE <= 60 mm, WA-MPJPE <= 45 mm, RTE <= 1 %.

    .venv/bin/python benchmarks/bench_motion.py --seeds 0 1 2 3 4 5 6 7 8 9 --out /tmp/bench_calib

Issue 11 (Stage IV from keypoints alone): ``--perception hard`` synthesises the studio's hard
detector (``embodmocap synth --perception hard``: BODY_25 output, outliers, swaps, misses,
furniture occlusion), ``--priors none realistic`` fits each session with and without the
camera-space body prior (same sessions, same Stage I-III results), and ``--old-src DIR`` also
times and scores the Stage IV of another source tree (e.g. ``git archive 312dde1 src | tar -x -C
DIR``) on the same sessions, in a subprocess, for a same-machine speed ratio. Targets (no prior,
hard perception): W-MPJPE <= 45 mm, PA-MPJPE <= 35 mm, RTE <= 1.5 %; no prior / realistic prior
W-MPJPE <= 1.3; median fit / triangulation keypoint error <= 1.0.

    .venv/bin/python benchmarks/bench_motion.py --perception hard --priors none realistic \
        --old-src /tmp/old --seeds 0 1 2 3 4 5 6 7 8 9 --out /tmp/bench_motion_hard
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from _seeds import run_seeds, seed_arguments

KEYS = ("w_mpjpe_mm", "wa_mpjpe_mm", "w_mpjpe_mm_c500", "wa_mpjpe_mm_c500", "w_mpjpe_mm_c1000",
        "wa_mpjpe_mm_c1000", "pa_mpjpe_mm", "rte_pct")
KP_KEYS = ("kp3d_triangulation_err_mm", "kp3d_fit_err_mm", "fit_vs_triangulation", "invalid_frames")

_OLD = """
import sys, time
from pathlib import Path
from embodmocap.motion import stage as stage4
t0 = time.perf_counter()
stage4.run(stage4.MotionConfig(use_body_prior=sys.argv[2] == '1'), Path(sys.argv[1]), force=True)
print(time.perf_counter() - t0)
"""


def _stage4(session: Path, prior: str, old_src: Path | None) -> tuple[float, dict]:
    """Stage IV (forced) with or without the body prior, timed; then its errors against the truth."""
    import os
    import subprocess
    import sys

    from embodmocap.evaluate.session import sequence_errors
    from embodmocap.io.layout import SessionLayout
    from embodmocap.motion import stage as stage4

    if old_src is None:
        t0 = time.perf_counter()
        stage4.run(stage4.MotionConfig(use_body_prior=prior != "none"), session, force=True)
        wall = time.perf_counter() - t0
    else:
        env = dict(os.environ, PYTHONPATH=str(old_src))
        res = subprocess.run([sys.executable, "-c", _OLD, str(session), "1" if prior != "none" else "0"], env=env,
                             capture_output=True, text=True, check=True)
        wall = float(res.stdout.strip().splitlines()[-1])
    errs = sequence_errors(SessionLayout(session), "scene0", "seq0")
    return wall, errs


def one_seed_variants(root: Path, seed: int, preset: str, seconds: float, scene_seconds: float, perception: str,
                      priors: list[str], old_src: Path | None) -> dict:
    """Issue 11: one session (prepared once), Stage IV per prior setting (and the old code's)."""
    from embodmocap.calibrate import stage as stage3
    from embodmocap.scene import stage as stage1
    from embodmocap.scene.config import SceneConfig
    from embodmocap.sequence import stage as stage2
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = root / f"{perception}_{seed}"
    if not (session / "ground_truth" / "ground_truth.json").is_file():
        synthesize(SynthConfig(seed=seed, preset=preset, seconds=seconds, scene_seconds=scene_seconds,
                               perception=perception), session)
    stage1.run(SceneConfig(), session)
    stage2.run(SequenceConfig(), session)
    stage3.run(stage3.CalibrateConfig(), session)
    row: dict = {"preset": preset, "seed": seed, "perception": perception}
    for prior in priors:
        for code, src in (("old", old_src), ("new", None)) if old_src else (("new", None),):
            wall, errs = _stage4(session, prior, src)
            row[f"{code}_{prior}"] = {"motion_s": round(wall, 2), **{k: errs.get(k) for k in KEYS + KP_KEYS}}
    return row


def one_seed(root: Path, seed: int, preset: str, seconds: float, scene_seconds: float) -> dict:
    from embodmocap.calibrate import stage as stage3
    from embodmocap.evaluate.session import sequence_errors
    from embodmocap.io.layout import SessionLayout
    from embodmocap.motion import stage as stage4
    from embodmocap.scene import stage as stage1
    from embodmocap.scene.config import SceneConfig
    from embodmocap.sequence import stage as stage2
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = root / f"{preset}_{seed}"
    if not (session / "ground_truth" / "ground_truth.json").is_file():
        synthesize(SynthConfig(seed=seed, preset=preset, seconds=seconds, scene_seconds=scene_seconds), session)
    stage1.run(SceneConfig(), session)
    stage2.run(SequenceConfig(), session)
    stage3.run(stage3.CalibrateConfig(), session)
    t0 = time.perf_counter()
    out = stage4.run(stage4.MotionConfig(), session, force=True)
    wall = time.perf_counter() - t0
    errs = sequence_errors(SessionLayout(session), "scene0", "seq0")
    row = {"preset": preset, "seed": seed, "frames": int(np.load(out.layout.joints_world)["joints"].shape[0]),
           "motion_s": round(wall, 1), **{k: errs[k] for k in KEYS}}
    row["reproj_px"] = {v: out.figures.get(f"{v}_reproj_px") for v in ("v1", "v2")}
    return row


def _variants_table(ok: list[dict], priors: list[str], old: bool) -> None:
    print("| variant | seeds | W-MPJPE | WA-MPJPE | PA-MPJPE | RTE % | fit / triangulation | kp fit mm | kp tri mm | "
          "invalid frames | Stage IV s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for code in ("old", "new") if old else ("new",):
        for prior in priors:
            rows = [r[f"{code}_{prior}"] for r in ok]
            med = lambda k: float(np.median([x[k] for x in rows if x.get(k) is not None] or [np.nan]))  # noqa: E731
            print(f"| {code} prior={prior} | {len(rows)} | {med('w_mpjpe_mm'):.1f} | {med('wa_mpjpe_mm'):.1f} | "
                  f"{med('pa_mpjpe_mm'):.1f} | {med('rte_pct'):.2f} | {med('fit_vs_triangulation'):.3f} | "
                  f"{med('kp3d_fit_err_mm'):.1f} | {med('kp3d_triangulation_err_mm'):.1f} | "
                  f"{sum(x.get('invalid_frames') or 0 for x in rows)} | {sum(x['motion_s'] for x in rows):.1f} |")
    if "none" in priors and "realistic" in priors:
        ratio = [r["new_none"]["w_mpjpe_mm"] / r["new_realistic"]["w_mpjpe_mm"] for r in ok]
        print(f"\nno prior / realistic prior W-MPJPE (new), median over sessions: {np.median(ratio):.3f}")
    if old:
        for prior in priors:
            t_old = sum(r[f"old_{prior}"]["motion_s"] for r in ok)
            t_new = sum(r[f"new_{prior}"]["motion_s"] for r in ok)
            print(f"Stage IV time new / old, prior={prior}: {t_new / t_old:.2f} ({t_new:.1f} s / {t_old:.1f} s)")


def main() -> None:
    import argparse
    import sys

    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--perception", default=None, choices=("clean", "hard"))
    extra.add_argument("--priors", nargs="+", default=["none", "realistic"])
    extra.add_argument("--old-src", type=Path, default=None)
    ns, rest = extra.parse_known_args()
    sys.argv = sys.argv[:1] + rest
    args = seed_arguments(__doc__.splitlines()[0], "bench_out/calibrate")
    if ns.perception:
        def fn(root, seed, preset, seconds, scene_seconds):
            return one_seed_variants(root, seed, preset, seconds, scene_seconds, ns.perception, ns.priors, ns.old_src)

        ok = run_seeds(fn, args, f"bench_motion_{ns.perception}")
        _variants_table(ok, ns.priors, ns.old_src is not None)
        return
    ok = run_seeds(one_seed, args, "bench_motion")
    print("| metric | median | p95 | max |")
    print("|---|---|---|---|")
    for k in KEYS:
        a = np.array([r[k] for r in ok], dtype=float)
        if len(a):
            print(f"| {k} | {np.median(a):.2f} | {np.percentile(a, 95):.2f} | {a.max():.2f} |")


if __name__ == "__main__":
    main()
