"""Issue 29 part 7: `sim check` in our own Stage I mesh, which saw every surface from one side only.

Per studio session (a folder with Stages I-IV done and the studio's ``ground_truth/``), ``sim
check``'s penetration (max and mean over frames), unsupported frames and contact, with the rule of
session 7 (``through_surface``: a body vertex behind a scene face penetrates only when its patch got
there through a seen surface) and the rule before it (``old``: the closest face's side alone):

- ``truth``: the studio's true motion of the session, in our Stage I mesh placed in the studio's
  frame by the studio's true ``T_scene_vio`` (an oracle placement: only the mesh is ours);
- ``fit``: our fit in our Stage I mesh (nothing from the truth);
- ``truth_<interaction>``: the studio's scripted motion of one interaction (``chair``, ``sofa`` =
  sofa or bed seat, ``table`` = leaning on it, ``lie`` = lying on the bed) in the session's room,
  its interaction frames only (from the first frame of sitting down / leaning in / lying down to the
  end), in the same placed Stage I mesh: seated, leaning and lying truth the session's own 6 s may
  not hold.

The depth is measured, like ``sim check``, on Stage I's full-resolution mesh near the vertices the
simplified mesh finds inside (rule ``simplified_depth``: on the simplified mesh, before session 13).

Targets: max penetration <= 3 cm on every truth row, <= 5 cm on the fit. The residual force is not
computed (``residual=False``): penetration and contact do not depend on it.

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/bench_sim_open.py \\
        --sessions /tmp/simcheck/hard_{101,110,100} --json /tmp/simcheck/bench_sim_open.json
    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/bench_sim_open.py --time /tmp/simcheck/hard_101
    # only our fits, the session-7 rule:
    ... bench_sim_open.py --sessions S1 S2 ... --kinds fit --rules through_surface --json OUT.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

INTERACTIONS = ("chair", "sofa", "table", "lie")
#: Script segments that are not the interaction.
WALKING = ("idle", "turn", "walk", "step_away", "step_back")


def placed_stage1_mesh(session: Path):
    """Our Stage I meshes (what ``sim check`` reads: the simplified one and the full-resolution one
    it measures depth on) in the studio's scene frame (true T_scene_vio): the fit, then keyword
    arguments of :class:`SimSequence` for the truth rows."""
    from embodmocap.sim.session import load_sequence

    fit = load_sequence(session, detail=True)
    T = np.load(session / "ground_truth" / "scene_scene0_device.npz")["T_scene_vio"]
    placed = {"scene_vertices": fit.scene_vertices @ T[:3, :3].T + T[:3, 3], "scene_faces": fit.scene_faces}
    if fit.detail_vertices is not None:
        placed.update(detail_vertices=fit.detail_vertices @ T[:3, :3].T + T[:3, 3], detail_faces=fit.detail_faces)
    return fit, placed


def truth_params(session: Path):
    from embodmocap.types import SmplParams

    info = json.loads((session / "ground_truth" / "ground_truth.json").read_text())
    gt = np.load(session / "ground_truth" / f"seq_{info['sequence']}.npz")
    return SmplParams(gt["betas"], gt["global_orient"], gt["body_pose"], gt["transl"], fps=float(info["config"]["fps"]))


def interaction_params(session: Path, body, name: str):
    """The studio's scripted motion of one interaction in the session's room (its frames from the
    interaction's first segment on), or None when the room lacks the furniture."""
    import dataclasses

    from embodmocap.synth.motion import MotionScriptConfig, script_motion
    from embodmocap.synth.scene import build_scene

    info = json.loads((session / "ground_truth" / "ground_truth.json").read_text())
    cfg = info["config"]
    seed = int(cfg["seed"])
    built = build_scene(cfg["preset"], np.random.default_rng([seed, 1]), cfg.get("room", "standard"))
    if name == "lie" and "bed" not in built.spec.furniture:
        return None
    betas = np.zeros(body.num_betas)
    betas[:4] = np.random.default_rng([seed, 2]).normal(0.0, [0.8, 0.6, 0.5, 0.5])
    sc = script_motion(built.spec, body, betas, 12.0, float(cfg["fps"]), np.random.default_rng([seed, 3]),
                       MotionScriptConfig(interactions=(name,)))
    moves = [(n, s, e) for n, s, e in sc.segments if n not in WALKING]
    if not moves:
        return None
    idx = np.arange(moves[0][1], moves[-1][2])
    p = sc.params
    return dataclasses.replace(p, global_orient=p.global_orient[idx], body_pose=p.body_pose[idx],
                               transl=p.transl[idx]), [n for n, _, _ in moves]


def rows_for(session: Path, interactions: tuple[str, ...], kinds: tuple[str, ...] = ("truth", "fit"),
             rules: tuple[str, ...] = ("through_surface", "old")) -> list[dict]:
    from embodmocap.sim.check import plausibility
    from embodmocap.sim.config import SimCheckConfig
    from embodmocap.sim.session import SimSequence

    fit, mesh = placed_stage1_mesh(session)
    truth = truth_params(session)
    cases = [("truth", SimSequence(session, "truth", truth, np.arange(len(truth)), fit.body_model, **mesh), None),
             ("fit", fit, None)]
    cases = [c for c in cases if c[0] in kinds]
    for name in (interactions if "truth" in kinds else ()):
        got = interaction_params(session, fit.body_model, name)
        if got is not None:
            p, moves = got
            cases.append((f"truth_{name}", SimSequence(session, name, p, np.arange(len(p)), fit.body_model, **mesh), moves))
    rows = []
    for kind, sq, moves in cases:
        for rule, cfg in (("through_surface", SimCheckConfig()), ("old", SimCheckConfig(through_surface=False)),
                          ("simplified_depth", SimCheckConfig(full_resolution_depth=False))):
            if rule not in rules:
                continue
            s = plausibility(sq, cfg, residual=False)["summary"]
            rows.append({"session": session.name, "kind": kind, "rule": rule, "frames": s["frames"],
                         "segments": moves, "penetration_max_cm": s["penetration_max_cm"],
                         "penetration_mean_cm": s["penetration_mean_cm"], "unsupported_frames": s["unsupported_frames"],
                         "unseen_side_frames": s["unseen_side_frames"], "seconds": s["seconds"],
                         "contact_fraction": {k: x for k, x in s["contact_fraction"].items() if x > 0}})
            print(json.dumps({k: (round(x, 2) if isinstance(x, float) else x) for k, x in rows[-1].items()}), flush=True)
    return rows


def check_time_60s(session: Path) -> dict:
    """Seconds of ``plausibility`` (residual included, as ``sim check`` runs it) on the session's fit
    tiled to 60 s, with ``through_surface`` and without, with the depth on the simplified mesh (the
    rule before session 13) and on the full one, vertex strides 1 and 4, one process."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_sim_side import check_time_60s as timed

    return timed(session, (("old", {"through_surface": False}), ("simplified_depth", {"full_resolution_depth": False}),
                           ("through_surface", {})))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=Path, nargs="+", default=[])
    ap.add_argument("--time", type=Path, help="only time the check on this session's fit tiled to 60 s")
    ap.add_argument("--interactions", nargs="*", default=list(INTERACTIONS), choices=INTERACTIONS)
    ap.add_argument("--kinds", nargs="+", default=["truth", "fit"], choices=["truth", "fit"],
                    help="rows: the truth (and its interactions) and/or our fit")
    ap.add_argument("--rules", nargs="+", default=["through_surface", "old"],
                    choices=["through_surface", "old", "simplified_depth"],
                    help="through_surface: today's check; old: without through_surface (before session 7); "
                         "simplified_depth: depth on the simplified mesh (before session 13)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    if a.time:
        out = check_time_60s(a.time)
        if a.json:
            a.json.write_text(json.dumps(out, indent=1))
        return
    res: dict = {"date": time.strftime("%Y-%m-%d"), "sessions": [str(s) for s in a.sessions], "rows": []}
    for s in a.sessions:
        res["rows"] += rows_for(s, tuple(a.interactions), tuple(a.kinds), tuple(a.rules))
        if a.json:
            a.json.write_text(json.dumps(res, indent=1))
    summary = {}
    for rule in ("through_surface", "old", "simplified_depth"):
        for group in ("truth", "fit"):
            sel = [r for r in res["rows"] if r["rule"] == rule and r["kind"].split("_")[0] == group]
            if sel:
                summary[f"{rule}/{group}"] = {"rows": len(sel), "sessions": len({r["session"] for r in sel}),
                                              "penetration_max_cm": max(r["penetration_max_cm"] for r in sel),
                                              "penetration_mean_cm": float(np.mean([r["penetration_mean_cm"] for r in sel]))}
    res["summary"] = summary
    print(json.dumps(summary, indent=1))
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
