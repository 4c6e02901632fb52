"""Issue 17 item 1: skill clips found per skill on scripted studio sessions (``embodmocap skills``).

Each session: an indoor studio room with a bed (lie / prone need one), a random body shape, 70 s
at 30 fps scripting all six interactions (follow, sit, climb, lie, prone, support; the studio's
:class:`~embodmocap.synth.motion.ScriptedClip` list is the truth). The finder reads the motion and
the studio's scene mesh:

* ``oracle Stage IV (studio truth)``: the true motion as the fit (what Stage IV would give if it
  were exact);
* ``oracle Stage IV + fit-like noise``: the same with per-frame noise of the size of our Stage IV
  errors (1.5 cm on the root, 1.5 degrees on every joint, low-passed over 5 frames so it wobbles
  like a fit rather than jitters).

A found clip is a **label** hit when it overlaps a true clip of the same skill by a temporal IoU
>= 0.5, a **frame** hit when its start and end are also within 10 frames of the truth. Truth follow
clips shorter than the finder's ``follow_min_s`` + 1 s are optional (not missed, matched if found).
Precision = hits / found, recall = hits / truth, per skill; box error = largest distance from a
corner of the scripted furniture's usable top (floor to top) to the found box's nearest corner.

    OMP_NUM_THREADS=1 PYTHONPATH=src:tests .venv/bin/python benchmarks/bench_skills_clips.py \
        --sessions 10 --json /work/bench/17c/bench_skills_clips.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

SKILLS = ("follow", "sit", "climb", "lie", "prone", "support")


def noisy(params, rng, root_m=0.015, joint_deg=1.5, smooth=5):
    """``params`` with low-passed Gaussian noise on the root translation and every joint rotation."""
    from scipy.ndimage import uniform_filter1d
    from scipy.spatial.transform import Rotation

    from embodmocap.types import SmplParams

    T = len(params)

    def wobble(shape, sigma):
        n = uniform_filter1d(rng.normal(0.0, 1.0, shape), smooth, axis=0)
        return n / max(n.std(), 1e-9) * sigma

    transl = params.transl + wobble((T, 3), root_m)
    rot = lambda a, d: (Rotation.from_rotvec(d.reshape(-1, 3)) * Rotation.from_rotvec(np.array(a).reshape(-1, 3))).as_rotvec()  # noqa: E731
    go = rot(params.global_orient, wobble((T, 3), np.deg2rad(joint_deg))).reshape(T, 3)
    bp = rot(params.body_pose, wobble((T, 69), np.deg2rad(joint_deg))).reshape(T, 69)
    return SmplParams(params.betas, go, bp, transl, fps=params.fps)


def score(truth, found, built, fps, follow_min_s):
    """Per skill: truth / found counts, label and frame hits, box corner errors."""
    from skills_truth import corner_error, surface_corners

    opt = int(round((follow_min_s + 1.0) * fps))
    out = {s: {"truth": 0, "found": 0, "label_hits_found": 0, "label_hits_truth": 0, "frame_hits_found": 0,
               "frame_hits_truth": 0, "box_err_m": []} for s in SKILLS}
    optional = [t for t in truth if t.skill == "follow" and t.end - t.start < opt]
    required = [t for t in truth if t not in optional]
    for t in required:
        out[t.skill]["truth"] += 1

    def iou(a, b):
        inter = max(0, min(a.end, b.end) - max(a.start, b.start))
        return inter / max(a.end - a.start + b.end - b.start - inter, 1)

    for f in found:
        o = out[f.skill]
        same = [t for t in truth if t.skill == f.skill and iou(t, f) >= 0.5]
        near = [t for t in same if abs(t.start - f.start) <= 10 and abs(t.end - f.end) <= 10]
        if not same and any(t.skill == f.skill and iou(t, f) > 0 for t in optional):
            continue  # a short walk the truth leaves optional: neither a hit nor a false clip
        o["found"] += 1
        o["label_hits_found"] += bool(same)
        o["frame_hits_found"] += bool(near)
        if near and f.object is not None:
            o["box_err_m"].append(corner_error(np.asarray(f.object.corners), surface_corners(built.spec.furniture[near[0].furniture])))
    for t in required:
        o = out[t.skill]
        same = [f for f in found if f.skill == t.skill and iou(t, f) >= 0.5]
        o["label_hits_truth"] += bool(same)
        o["frame_hits_truth"] += any(abs(t.start - f.start) <= 10 and abs(t.end - f.end) <= 10 for f in same)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=70.0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from embodmocap.body.model import load_body_model
    from embodmocap.skills.config import SkillsConfig
    from embodmocap.skills.stage import clips_of_motion
    from skills_truth import ALL_SIX, FPS, bed_seeds, scripted

    body = load_body_model(None)
    cfg = SkillsConfig()
    rows = {"oracle Stage IV (studio truth)": [], "oracle Stage IV + fit-like noise": []}
    seconds = []
    for seed in bed_seeds(args.sessions):
        betas = np.zeros(10)
        betas[:4] = np.random.default_rng([seed, 2]).normal(0.0, [0.8, 0.6, 0.5, 0.5])
        built, script = scripted(body, seed, ALL_SIX, args.seconds, betas)
        for name, params in (("oracle Stage IV (studio truth)", script.params),
                             ("oracle Stage IV + fit-like noise", noisy(script.params, np.random.default_rng(seed)))):
            t0 = time.perf_counter()
            found, _ = clips_of_motion(params, body, built.vertices, built.faces, cfg)
            if name.endswith("truth)"):
                seconds.append(time.perf_counter() - t0)
            rows[name].append(score(script.clips, found, built, FPS, cfg.follow_min_s))
        print(f"seed {seed}: truth {[c.skill for c in script.clips if c.skill != 'follow']}", flush=True)

    table = {}
    for name, per in rows.items():
        table[name] = {}
        for s in SKILLS:
            tot = {k: sum(p[s][k] for p in per) for k in ("truth", "found", "label_hits_found", "label_hits_truth",
                                                          "frame_hits_found", "frame_hits_truth")}
            errs = [e for p in per for e in p[s]["box_err_m"]]
            div = lambda a, b: round(a / b, 3) if b else None  # noqa: E731
            table[name][s] = {"truth": tot["truth"], "found": tot["found"],
                              "label_precision": div(tot["label_hits_found"], tot["found"]),
                              "label_recall": div(tot["label_hits_truth"], tot["truth"]),
                              "frame_precision": div(tot["frame_hits_found"], tot["found"]),
                              "frame_recall": div(tot["frame_hits_truth"], tot["truth"]),
                              "box_err_cm_median": round(100 * float(np.median(errs)), 1) if errs else None,
                              "box_err_cm_max": round(100 * float(np.max(errs)), 1) if errs else None}
    out = {"sessions": args.sessions, "seconds": args.seconds, "fps": FPS, "finder_s_per_session_mean": round(float(np.mean(seconds)), 2),
           "rows": table}
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
