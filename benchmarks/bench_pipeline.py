"""Speed of every stage on one synthetic session (default 60 s of two-view capture).

Synthesises the session (indoor, 640x480, 15 s scene capture) unless OUT already holds it, then runs
each stage from scratch in its own child process (`embodmocap <stage> SESSION --force`): wall time,
CPU time (user + system of all the child's threads), peak RSS of that process, frames/s (sequence
frames per second of wall time, per view where the stage works per view), and the split of each
stage into its steps from the stage manifests.

With ``--old-src OTHER/src`` the same is done for another checkout (e.g. main before a change),
interleaved stage by stage on two copies of the session (old then new for one stage, new then old
for the next, so that a load spike on a shared machine does not fall on one side only); the table
then has both rows per stage and the new / old ratios, and the evaluation's accuracy figures of both.
``--device cuda`` passes ``--device`` to the new code's Stage IV (the old code runs on its default).
With ``--old-src`` and every stage, the whole pipeline is then timed once more as the user runs it,
``embodmocap run SESSION`` on two more fresh copies (old and new, in the order opposite to the last
stage's), and the summary gives the ratio of that run's wall time, CPU and peak RSS (the issue's
figure; ``--no-whole-run`` skips it), the ratios of each stage, and the accuracy figures of both
codes side by side (W-, WA-, PA-MPJPE, W-MPJPE over 100-frame chunks, RTE, camera errors).
``--stages scene`` (or any subset, in pipeline order) times only those stages (each needs its
predecessors' outputs: ``scene`` alone needs nothing); ``--stages run`` only the whole run.

The whole run's memory is the sum over the processes alive at one moment (``embodmocap run`` with
``--workers 2`` runs stages in worker processes): its rows give the run process's own peak and the
peak of the sum of the resident memory (RSS; and Pss, shared pages counted once) of the process
and every process below it, sampled every 0.2 s (``_child.run_cli_tree``). ``--new-workers 2 1``
times the new code's run once per value (``--workers N``) after the old code's, the order reversed
on each of ``--repeat`` rounds; the ratio rows use the means. When the session has ground truth, the scene
stage's mesh accuracy and completeness of each code are printed too (one evaluator, this checkout's).

Targets: Stage III on a 60 s two-view sequence <= 3 min (issue 5, split between feature work =
registration and optimisation = refinement); Stage IV fit of 1800 frames <= 2 min (issue 6);
issue 30: the four stages <= 1/3 of main's wall time, Stages I, III and IV each <= 1/2.

    .venv/bin/python benchmarks/bench_pipeline.py --seconds 60 --out /tmp/bench_pipeline
    git worktree add --detach /tmp/main-src main
    .venv/bin/python benchmarks/bench_pipeline.py --seconds 60 --out /tmp/bench_pipeline --old-src /tmp/main-src/src
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

from _child import run_cli_tree, run_cli_usage, sequence_figures

STAGES = (("scene", "scenes/scene0/manifest.json"), ("sequence", "sequences/seq0/manifest.json"),
          ("calibrate", "sequences/seq0/calibrate_manifest.json"), ("motion", "sequences/seq0/motion_manifest.json"),
          ("evaluate", None))
#: Accuracy figures of ``evaluation.json``'s sequence entry shown for both codes.
ACCURACY = ("w_mpjpe_mm", "wa_mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm_c100", "wa_mpjpe_mm_c100", "w_mpjpe_mm_c500", "rte_pct",
            "v1_view_translation_err_cm", "v2_view_translation_err_cm", "camera_rot_err_deg", "camera_trans_err_m")
#: The paper's names of the stages in the ratio rows.
ROMAN = {"scene": "Stage I (scene)", "sequence": "Stage II (sequence)", "calibrate": "Stage III (calibrate)",
         "motion": "Stage IV (motion)", "evaluate": "evaluate"}


def _steps(session: Path, manifest: str | None) -> dict[str, float]:
    if manifest is None:
        return {}
    man = json.loads((session / manifest).read_text())
    return {k: v["seconds"] for k, v in man["steps"].items()}


def _accuracy(session: Path) -> dict[str, float]:
    return sequence_figures(session, ACCURACY)


def _scene_accuracy(codes) -> None:
    """Stage I mesh accuracy (mean distance to the true surface) and completeness (5 cm) of each
    code's ``mesh_raw.ply``, with this checkout's evaluator, plus the sparse model's figures."""
    from embodmocap.evaluate.session import scene_errors
    from embodmocap.io.layout import SessionLayout

    print("\n| code | mesh accuracy cm | mesh completeness % | mesh faces | sfm points | sfm reproj px |")
    print("|---|---|---|---|---|---|")
    for code, _, sess in codes:
        if not (sess / "ground_truth" / "ground_truth.json").is_file():
            continue
        fig = json.loads((sess / STAGES[0][1]).read_text())["figures"]
        err = scene_errors(SessionLayout(sess), "scene0")
        print(f"| {code} | {err['mesh_accuracy_cm']} | {err['mesh_completeness_pct']} | {fig['mesh_faces']} | "
              f"{fig['sfm_points']} | {fig['sfm_mean_reproj_error_px']} |", flush=True)


