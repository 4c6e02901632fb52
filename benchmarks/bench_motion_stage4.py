"""Issue 11: Stage IV alone, old and new code, on prepared hard-perception sessions.

Synthesising a hard session and running Stages I-III takes minutes; Stage IV seconds. This script
takes sessions prepared once (``SESSIONS/<perception>_<seed>`` with Stages I-III done, e.g. by
``bench_motion.py --perception hard`` or ``embodmocap synth ... && embodmocap run ...`` up to
calibrate), never modifies them, and in a work folder per session (hard links to the inputs, a
copy of ``sequences/``) runs Stage IV with each body-prior setting and each code version, each in
its own subprocess (same machine, same moment: the time ratio is fair), then scores every result
with the new evaluation (:func:`embodmocap.evaluate.session.sequence_errors`).

Prior settings: ``none`` (keypoints only), ``realistic`` (the session's own prior, the studio's
default regressor noise), ``poor`` (a prior drawn again from the session's true motion with the
studio's ``POOR_PRIOR_NOISE``: depth 20 %, 15 degrees per joint, seeded per seed and view; see
:func:`write_poor_prior`).

    .venv/bin/python benchmarks/bench_motion_stage4.py --sessions /work/bench/11/sessions \
        --seeds 0 1 2 3 4 5 6 7 8 9 --priors none realistic poor --old-src /tmp/old/src \
        --work /tmp/bench_s4 --json /tmp/bench_s4/results.json

Targets (no prior, hard): W-MPJPE <= 45 mm, PA-MPJPE <= 35 mm, RTE <= 1.5 %; no prior / realistic
prior W-MPJPE <= 1.3; fit / triangulation keypoint error <= 1.0; Stage IV time <= 1.5x.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

KEYS = ("w_mpjpe_mm", "wa_mpjpe_mm", "pa_mpjpe_mm", "rte_pct", "kp3d_triangulation_err_mm", "kp3d_fit_err_mm",
        "fit_vs_triangulation", "invalid_frames", "w_mpjpe_mm_incl_invalid", "pa_mpjpe_mm_incl_invalid")

_RUN = """
import sys, time
from pathlib import Path
from embodmocap.motion import stage as stage4
t0 = time.perf_counter()
stage4.run(stage4.MotionConfig(use_body_prior=sys.argv[2] == '1'), Path(sys.argv[1]), force=True)
print(time.perf_counter() - t0)
"""


def work_copy(src: Path, dst: Path) -> Path:
    """``dst``: hard links to ``src``'s files, ``sequences/`` copied (Stage IV writes there)."""
    if not dst.exists():
        shutil.copytree(src, dst, copy_function=os.link, ignore=shutil.ignore_patterns("sequences"))
        shutil.copytree(src / "sequences", dst / "sequences")
    return dst


def write_poor_prior(session: Path, seed: int, seq: str = "seq0") -> str:
    """Replace the work copy's body priors by ones drawn from the truth with the studio's
    poor-regressor noise (one generator per seed and view). Sessions whose Stage II manifest
    records its outputs' fingerprints get the detector-side files (``perception/``, as the studio
    writes them) and Stage II re-slices them (its other steps are current: checked); older ones get
    the sliced ``sequences/<seq>/<view>/body_prior.npz`` written as Stage II's body-prior step
    writes it. Returns which of the two was done."""
    import json

    from embodmocap.body.model import load_body_model
    from embodmocap.io.body_prior import BodyPriorSeq, write_body_prior
    from embodmocap.io.layout import VIEWS, SessionLayout
    from embodmocap.sequence import stage as stage2
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth import perception
    from embodmocap.types import SmplParams

    lay = SessionLayout(session)
    g = np.load(lay.ground_truth.sequence(seq))
    body = load_body_model(None)
    steps = json.loads(lay.sequence(seq).manifest.read_text())["steps"]
    recorded = all("output_fingerprints" in steps.get(f"body_prior_{v}", {}) for v in VIEWS)
    for k, v in enumerate(VIEWS):
        T_scene_cam = g[f"{v}_T_scene_cam"]
        start = int(g[f"{v}_motion_start"])
        span = np.clip(np.arange(start, start + len(T_scene_cam)), 0, len(g["body_pose"]) - 1)
        params = SmplParams(g["betas"], g["global_orient"][span], g["body_pose"][span], g["transl"][span],
                            float(g["fps"]), "neutral")
        rng = np.random.default_rng([seed, 1100 + k])
        prior = perception.body_prior(params, T_scene_cam, body, rng, perception.POOR_PRIOR_NOISE)
        if recorded:
            path = lay.perception(seq, v).body_prior
            path.unlink()  # a hard link to the prepared session's file: never write through it
            write_body_prior(path, prior)
        else:
            vl = lay.sequence(seq).view(v)
            raw = np.load(vl.cameras)["raw_frames"].astype(np.int64)
            write_body_prior(vl.body_prior, BodyPriorSeq(prior.global_orient_cam[raw], prior.body_pose[raw],
                                                         prior.betas[raw], prior.transl_cam[raw], np.arange(len(raw))))
    if not recorded:
        return "sliced priors written"
    out = stage2.run(SequenceConfig(), session, seq)
    ran = [n for n in steps if n not in out.skipped]
    if any(not n.startswith("body_prior") for n in ran):
        raise RuntimeError(f"{session}: Stage II redid {ran}, not only the body priors")
    return f"Stage II re-sliced ({', '.join(ran)})"


