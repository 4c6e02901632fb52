"""Why a W-MPJPE chunk-100 figure is what it is: per frame of a processed studio session, the
fitted body's torso orientation and root position against the truth, next to the joint error and
to the rotation and scale that a chunk anchored on that frame gets (issue 29, the anchors' yaw).

W c100 aligns each 100-frame chunk by the similarity (Umeyama with scale) fitted on all joints of
its first two evaluated frames (:func:`embodmocap.evaluate.metrics.w_mpjpe`). This script prints,
per evaluated frame ``t`` (the same frames ``evaluate`` scores: inside the scripted motion and
placed):

- ``err``: mean joint error without alignment (mm); ``max``: the worst joint (mm, its SMPL id);
- ``tyaw tpit trol``: the torso's orientation error (deg; yaw about the world's up axis, then
  pitch and roll) from the torso frame of the joints (hips, shoulders, pelvis -> neck), fitted
  against true; ``gyaw``: the yaw error of SMPL's root rotation (``global_orient``);
- ``root``: the pelvis joint's position error (mm);
- ``ayaw atilt ascale``: the similarity an anchor on frames ``t, t+1`` fits (as W c100 does): its
  rotation's yaw and tilt (deg) and its scale minus 1 (%), each against the similarity fitted on
  the whole chunk (what WA uses), so a perfect anchor reads 0;
- ``W``: W-MPJPE of the 100-frame chunk starting at ``t`` (mm); ``*`` marks W c100's own anchors.

    PYTHONPATH=src python benchmarks/anchor_orientation.py SESSION [SESSION ...] [--frames] [--json OUT]

Without ``--frames`` one summary line per session: W c100 per chunk with its anchors' figures, and
over all frames the median absolute torso yaw / tilt error and the correlation of the anchor yaw
with the torso yaw. Uses the truth: an analysis tool, never part of a run.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

def torso_frames(joints: np.ndarray) -> np.ndarray:
    """(..., 3, 3) torso rotations (columns: the body's left, up and forward in the world) of SMPL
    joints (..., 24, 3): left = the mean of the hips' and the shoulders' right -> left directions,
    up = pelvis -> neck made orthogonal to it, forward = left x up (the heading the hip and
    shoulder keypoints give)."""
    j = np.asarray(joints, dtype=np.float64)
    unit = lambda v: v / np.clip(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9, None)  # noqa: E731
    left = unit(unit(j[..., 1, :] - j[..., 2, :]) + unit(j[..., 16, :] - j[..., 17, :]))
    up = j[..., 12, :] - j[..., 0, :]
    up = unit(up - (up * left).sum(-1, keepdims=True) * left)
    return np.stack([left, up, np.cross(left, up)], -1)


def yaw_tilt_deg(R: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split rotations R (..., 3, 3) into the signed angle about ``up`` (3,) and the tilt of the
    rest (swing-twist: twist about ``up``, tilt = the angle ``up`` itself is moved), degrees."""
    tilt = np.degrees(np.arccos(np.clip(np.einsum("...ij,j,i->...", R, up, up), -1.0, 1.0)))
    # twist: the angle of the rotation's quaternion about ``up``
    w = 0.5 * np.sqrt(np.clip(1.0 + np.trace(R, axis1=-2, axis2=-1), 0.0, None))
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1) * 0.25
    proj = v @ up
    yaw = np.degrees(2.0 * np.arctan2(proj, np.where(np.abs(w) < 1e-12, 1e-12, w)))
    yaw = (yaw + 180.0) % 360.0 - 180.0
    return yaw, tilt


