"""Stage IV's per-frame quality is computed in pieces of frames on the cores the fit may use
(:func:`embodmocap.motion.solve.fit_quality`): the answer is the whole sequence's, bit for bit, and
does not depend on the number of threads. A walking body seen by two views with depth and person
masks, its left forearm fitted 30 cm off along view 1's ray over one stretch of frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodmocap.body.joints import smpl_to_coco17
from embodmocap.body.model import load_body_model
from embodmocap.io.stage_files import Keypoints3DFile
from embodmocap.motion import solve
from embodmocap.motion.config import MotionConfig
from embodmocap.motion.free_space import free_space_limbs
from embodmocap.motion.quality import frame_quality
from embodmocap.motion.seen_surface import joint_in_front, unexplained_surface
from embodmocap.parallel import lend_cores
from embodmocap.types import SmplParams
from test_free_space import DEPTH, K, RGB, _cameras, _depth_map, _keypoints
from test_seen_surface import _mask

T = 300  # three pieces (128 frames each, the last shorter)
OFF = slice(140, 170)  # the forearm's wrong stretch, across the second piece's end


def _walk():
    """(true params, fitted params): a body turning and swaying in front of the views; the fit
    has the left elbow bent 60 degrees off over :data:`OFF`."""
    t = np.arange(T) / 30.0
    pose = np.zeros((T, 69))
    pose[:, 3 * 15 + 2] = 0.4 * np.sin(2 * t)  # left shoulder swings
    pose[:, 3 * 0] = 0.3 * np.sin(3 * t)  # left hip
    go = np.stack([np.full(T, np.pi / 2), np.zeros(T), 0.2 * np.sin(t)], -1)  # Y up -> Z up, a slow turn
    transl = np.stack([0.1 * np.sin(t), np.full(T, 1.0), np.full(T, 1.2)], -1)
    true = SmplParams(betas=np.zeros(10), global_orient=go, body_pose=pose, transl=transl, fps=30.0)
    bent = pose.copy()
    bent[OFF, 3 * 17 + 1] -= np.deg2rad(60)  # left elbow
    return true, SmplParams(betas=np.zeros(10), global_orient=go, body_pose=bent, transl=transl, fps=30.0)


@pytest.fixture(scope="module")
def scene():
    model = load_body_model(None)
    true, fitted = _walk()
    with torch.no_grad():
        out = model.from_params(true, dtype=torch.float64)
    verts, joints = out.vertices.numpy(), out.joints.numpy()
    coco = smpl_to_coco17(joints, verts, model.vertex_ids)
    Twc = _cameras(verts[0].mean(0))
    depth = {v: np.stack([_depth_map(verts[t], Twc[i]) for t in range(T)]) for i, v in enumerate(("v1", "v2"))}
    masks = {v: np.stack([_mask(d) for d in depth[v]]) for v in depth}
    kp2d = np.stack([_keypoints(coco[t], Twc) for t in range(T)])  # (T, 2, 17, 3)
    cams = {v: {"K": K, "T_world_cam": np.stack([Twc[i]] * T)} for i, v in enumerate(("v1", "v2"))}
    kps = {v: kp2d[:, i] for i, v in enumerate(("v1", "v2"))}
    k3 = Keypoints3DFile(version=np.int64(1), points=coco, conf=np.full((T, 17), 0.9), filled=np.zeros((T, 17), bool))
    depth_in = {v: (depth[v], RGB, masks[v]) for v in depth}
    return model, fitted, cams, kps, kp2d, k3, depth_in


def _whole(cfg, model, params, cams, kps, kp2d, k3, depth):
    """The figures computed on the whole sequence at once (what the pieces must reproduce)."""
    names = ["v1", "v2"]
    Ks, Twc = np.stack([cams[v]["K"] for v in names]), np.stack([cams[v]["T_world_cam"] for v in names], 1)
    raw = np.stack([kps[v] for v in names], 1)
    with torch.no_grad():
        out = model.from_params(params, dtype=torch.float64)
    verts = out.vertices.numpy()
    fitted = smpl_to_coco17(out.joints, out.vertices, model.vertex_ids).numpy()
    q = cfg.quality
    sizes, stacks, masks = [depth[v][1] for v in names], [depth[v][0] for v in names], [depth[v][2] for v in names]
    free = free_space_limbs(verts, model.lbs_weights, Ks, Twc, sizes, stacks, q.free_space_m, q.free_space_window_px)
    surface = unexplained_surface(verts, Ks, Twc, sizes, stacks, masks, raw, q.surface_conf, q.surface_window_px,
                                  q.surface_quantile)
    front = joint_in_front(fitted, Ks, Twc, sizes, stacks, masks, kp2d, raw, q.front_conf, q.front_window_px)
    return frame_quality(fitted, Ks, Twc, kp2d, raw, k3["points"], k3["filled"], tuple(names), q, free, surface, front)


def test_the_quality_in_pieces_on_one_or_two_threads_is_the_whole_sequences(scene):
    model, fitted, cams, kps, kp2d, k3, depth = scene
    cfg = MotionConfig()
    assert cfg.quality.free_space_m > 0 and cfg.quality.surface_m > 0 and cfg.quality.front_m > 0
    assert len(solve.frame_pieces(T)) == 3
    ref = _whole(cfg, model, fitted, cams, kps, kp2d, k3, depth)
    got = {}
    for n in (1, 2):
        with lend_cores(n):
            got[n] = solve.fit_quality(cfg, model, fitted, "COCO17", cams, kps, kp2d, k3, T, depth)
    for name in ("reproj_px", "kp3d_err_m", "limb_off_m", "suspect", "joint_off_m", "free_space", "surface", "front"):
        for n in (1, 2):
            assert np.array_equal(getattr(got[n], name), getattr(ref, name), equal_nan=name != "suspect"), (name, n)
    # Not a vacuous comparison: the bent forearm is flagged, the frames well away from it are not.
    sus = got[2].suspect
    assert sus[OFF].mean() > 0.8 and not sus[:100].any() and not sus[220:].any()
    assert np.isfinite(got[2].surface).any() and np.isfinite(got[2].free_space).any()
