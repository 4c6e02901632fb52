"""Issue 11: how well Stage IV's keypoint checks find a detector's blunders, against the studio's truth.

On prepared sessions (``SESSIONS/<perception>_<seed>`` with Stages I-III done; never modified)
this replays Stage IV's triangulation step on the views' synced 2D keypoints and scores, against
the true joints projected through the cameras Stage III estimated:

- left/right labels: frames where a view's arm or leg pair is still the wrong way round (both
  points nearer the other side's true point by half) after the geometric swap check alone, after
  the time tracking alone and after both (Stage IV's order), and the triangulated limb points
  more than 20 cm off;
- the temporal run check (:mod:`embodmocap.motion.temporal`) and the scene-occlusion check
  (:mod:`embodmocap.motion.occlusion`): detections flagged (of those the triangulation uses,
  confidence >= 0.3), how many of them are wrong (> 40 px from the truth), the share of all wrong
  ones found.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_keypoint_checks.py --sessions /work/bench/11/sessions \\
        --seeds 0 1 2 3 4 5 6 7 8 9
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

COCO_FROM_SMPL = {5: 16, 6: 17, 7: 18, 8: 19, 9: 20, 10: 21, 11: 1, 12: 2, 13: 4, 14: 5, 15: 7, 16: 8}
LIMBS = [7, 8, 9, 10, 13, 14, 15, 16]
GROUPS = {"arms": ((7, 8), (9, 10)), "legs": ((13, 14), (15, 16))}


def session_inputs(session: Path, seq: str = "seq0"):
    """(P (T, V, 3, 4), T_world_cam (T, V, 4, 4), keypoints (T, V, 17, 3), true pixels {joint: (T, V, 2)},
    true world joints (T, 24, 3)) of a prepared session, as Stage IV sees them."""
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.geometry.triangulation import projection_matrices
    from embodmocap.io.layout import VIEWS, SessionLayout
    from embodmocap.io.stage_files import read_cameras, read_keypoints2d
    from embodmocap.sequence.subframe import synced_views

    lay = SessionLayout(session)
    out = lay.sequence(seq)
    cams = {v: read_cameras(out.view(v).cameras_world) for v in VIEWS}
    kps = {v: read_keypoints2d(out.view(v).keypoints).keypoints for v in VIEWS}
    cams, kps = synced_views(out, cams, kps)
    T = min(len(kps[v]) for v in VIEWS)
    K = np.stack([cams[v]["K"] for v in VIEWS])
    Tw = np.stack([cams[v]["T_world_cam"][:T] for v in VIEWS], axis=1)
    P = projection_matrices(K, Tw)
    kp = np.stack([kps[v][:T] for v in VIEWS], axis=1)
    truth = sequence_truth(lay, "scene0", seq).joints[:T]
    h = np.concatenate([truth, np.ones(truth.shape[:-1] + (1,))], -1)
    uvw = np.einsum("tvab,tjb->tvja", P, h)
    px = uvw[..., :2] / uvw[..., 2:]
    return P, Tw, kp, {c: px[:, :, s] for c, s in COCO_FROM_SMPL.items()}, truth


def wrong_labels(kp: np.ndarray, px: dict) -> int:
    """Frames x views x groups whose pair is the wrong way round (>= 3 confident points, the
    crossed assignment under half the error of the given one, the given one > 25 px a point)."""
    n_bad = 0
    for pairs in GROUPS.values():
        same = np.zeros(kp.shape[:2])
        cross = np.zeros(kp.shape[:2])
        n = np.zeros(kp.shape[:2])
        for a, b in pairs:
            for x, y in ((a, b), (b, a)):
                ok = kp[..., x, 2] >= 0.3
                same += np.where(ok, np.linalg.norm(kp[..., x, :2] - px[x], axis=-1), 0)
                cross += np.where(ok, np.linalg.norm(kp[..., x, :2] - px[y], axis=-1), 0)
                n += ok
        n_bad += int(((n >= 3) & (cross < 0.5 * same) & (same / np.maximum(n, 1) > 25)).sum())
    return n_bad


def far_limb_points(P, kp, truth) -> int:
    from embodmocap.geometry.triangulation import TriangulationConfig, triangulate

    tri = triangulate(P, kp[..., :2], kp[..., 2], TriangulationConfig())
    e = np.linalg.norm(tri.points[:, LIMBS] - truth[:, [COCO_FROM_SMPL[j] for j in LIMBS]], axis=-1)
    return int((e > 0.2).sum())


def flag_scores(flags: np.ndarray, kp: np.ndarray, px: dict) -> np.ndarray:
    """[flagged used, of them wrong, wrong used in all] over the limb points."""
    err = np.stack([np.linalg.norm(kp[..., j, :2] - px[j], axis=-1) for j in LIMBS], -1)
    used = kp[..., LIMBS, 2] >= 0.3
    wrong = used & (err > 40)
    f = flags[..., LIMBS] & used
    return np.array([f.sum(), (f & wrong).sum(), wrong.sum()])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=Path, required=True)
    ap.add_argument("--perception", default="hard")
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from embodmocap.geometry.raycast import raycasting_scene
    from embodmocap.geometry.triangulation import TriangulationConfig
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.motion.label_track import track_labels
    from embodmocap.motion.occlusion import OcclusionConfig, drop_scene_hidden
    from embodmocap.motion.swaps import fix_swaps
    from embodmocap.motion.temporal import TemporalConfig, temporal_outliers

    tcfg = TriangulationConfig()
    print("| seed | wrong labels: as detected | geometric check | time tracking | both | limb points > 20 cm: geometric | both | "
          "temporal flags (wrong) | scene-hidden flags (wrong) | wrong detections |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    tot, tot_occ = np.zeros(9), np.zeros(3)
    for seed in args.seeds:
        session = args.sessions / f"{args.perception}_{seed}"
        P, Tw, kp, px, truth = session_inputs(session)
        geo, _ = fix_swaps(P, kp, tcfg)
        tracked, _ = track_labels(kp, P=P)
        both, _ = fix_swaps(P, tracked, tcfg)
        temporal = flag_scores(temporal_outliers(both, TemporalConfig(enabled=True, middle=False)), both, px)
        mesh = read_mesh_ply(SessionLayout(session).scene("scene0").mesh_simplified)
        _, hidden = drop_scene_hidden(raycasting_scene(mesh[0], mesh[1]), P, Tw, both, tcfg, OcclusionConfig())
        occ = flag_scores(hidden, both, px)
        row = np.array([wrong_labels(kp, px), wrong_labels(geo, px), wrong_labels(tracked, px), wrong_labels(both, px),
                        far_limb_points(P, geo, truth), far_limb_points(P, both, truth)])
        tot += np.concatenate([row, [temporal[0], temporal[1], temporal[2]]])
        tot_occ += occ
        print(f"| {seed} | {row[0]} | {row[1]} | {row[2]} | {row[3]} | {row[4]} | {row[5]} | "
              f"{temporal[0]} ({temporal[1]}) | {occ[0]} ({occ[1]}) | {temporal[2]} |", flush=True)
    print(f"| all | {int(tot[0])} | {int(tot[1])} | {int(tot[2])} | {int(tot[3])} | {int(tot[4])} | {int(tot[5])} | "
          f"{int(tot[6])} ({int(tot[7])}) | {int(tot_occ[0])} ({int(tot_occ[1])}) | {int(tot[8])} |")
    print(f"\ntemporal check: precision {tot[7] / max(tot[6], 1):.2f}, recall {tot[7] / max(tot[8], 1):.2f}; "
          f"scene occlusion: precision {tot_occ[1] / max(tot_occ[0], 1):.2f}, recall {tot_occ[1] / max(tot_occ[2], 1):.2f}")


if __name__ == "__main__":
    main()