def _copy_session(src: Path, dst: Path) -> Path:
    """A fresh copy of the synthesised inputs (no stage outputs), so each code starts from scratch."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("scenes", "sequences", "evaluation.json"))
    return dst


def _whole_runs(codes, session: Path, args, rows: dict, first_new: bool) -> None:
    """``embodmocap run`` end to end on fresh copies: the old code and the new one with each
    ``--new-workers`` value, interleaved, ``--repeat`` times; ``rows["run", code]`` gets the mean
    (wall, CPU, peak of the process tree's RSS sum) of each."""
    print("\n| `embodmocap run` | code | wall s | CPU s | own peak RSS MB | tree peak RSS MB | tree peak Pss MB | processes |")
    print("|---|---|---|---|---|---|---|---|")
    news = [("new" if i == 0 else f"new w{n}", ["--workers", str(n)] if n else []) for i, n in enumerate(args.new_workers)]
    runs = [("old", codes[0][1], [])] + [(c, codes[1][1], extra) for c, extra in news]
    if first_new:
        runs = runs[::-1]
    got: dict[str, list] = {}
    for k in range(args.repeat):
        for code, src, extra in (runs if k % 2 == 0 else runs[::-1]):
            run_copy = _copy_session(session, args.out / f"whole_{code.replace(' ', '_')}")
            if args.device and code.startswith("new"):
                extra = extra + ["--device", args.device]
            r = run_cli_tree("run", str(run_copy), *extra, src=src)
            got.setdefault(code, []).append(r)
            label = code if code == "old" else f"{code.split()[0]} (--workers {extra[1] if extra else 'default'})"
            print(f"| run | {label} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['peak_mb']} | {r['tree_rss_mb']} | "
                  f"{r['tree_pss_mb']} | {r['processes']} |", flush=True)
    for code, rs in got.items():
        rows["run", code] = tuple(sum(r[k] for r in rs) / len(rs) for k in ("wall_s", "cpu_s", "tree_rss_mb"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/pipeline"))
    ap.add_argument("--old-src", type=Path, default=None, help="src folder of the code to compare with (interleaved)")
    ap.add_argument("--device", default=None, help="--device of the new code's Stage IV (auto, cpu, cuda)")
    ap.add_argument("--stages", nargs="+", default=[s for s, _ in STAGES], choices=[s for s, _ in STAGES] + ["run"],
                    help="the stages to time (default all, in pipeline order); `run`: only the whole run")
    ap.add_argument("--new-workers", nargs="+", type=int, default=[0],
                    help="--workers of the new code's whole run, one run per value (0: its default)")
    ap.add_argument("--repeat", type=int, default=1, help="whole runs of each code and --new-workers value")
    ap.add_argument("--no-whole-run", action="store_true",
                    help="with --old-src: skip the timing of `embodmocap run` on two more fresh copies")
    args = ap.parse_args()
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = args.out / f"indoor_{int(args.seconds)}s"
    if not (session / "ground_truth" / "ground_truth.json").is_file():
        synthesize(SynthConfig(seed=args.seed, seconds=args.seconds, scene_seconds=15.0), session)
    new_src = str(Path(__file__).resolve().parents[1] / "src")
    if args.old_src is None:
        codes = [("new", new_src, session)]
    else:
        codes = [("old", str(args.old_src.resolve()), _copy_session(session, args.out / "run_old")),
                 ("new", new_src, _copy_session(session, args.out / "run_new"))]
    print(f"load average at start: {os.getloadavg()}", flush=True)
    frames = None
    rows: dict[tuple[str, str], tuple[float, float, int]] = {}
    print("| stage | code | wall s | CPU s | peak RSS MB | frames/s | steps (wall s) |")
    print("|---|---|---|---|---|---|---|")
    stages = [(s, m) for s, m in STAGES if s in args.stages]
    if "run" in args.stages and args.old_src is None:
        ap.error("--stages run needs --old-src")
    for i, (stage, manifest) in enumerate(stages):
        order = codes if i % 2 == 0 else codes[::-1]
        for code, src, sess in order:
            extra = [] if stage == "evaluate" else ["--force"]
            if args.device and code == "new" and stage == "motion":
                extra += ["--device", args.device]
            wall, rss, cpu = run_cli_usage(stage, str(sess), *extra, src=src)
            rows[stage, code] = (wall, cpu, rss)
            steps = _steps(sess, manifest)
            if stage == "sequence":
                frames = json.loads((sess / manifest).read_text())["figures"]["frames"]
            fps = f"{frames / wall:.1f}" if frames and stage != "scene" else "-"
            print(f"| {stage} | {code} | {wall:.1f} | {cpu:.1f} | {rss} | {fps} | "
                  f"{', '.join(f'{k} {v:.1f}' for k, v in steps.items())} |", flush=True)
    if "scene" in args.stages:
        _scene_accuracy(codes)
    seq = f"{frames} sequence frames per view ({args.seconds:.0f} s at 30 fps); " if frames else ""
    print(f"\n{seq}load average at the end: {os.getloadavg()}")
    if args.old_src is None:
        return
    four = [s for s, _ in STAGES[:4] if s in args.stages]
    if (len(four) == 4 and not args.no_whole_run) or "run" in args.stages:
        _whole_runs(codes, session, args, rows, first_new=len(stages) % 2 == 0)
    print(f"\nload average now: {os.getloadavg()}")
    print("\n| ratio row | wall new / old | CPU new / old | peak RSS new / old | wall old / new s |")
    print("|---|---|---|---|---|")
    if ("run", "old") in rows:
        (wo, co, ro), (wn, cn, rn) = rows["run", "old"], rows["run", "new"]
        print(f"| whole run (`embodmocap run`) | {wn / wo:.3f} | {cn / co:.3f} | {rn / ro:.3f} | {wo:.1f} / {wn:.1f} |")
    for n in args.new_workers:
        if ("run", f"new w{n}") in rows and n != args.new_workers[0]:
            (wo, co, ro), (wn, cn, rn) = rows["run", "old"], rows["run", f"new w{n}"]
            print(f"| whole run, new `--workers {n}` | {wn / wo:.3f} | {cn / co:.3f} | {rn / ro:.3f} | {wo:.1f} / {wn:.1f} |")
    for stage in [s for s, _ in stages]:
        (wo, co, ro), (wn, cn, rn) = rows[stage, "old"], rows[stage, "new"]
        print(f"| {ROMAN[stage]} | {wn / wo:.3f} | {cn / co:.3f} | {rn / ro:.3f} | {wo:.1f} / {wn:.1f} |")
    if len(four) < 4:
        return
    tot = {c: [sum(rows[s, c][k] for s in four) for k in range(2)] + [max(rows[s, c][2] for s in four)] for c in ("old", "new")}
    print(f"| Stages I-IV (sum of the stage processes) | {tot['new'][0] / tot['old'][0]:.3f} | {tot['new'][1] / tot['old'][1]:.3f} | "
          f"{tot['new'][2] / tot['old'][2]:.3f} ({tot['new'][2]} / {tot['old'][2]} MB) | {tot['old'][0]:.1f} / {tot['new'][0]:.1f} |")
    if "evaluate" not in args.stages:  # the evaluation's figures need every stage
        return
    acc = {c: _accuracy(s) for c, _, s in codes}
    print("\n| figure | old | new | new / old |")
    print("|---|---|---|---|")
    for k in sorted(set(acc["old"]) | set(acc["new"])):  # a figure only one code writes: nan on the other side
        o, n = acc["old"].get(k, float("nan")), acc["new"].get(k, float("nan"))
        print(f"| {k} | {o:.4g} | {n:.4g} | {n / o if o else float('nan'):.3f} |")


if __name__ == "__main__":
    main()
