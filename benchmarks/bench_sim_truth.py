"""Issue 16: the studio's own ground truth as `sim check` sees it, and its scan's floor coverage,
without rendering a session (fast; the studio's own random draws, so the same motion and room as
`embodmocap synth --seed S` writes for a 6 s sequence with a 15 s scene scan).

1. ``sim check`` figures of the true motion (7.2 s at 30 fps: the 6 s sequence plus the studio's
   lead and tail) in the true scene mesh, per seed: target penetration and floating < 1 cm.
2. Fraction of the walk area's floor (5 cm grid) inside the depth frustum (hfov 67 deg, 4:3,
   range 5 m; occlusion ignored) of some frame of the 15 s empty-scene scan: the default scan
   (session 6: turning in across the walk area), session 5's stop-and-turn glance, and the earlier
   outward-only scan (``SceneWalkConfig(turns_per_lap=0)``).

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/bench_sim_truth.py --seeds 0 1 2 3 4 \\
        --json /work/bench/16/s5/bench_sim_truth.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

KEYS = ("penetration_max_cm", "penetration_mean_cm", "floating_max_cm", "floating_mean_cm", "unsupported_frames",
        "foot_skating_mean_cm", "residual_force_n_per_kg_mean", "residual_torque_nm_per_kg_mean")


def truth_row(seed: int, body) -> dict:
    from embodmocap.sim.check import plausibility
    from embodmocap.sim.session import SimSequence
    from embodmocap.synth.motion import MotionScriptConfig, script_motion
    from embodmocap.synth.scene import build_scene

    built = build_scene("indoor", np.random.default_rng([seed, 1]), "standard")
    betas = np.zeros(body.num_betas)
    betas[:4] = np.random.default_rng([seed, 2]).normal(0.0, [0.8, 0.6, 0.5, 0.5])
    # synthesize(): lead_max_s = max(lead_min_s + 0.6, 1.0) = 1.0, then seconds + 0.2.
    sc = script_motion(built.spec, body, betas, 1.0 + 6.0 + 0.2, 30.0, np.random.default_rng([seed, 3]),
                       MotionScriptConfig())
    sq = SimSequence(Path("."), f"seed{seed}", sc.params, np.arange(len(sc.params)), body,
                     np.asarray(built.vertices, float), np.asarray(built.faces, np.int64))
    s = plausibility(sq)["summary"]
    moves = sorted({n for n, _, _ in sc.segments} - {"idle", "turn", "walk"})
    return {"seed": seed, "frames": s["frames"], "interactions": moves, **{k: s[k] for k in KEYS}}


def floor_coverage(spec, T: np.ndarray, hfov_deg: float = 67.0, aspect: float = 0.75, range_m: float = 5.0) -> float:
    """Fraction of walk-area floor points (5 cm grid) inside some camera's frustum (every 3rd frame)."""
    lo, hi = np.asarray(spec.walk_area_min_xy), np.asarray(spec.walk_area_max_xy)
    g = np.stack(np.meshgrid(np.arange(lo[0], hi[0], 0.05), np.arange(lo[1], hi[1], 0.05), indexing="ij"), -1)
    P = np.column_stack([g.reshape(-1, 2), np.zeros(g.shape[0] * g.shape[1])])
    seen = np.zeros(len(P), bool)
    tx = np.tan(np.radians(hfov_deg / 2))
    ty = tx * aspect
    for Tk in T[::3]:
        pc = (P - Tk[:3, 3]) @ Tk[:3, :3]
        z = pc[:, 2]
        seen |= (z > 0.05) & (z < range_m) & (np.abs(pc[:, 0]) < tx * z) & (np.abs(pc[:, 1]) < ty * z)
    return float(seen.mean())


def coverage_row(seed: int) -> dict:
    from embodmocap.synth import trajectory as tr
    from embodmocap.synth.scene import build_scene

    spec = build_scene("indoor", np.random.default_rng([seed, 1]), "standard").spec
    out = {"seed": seed}
    # Session 6: the default scan turns in across the walk area while walking (turns_per_lap=1);
    # "with_glance" is session 5's stop-and-turn glance on the outward scan.
    for name, cfg in (("default", tr.SceneWalkConfig()),
                      ("with_glance", tr.SceneWalkConfig(glance_every_s=15.0, turns_per_lap=0.0)),
                      ("outward_only", tr.SceneWalkConfig(turns_per_lap=0.0))):
        T = tr.scene_walk(spec, 15.0, 30.0, np.random.default_rng([seed, 5]), cfg)
        out[name] = floor_coverage(spec, T)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    from embodmocap.body.model import load_body_model

    body = load_body_model(None)  # the generated test model the studio writes
    res: dict = {"date": time.strftime("%Y-%m-%d"), "truth": [], "coverage": []}
    for seed in a.seeds:
        res["truth"].append(truth_row(seed, body))
        res["coverage"].append(coverage_row(seed))
        print(json.dumps(res["truth"][-1]), json.dumps(res["coverage"][-1]), flush=True)
    for k in KEYS:
        res[f"truth_max_{k}"] = float(np.max([r[k] for r in res["truth"]]))
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