def euler_err_deg(R_fit: np.ndarray, R_gt: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(T, 3) yaw, pitch, roll error (deg) of torso frames R_fit against R_gt (T, 3, 3), in the
    true torso's own axes: yaw about the world's ``up``, pitch about the torso's left axis, roll
    about its forward axis (small-angle split of R_gt^T R_fit)."""
    from embodmocap.geometry.rotations import matrix_to_rotvec

    yaw, _ = yaw_tilt_deg(np.einsum("tij,tkj->tik", R_fit, R_gt), up)  # world-frame error R_fit R_gt^T
    local = np.degrees(matrix_to_rotvec(np.einsum("tji,tjk->tik", R_gt, R_fit)))  # body-frame error
    return np.stack([yaw, local[:, 0], local[:, 2]], -1)


def session_frames(session: str | Path) -> dict:
    """Everything the table needs for one processed session's first sequence (evaluated frames)."""
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.geometry.rotations import rotvec_to_matrix
    from embodmocap.io.ground_truth import read_truth_scene_device, read_truth_sequence
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.smpl_file import read_smpl_valid
    from embodmocap.io.stage_files import read_cameras, read_world_joints
    from embodmocap.geometry.transforms import invert_T

    lay = SessionLayout(Path(session))
    man = load_manifest(lay.manifest)
    seq = next(iter(man.sequences))
    scene = man.sequences[seq].scene
    truth = sequence_truth(lay, scene, seq)
    wj = read_world_joints(lay.sequence(seq).joints_world)
    J, frames = np.asarray(wj["joints"]), np.asarray(wj["frames"])
    valid = read_smpl_valid(lay.sequence(seq).smpl_world)
    ok = truth.valid[frames] & valid
    pred, gt = J[ok][:, :24], truth.joints[frames][ok]
    world = np.load(lay.sequence(seq).smpl_world)
    go_fit = np.asarray(world["poses"])[ok][:, :3]
    g = read_truth_sequence(lay.ground_truth.sequence(seq))
    T_world_scene = invert_T(read_truth_scene_device(lay.ground_truth.scene_device(scene))["T_scene_vio"])
    v1 = lay.sequence(seq).views()[0]
    raw = read_cameras(lay.sequence(seq).view(v1).cameras).raw_frames.astype(np.int64)
    motion = int(g[f"{v1}_motion_start"]) + raw[frames[ok]]
    go_gt = T_world_scene[:3, :3] @ rotvec_to_matrix(np.asarray(g["global_orient"])[motion])
    return {"session": Path(session).name, "frames": frames[ok], "pred": pred, "gt": gt,
            "R_go_fit": rotvec_to_matrix(go_fit), "R_go_gt": go_gt}


def frame_table(d: dict, chunk: int = 100) -> dict:
    """Per-frame figures (see the module docstring) of :func:`session_frames`' output."""
    from embodmocap.evaluate import metrics as M

    pred, gt = d["pred"], d["gt"]
    T = len(pred)
    up = np.array([0.0, 0.0, 1.0])
    err = np.linalg.norm(pred - gt, axis=-1)
    torso = euler_err_deg(torso_frames(pred), torso_frames(gt), up)
    gyaw, _ = yaw_tilt_deg(np.einsum("tij,tkj->tik", d["R_go_fit"], d["R_go_gt"]), up)
    root = 1000 * np.linalg.norm(pred[:, 0] - gt[:, 0], axis=-1)
    ayaw, atilt, ascale, W = (np.full(T, np.nan) for _ in range(4))
    for t in range(T - 1):
        c = slice(t, min(t + chunk, T))
        s2, R2, _ = M.umeyama(pred[t:t + 2].reshape(-1, 3), gt[t:t + 2].reshape(-1, 3))
        sa, Ra, _ = M.umeyama(pred[c].reshape(-1, 3), gt[c].reshape(-1, 3))
        ayaw[t], atilt[t] = yaw_tilt_deg(R2 @ Ra.T, up)
        ascale[t] = 100.0 * (s2 / sa - 1.0)
        W[t] = M.w_mpjpe(pred[c], gt[c], chunk=chunk)
    return {"err": 1000 * err.mean(-1), "max": 1000 * err.max(-1), "max_joint": err.argmax(-1), "tyaw": torso[:, 0],
            "tpit": torso[:, 1], "trol": torso[:, 2], "gyaw": gyaw, "root": root, "ayaw": ayaw, "atilt": atilt,
            "ascale": ascale, "W": W}


def summary(d: dict, f: dict, chunk: int = 100) -> dict:
    """W c100 per chunk with its anchors' figures; medians and the anchor-torso yaw correlation."""
    from embodmocap.evaluate import metrics as M

    T = len(d["pred"])
    starts = list(range(0, T - 1, chunk))
    if T - starts[-1] < 2:
        starts = starts[:-1]
    ok = np.isfinite(f["ayaw"])
    corr = float(np.corrcoef(f["ayaw"][ok], f["tyaw"][ok])[0, 1]) if ok.sum() > 2 else float("nan")
    r = lambda x: round(float(x), 2)  # noqa: E731
    return {"session": d["session"], "w_mpjpe_mm": r(M.w_mpjpe(d["pred"], d["gt"], chunk=chunk)),
            "chunks": [{"frame": int(d["frames"][s]), "W": r(f["W"][s]), "ayaw": r(f["ayaw"][s]),
                        "atilt": r(f["atilt"][s]), "ascale": r(f["ascale"][s]),
                        "tyaw": [r(f["tyaw"][s]), r(f["tyaw"][s + 1])], "err": [r(f["err"][s]), r(f["err"][s + 1])]}
                       for s in starts],
            "median_abs_torso_yaw_deg": r(np.median(np.abs(f["tyaw"]))),
            "median_abs_torso_pitch_deg": r(np.median(np.abs(f["tpit"]))),
            "median_abs_torso_roll_deg": r(np.median(np.abs(f["trol"]))),
            "median_abs_root_yaw_deg": r(np.median(np.abs(f["gyaw"]))),
            "median_abs_anchor_yaw_deg": r(np.nanmedian(np.abs(f["ayaw"]))),
            "median_abs_anchor_scale_pct": r(np.nanmedian(np.abs(f["ascale"]))),
            "median_root_mm": r(np.median(f["root"])), "median_frame_mm": r(np.median(f["err"])),
            "corr_anchor_yaw_torso_yaw": r(corr)}


def main() -> None:
    args = sys.argv[1:]
    out = None
    if "--json" in args:
        i = args.index("--json")
        out, args = Path(args[i + 1]), args[:i] + args[i + 2:]
    frames = "--frames" in args
    rows = []
    for s in [a for a in args if a != "--frames"]:
        d = session_frames(s)
        f = frame_table(d)
        sm = summary(d, f)
        rows.append(sm)
        if frames:
            anchors = {c["frame"] for c in sm["chunks"]}
            print(f"# {d['session']}")
            print("frame   err   max(j)  tyaw  tpit  trol  gyaw  root   ayaw atilt ascale     W")
            for t, fr in enumerate(d["frames"]):
                print(f"{fr:5d}{'*' if fr in anchors else ' '} {f['err'][t]:5.1f} {f['max'][t]:5.0f}({f['max_joint'][t]:2d})"
                      f" {f['tyaw'][t]:5.1f} {f['tpit'][t]:5.1f} {f['trol'][t]:5.1f} {f['gyaw'][t]:5.1f}"
                      f" {f['root'][t]:5.1f} {f['ayaw'][t]:6.2f} {f['atilt'][t]:5.2f} {f['ascale'][t]:6.2f} {f['W'][t]:6.1f}")
        print(json.dumps(sm))
    if out:
        out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
