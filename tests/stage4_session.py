"""A tiny synthetic session whose Stage II-IV outputs are written straight from the ground truth.

Used by the render, viewer and evaluation tests: with the true body, true cameras, true offsets and
true sync frames as the "prediction", overlays must land on the performer and every error metric
must be zero. Not a test module (no ``test_`` prefix); test modules import it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from embodmocap.body.model import load_body_model
from embodmocap.geometry.transforms import invert_T
from embodmocap.io.atomic import write_json, write_npz
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.smpl_file import write_smpl_npz
from embodmocap.synth.config import SynthConfig
from embodmocap.types import SmplParams

SYNTH = SynthConfig(seconds=1.0, scene_seconds=1.0, fps=10, width=320, height=240, depth_width=64, depth_height=48)


def make_stage4_session(root: Path, cfg: SynthConfig = SYNTH, stage1_world: bool = False) -> dict:
    """Synthesize a tiny session into ``root`` and write its Stage II-IV outputs from the truth.

    Sequence frames are the motion frames both views recorded. With ``stage1_world`` everything is
    written in Stage I's world (the scene capture's VIO world, as the real stages write it); else in
    the synthetic scene frame. Returns ``start`` (view -> motion frame of the view's raw frame 0),
    ``motion`` (first motion frame of the sequence), ``T`` (frames), ``K``, ``T_world_scene``.
    """
    from embodmocap.synth.studio import synthesize

    synthesize(cfg, root)
    lay = SessionLayout(root)
    gt = np.load(lay.ground_truth.sequence(cfg.sequence_name))
    info = json.loads(lay.ground_truth.info.read_text())
    T_ws = invert_T(np.load(lay.ground_truth.scene_device(cfg.scene_name))["T_scene_vio"]) if stage1_world else np.eye(4)
    start = {v: int(info["view_motion_start"][v]) for v in VIEWS}
    end = {v: int(info["view_motion_end"][v]) for v in VIEWS}
    m = np.arange(max(start.values()), min(end.values()))
    out = lay.sequence(cfg.sequence_name)
    params = SmplParams(gt["betas"], gt["global_orient"][m], gt["body_pose"][m], gt["transl"][m], fps=cfg.fps)
    params = load_body_model(None).params_for_world_frame(params, T_ws)
    move = lambda p: p @ T_ws[:3, :3].T + T_ws[:3, 3]  # noqa: E731
    write_smpl_npz(out.smpl_world, params)
    write_npz(out.joints_world, version=np.int64(1), joints=move(gt["joints_smpl24"][m]),
              coco17=move(gt["joints_coco17"][m]), frames=np.arange(len(m)))
    points = move(gt["joints_coco17"][m])
    points[0, :5] = np.nan  # a frame whose face points were not triangulated
    T = len(m)
    write_npz(out.keypoints3d, version=np.int64(1), points=points, conf=np.full((T, 17), 0.9),
              reproj_err_px=np.ones((T, 17, 2)), filled=np.zeros((T, 17), bool))
    K = cfg.intrinsics()
    views = {}
    for v in VIEWS:
        raw = (m - start[v]).astype(np.int64)
        T_wc = T_ws @ gt[f"{v}_T_scene_cam"][raw]
        cams = dict(K=K.K, width=np.int64(K.width), height=np.int64(K.height), T_world_cam=T_wc, raw_frames=raw)
        write_npz(out.view(v).cameras_final, version=np.int64(1), **cams)
        write_npz(out.view(v).cameras_world, version=np.int64(1), **cams)
        # Stage II's view of the same frames: VIO poses, K of the depth camera, 2D keypoints.
        Kd = cfg.depth_intrinsics()
        write_npz(out.view(v).cameras, version=np.int64(1), K=K.K, width=np.int64(K.width), height=np.int64(K.height),
                  K_depth=Kd.K, depth_width=np.int64(Kd.width), depth_height=np.int64(Kd.height),
                  T_world_cam=gt[f"{v}_T_vio_cam"][raw], raw_frames=raw, timestamps_s=np.arange(T) / cfg.fps,
                  untracked=np.zeros(T, bool))
        kp = np.concatenate([gt[f"{v}_keypoints2d_gt"][raw], gt[f"{v}_visibility"][raw][..., None]], axis=-1)
        write_npz(out.view(v).keypoints, version=np.int64(1), keypoints=kp, boxes=np.zeros((T, 4)), raw_frames=raw,
                  seen=np.ones(T, bool), track_id=np.int64(0))
        views[v] = {"T_world_vio": (T_ws @ gt[f"{v}_T_scene_vio"]).tolist()}
    write_json(out.calibration, {"version": 1, "sequence": cfg.sequence_name, "scene": cfg.scene_name,
                                 "views": views, "warnings": []})
    write_json(out.sync, {"version": 1, "views": {v: {"frame": int(gt[f"{v}_sync_frame"]), "confidence": 1.0,
                                                      "dot_xy_before": None, "frames_seen": 0, "method": "manual"}
                                                  for v in VIEWS}})
    write_json(out.manifest, {"version": 1, "stage": "sequence", "steps": {}, "figures": {"fps": float(cfg.fps), "frames": T}})
    scene = lay.scene(cfg.scene_name)
    scene.root.mkdir(parents=True, exist_ok=True)
    if stage1_world:
        from embodmocap.io.mesh_file import read_mesh_ply, write_mesh_ply

        mv, mf, mc = read_mesh_ply(lay.ground_truth.scene_mesh(cfg.scene_name))
        write_mesh_ply(scene.mesh_raw, move(mv), mf, mc if len(mc) else None)
        shutil.copy(scene.mesh_raw, scene.mesh_simplified)
    else:
        shutil.copy(lay.ground_truth.scene_mesh(cfg.scene_name), scene.mesh_simplified)
        shutil.copy(lay.ground_truth.scene_mesh(cfg.scene_name), scene.mesh_raw)
    return {"start": start, "motion": int(m[0]), "T": T, "K": K, "T_world_scene": T_ws}
