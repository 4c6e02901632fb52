"""What each of Stage IV's passes buys (issue 31): every pass that is on by default switched off in
turn, against all on, re-fitted in memory on processed sessions and scored against the truth.

For each session (Stages I-III done, e.g. ``/tmp/bench29/final_*``): Stage IV in memory exactly as
``embodmocap motion`` runs it (sub-frame sync, :func:`embodmocap.motion.solve.triangulate_views`,
body priors, :func:`~embodmocap.motion.solve.fit_motion`; nothing is written) with all passes at
their defaults, then once per pass of :data:`embodmocap.motion.passes.PASSES` that is on by
default and ran in that fit, with its switch off. A ``keypoints`` pass re-runs the triangulation;
a ``start`` or ``fitted`` pass reuses the all-on triangulation. A pass that did not run in the
all-on fit (e.g. ``turn_unplaced`` where a body prior starts the fit) would change nothing: it gets
no row for that session (``n`` counts the sessions behind each row). Passes off by default
(``weakest_view_conf``, ``prior_limbs``, ``edge_repair``) are not ablated here.

Scored as ``embodmocap benchmark`` scores ``dual``: W-MPJPE at chunk 100, WA- and PA-MPJPE, the
first five frames' unaligned error over the median frame's, and the frames with a joint more than
15 cm off that no flag marks (``wrong_unflagged_pct``).

    PYTHONPATH=src python benchmarks/bench_motion_passes.py SESSION [SESSION ...] [--json OUT.json]
    PYTHONPATH=src python benchmarks/bench_motion_passes.py --table OUT.json   # the tables again

With ``--check-files``, the all-on fit is also compared with the session's own ``smpl_fit.npz``
(equal when the session was processed by the same code, with the same settings).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

KEYS = ("w_mpjpe_mm", "wa_mpjpe_mm", "pa_mpjpe_mm", "first5_frame_mm", "median_frame_mm", "wrong_unflagged_pct")

#: Each pass that is on by default -> the config change that switches it off.
OFF = {"label_track": {"label_track.enabled": False}, "fix_swaps": {"fix_swaps": False},
       "temporal": {"temporal.enabled": False}, "bone_gate": {"bone_tol": 0.0},
       "prior_start": {"use_body_prior": False}, "prefer_keypoints": {"prefer_keypoints": False},
       "propagate": {"propagate_limbs": False}, "turn_unplaced": {"turn_unplaced": False}}


def main() -> None:
    from _stage4 import stage4_session
    from bench_motion_edges import motion_config

    from embodmocap.evaluate.benchmark import scored
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.io.stage_files import sequence_fps
    from embodmocap.motion import solve as s4
    from embodmocap.motion.config import MotionConfig
    from embodmocap.motion.passes import PASSES, PHASES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--check-files", action="store_true")
    args = ap.parse_args()
    default = MotionConfig()
    ablated = [p for p in PASSES if p.name in OFF and p.on(default)]
    rows = []
    for s in args.sessions:
        ss = stage4_session(s)
        fps = sequence_fps(ss.ctx.sl)

        def fit(cfg, tri):
            priors = ss.ctx._priors(cfg.min_prior_fraction, ss.T) if cfg.use_body_prior else {}
            return s4.fit_motion(cfg, ss.model, tri.file, ss.cams, ss.kps, ss.T, fps, priors, ss.layout, ss.gender,
                                 label=ss.seq)

        def score(name, fitted):
            e = scored(ss.ctx.joints(fitted.params), np.arange(len(fitted.params)), ss.truth, fitted.valid,
                       fitted.quality.suspect)
            row = {"session": s.name, "variant": name, **{k: e.get(k) for k in KEYS}}
            rows.append(row)
            print("RESULT " + " ".join(f"{k}={v}" for k, v in row.items()), flush=True)
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1))

        tri = s4.triangulate_views(default, ss.cams, ss.kps, ss.T, ss.seq)
        base = fit(default, tri)
        if args.check_files:
            params, _ = read_smpl_npz(ss.ctx.sl.smpl_fit)
            same = all(np.array_equal(np.asarray(getattr(params, k)), np.asarray(getattr(base.params, k)))
                       for k in ("betas", "global_orient", "body_pose", "transl"))
            print(f"CHECK {s.name}: all-on fit {'equal to' if same else 'DIFFERS from'} the session's smpl_fit.npz",
                  flush=True)
        score("all on", base)
        ran = {r["pass"] for r in tri.figures["keypoint_passes"] + base.figures["fit_passes"] if r["ran"]}
        for p in ablated:
            if p.name not in ran:
                print(f"SKIP {s.name}: {p.name} did not run with all passes on", flush=True)
                continue
            cfg = motion_config(OFF[p.name])
            t = s4.triangulate_views(cfg, ss.cams, ss.kps, ss.T, ss.seq) if PHASES[p.phase] == "triangulate" else tri
            score(f"{p.name} off", fit(cfg, t))
    print(table(rows))


def table(rows: list[dict]) -> str:
    """Per variant: its sessions (``n``), those where any figure moved (``changed``), and the median
    over its sessions of each figure and (in brackets) of its change from all on."""
    base = {r["session"]: r for r in rows if r["variant"] == "all on"}
    lines = ["| variant | n | changed | " + " | ".join(KEYS) + " | first5/median |", "|---" * (len(KEYS) + 4) + "|"]
    for name in dict.fromkeys(r["variant"] for r in rows):
        sel = [r for r in rows if r["variant"] == name]
        cells = []
        for k in KEYS + ("first5_over_median",):
            val = (lambda r: r["first5_frame_mm"] / r["median_frame_mm"]) if k == "first5_over_median" else (
                lambda r, k=k: float(r[k]))
            med = float(np.median([val(r) for r in sel]))
            if name == "all on":
                cells.append(f"{med:.2f}")
            else:
                d = float(np.median([val(r) - val(base[r["session"]]) for r in sel]))
                cells.append(f"{med:.2f} ({d:+.2f})")
        changed = sum(any(r[k] != base[r["session"]][k] for k in KEYS) for r in sel)
        lines.append(f"| {name} | {len(sel)} | {changed} | " + " | ".join(cells) + " |")
    sessions = list(base)
    lines += ["", "W-MPJPE c100 (mm) per session; in brackets the change from all on:", "",
              "| variant | mean change | worst change | " + " | ".join(sessions) + " |", "|---" * (len(sessions) + 3) + "|"]
    for name in dict.fromkeys(r["variant"] for r in rows):
        by = {r["session"]: r["w_mpjpe_mm"] for r in rows if r["variant"] == name}
        d = [by[x] - base[x]["w_mpjpe_mm"] for x in sessions if x in by]
        cells = [f"{by[x]:.1f}" + ("" if name == "all on" else f" ({by[x] - base[x]['w_mpjpe_mm']:+.1f})") if x in by else "-"
                 for x in sessions]
        lines.append(f"| {name} | {np.mean(d):+.2f} | {max(d, key=abs):+.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _table_from_json(path: str) -> None:
    """Print the tables of a ``--json`` file again (``python bench_motion_passes.py --table OUT.json``)."""
    print(table(json.loads(Path(path).read_text())))


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["--table"]:
        _table_from_json(sys.argv[2])
    else:
        main()
