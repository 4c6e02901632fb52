"""Stage IV as the user runs it (`embodmocap motion S --force`), old code vs this tree, interleaved.

Both codes run on hard-linked copies (``cp -al``) of one session whose Stages I-III are done (outputs
are replaced atomically, so the copies never write into the original); round r runs old then new
(r even) or new then old (r odd). CPU is user + system of the whole process tree (the forked fit
workers of ``SmplifyConfig.workers`` included: ``RUSAGE_CHILDREN`` of the waited-for command;
``time_stage4_interleaved.py`` counts its own process only). ``--evaluate`` then runs
``embodmocap evaluate`` on each copy with its own code and prints W-/WA-/PA-MPJPE and RTE.
``--variant NAME "ARGS"`` (repeatable) adds this tree's code run with extra ``embodmocap motion``
options (e.g. ``--variant w1 "--smplify.workers 1"``) on its own copy, interleaved the same way
(old, new, variants in even rounds, the reverse in odd ones; not evaluated: compare its ``smpl_world.npz`` with new's).

    python benchmarks/time_stage4_cli.py --old-src /work/base-src/src --session /tmp/coord/b60/run_new \\
        --work /tmp/s4cli --rounds 2 --evaluate
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
from pathlib import Path

from _child import run_cli_usage, sequence_figures

FIGURES = ("w_mpjpe_mm", "wa_mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm_c100", "rte_pct")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-src", type=Path, required=True)
    ap.add_argument("--session", type=Path, required=True, help="a session with Stages I-III done")
    ap.add_argument("--work", type=Path, required=True, help="folder for the two copies")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--evaluate", action="store_true")
    ap.add_argument("--variant", nargs=2, action="append", default=[], metavar=("NAME", "ARGS"),
                    help="this tree's code with extra `embodmocap motion` options, on its own copy")
    args = ap.parse_args()
    codes = {"old": str(args.old_src.resolve()), "new": str(Path(__file__).resolve().parents[1] / "src")}
    extra = {c: [] for c in codes}
    for name, opts in args.variant:
        codes[name], extra[name] = codes["new"], opts.split()
    args.work.mkdir(parents=True, exist_ok=True)
    sess = {c: args.work / c for c in codes}
    for c, d in sess.items():
        if not d.exists():
            subprocess.run(["cp", "-al", str(args.session), str(d)], check=True)
    print("| round | code | wall s | CPU s | peak RSS MB | load | steps (wall s) |\n|---|---|---|---|---|---|---|")
    rows = []
    names = list(codes)
    for r in range(args.rounds):
        for c in names if r % 2 == 0 else names[::-1]:
            load = os.getloadavg()[0]
            wall, rss, cpu = run_cli_usage("motion", str(sess[c]), "--force", *extra[c], src=codes[c])
            man = json.loads((sess[c] / "sequences/seq0/motion_manifest.json").read_text())
            steps = ", ".join(f"{k} {v['seconds']:.1f}" for k, v in man["steps"].items())
            print(f"| {r} | {c} | {wall:.1f} | {cpu:.1f} | {rss} | {load:.1f} | {steps} |", flush=True)
            rows.append((c, wall, cpu))
    for c in names[1:]:
        for name, i in (("wall", 1), ("CPU", 2)):
            old, new = (sum(x[i] for x in rows if x[0] == k) for k in ("old", c))
            print(f"{name}: {c} / old {new / old:.3f} ({new:.1f} / {old:.1f} s)")
    if args.evaluate:
        for c in ("old", "new"):
            run_cli_usage("evaluate", str(sess[c]), src=codes[c])
            flat = sequence_figures(sess[c], FIGURES)
            print(c, {k: round(v, 3) for k, v in flat.items() if k.split(".")[-1] in FIGURES}, flush=True)


if __name__ == "__main__":
    main()