def stage4(session: Path, prior: str, src: Path) -> tuple[float, dict]:
    from embodmocap.evaluate.session import sequence_errors
    from embodmocap.io.layout import SessionLayout

    env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    res = subprocess.run([sys.executable, "-c", _RUN, str(session), "0" if prior == "none" else "1"], env=env,
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"Stage IV failed on {session} ({src}):\n{res.stderr[-3000:]}")
    wall = float(res.stdout.strip().splitlines()[-1])
    return wall, sequence_errors(SessionLayout(session), "scene0", "seq0")


def table(rows: list[dict], codes: list[str], priors: list[str]) -> None:
    print("| seed | variant | W-MPJPE | WA-MPJPE | PA-MPJPE | RTE % | fit / tri | invalid | W-MPJPE incl. invalid | Stage IV s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        for c in codes:
            for p in priors:
                x = r.get(f"{c}_{p}")
                if x:
                    incl = x.get("w_mpjpe_mm_incl_invalid")
                    incl = f"{incl:.1f}" if incl is not None else ("-" if x["invalid_frames"] else f"{x['w_mpjpe_mm']:.1f}")
                    print(f"| {r['seed']} | {c}, prior {p} | {x['w_mpjpe_mm']:.1f} | {x['wa_mpjpe_mm']:.1f} | {x['pa_mpjpe_mm']:.1f} | "
                          f"{x['rte_pct']:.2f} | {x['fit_vs_triangulation']:.3f} | {x['invalid_frames']} | "
                          f"{incl} | {x['s']:.1f} |")
    print(f"\n**medians over {len(rows)} sessions**\n")
    print("| variant | W-MPJPE | WA-MPJPE | PA-MPJPE | RTE % | fit / tri | invalid frames (sum) | Stage IV s (sum) |")
    print("|---|---|---|---|---|---|---|---|")
    for c in codes:
        for p in priors:
            xs = [r[f"{c}_{p}"] for r in rows if r.get(f"{c}_{p}")]
            if not xs:
                continue
            med = lambda k: float(np.median([x[k] for x in xs]))  # noqa: E731
            print(f"| {c}, prior {p} | {med('w_mpjpe_mm'):.1f} | {med('wa_mpjpe_mm'):.1f} | {med('pa_mpjpe_mm'):.1f} | "
                  f"{med('rte_pct'):.2f} | {med('fit_vs_triangulation'):.3f} | {sum(x['invalid_frames'] for x in xs)} | "
                  f"{sum(x['s'] for x in xs):.1f} |")
    for c in codes:
        if all(r.get(f"{c}_none") and r.get(f"{c}_realistic") for r in rows):
            ratio = [r[f"{c}_none"]["w_mpjpe_mm"] / r[f"{c}_realistic"]["w_mpjpe_mm"] for r in rows]
            print(f"\n{c}: no prior / realistic prior W-MPJPE, median over sessions: {np.median(ratio):.2f} "
                  f"(per session: {', '.join(f'{x:.2f}' for x in ratio)})")
    if "old" in codes:
        for p in priors:
            t_old = sum(r[f"old_{p}"]["s"] for r in rows if r.get(f"old_{p}"))
            t_new = sum(r[f"new_{p}"]["s"] for r in rows if r.get(f"new_{p}"))
            if t_old:
                print(f"Stage IV time new / old, prior {p}: {t_new / t_old:.2f} ({t_new:.1f} s / {t_old:.1f} s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=Path, required=True, help="folder of prepared <perception>_<seed> sessions")
    ap.add_argument("--perception", default="hard")
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--priors", nargs="+", default=["none", "realistic"], choices=("none", "realistic", "poor"))
    ap.add_argument("--old-src", type=Path, default=None, help="another source tree's src/ to compare with")
    ap.add_argument("--old-priors", nargs="+", default=None, choices=("none", "realistic", "poor"),
                    help="prior settings the old code runs with (default: all of --priors)")
    ap.add_argument("--work", type=Path, required=True, help="work folder (copies of the sessions)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    new_src = Path(__file__).resolve().parents[1] / "src"
    sys.path.insert(0, str(new_src))  # the evaluation and the poor priors from this tree, whatever is installed
    codes = (["old"] if args.old_src else []) + ["new"]
    rows = []
    for seed in args.seeds:
        src = args.sessions / f"{args.perception}_{seed}"
        row: dict = {"seed": seed, "perception": args.perception}
        for prior in args.priors:
            dst = work_copy(src, args.work / (f"{src.name}_poor" if prior == "poor" else src.name))
            if prior == "poor" and not (dst / ".poor_prior").exists():
                how = write_poor_prior(dst, seed)
                (dst / ".poor_prior").write_text(f"body priors redrawn with POOR_PRIOR_NOISE: {how}\n")
            for code in codes:
                if code == "old" and args.old_priors is not None and prior not in args.old_priors:
                    continue
                wall, errs = stage4(dst, prior, args.old_src if code == "old" else new_src)
                row[f"{code}_{prior}"] = {"s": round(wall, 2), **{k: errs.get(k) for k in KEYS}}
                print(json.dumps({"seed": seed, "variant": f"{code}_{prior}", **row[f"{code}_{prior}"]}), flush=True)
        rows.append(row)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(rows, indent=1))
    table(rows, codes, args.priors)


if __name__ == "__main__":
    main()
