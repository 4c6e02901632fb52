"""The edge velocity term: a limb that the keypoints do not pin at the start of a sequence does
not stay off along a straight line (acceleration smoothing alone lets it)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodmocap.body.model import load_body_model
from embodmocap.geometry.transforms import invert_T, look_at_T
from embodmocap.motion import terms as TM
from embodmocap.motion.smplify import SmplifyConfig, ViewObservations, fit_world_smpl
from embodmocap.synth.motion import script_motion
from embodmocap.synth.scene import build_scene
from embodmocap.types import SmplParams

FPS = 30.0
K = np.array([[700.0, 0.0, 360.0], [0.0, 700.0, 480.0], [0.0, 0.0, 1.0]])
#: COCO-17 right elbow and wrist; SMPL right elbow, wrist and hand.
ARM_COCO, ARM_SMPL = [8, 10], [19, 21, 23]
HIDDEN = 7  # the first frames in which no view sees the right arm (fewer than SmplifyConfig.edge_frames)


def test_edge_weights_cover_the_edges_of_placeable_runs():
    valid = np.ones(20, dtype=bool)
    valid[8:10] = False
    w = TM.edge_weights(valid, 3)
    expected = np.zeros(20)
    expected[[0, 1, 2, 5, 6, 7, 10, 11, 12, 17, 18, 19]] = 1.0
    assert w.tolist() == expected.tolist()
    assert TM.edge_weights(valid, 0).sum() == 0.0
    assert TM.edge_weights(np.ones(4, dtype=bool), 10).tolist() == [1.0] * 4


def test_edge_velocity_term_known_answers():
    T = 5
    joints = torch.zeros(T, 3, 3, dtype=torch.float64)
    joints[:, :, 0] = torch.arange(T, dtype=torch.float64)[:, None]  # the whole body walks: no cost
    w = torch.tensor([1.0, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert float(TM.edge_velocity_term(joints, w)) == 0.0
    joints[:, 2, 1] = 0.1 * torch.arange(T, dtype=torch.float64)  # joint 2 moves 0.1 per frame relative to the root
    # Differences 0->1 and 1->2 are covered (the larger weight of their frames), 2 of the 4 differences;
    # each costs 0.01 on one of the three joints.
    assert float(TM.edge_velocity_term(joints, w)) == pytest.approx(2 * 0.01 / 3 / 4)


def _scene():
    body = load_body_model(None)
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    params = script_motion(spec, body, np.zeros(10), 2.0, FPS, np.random.default_rng(3)).params
    out = body.from_params(params, dtype=torch.float64)
    coco = out.coco17.numpy()
    T = len(coco)
    centre = coco.reshape(-1, 3).mean(0)
    views = []
    for name, ang in (("v1", 0.3), ("v2", 1.9)):
        cams = np.repeat(look_at_T(centre + [4 * np.cos(ang), 4 * np.sin(ang), 0.3], centre)[None], T, axis=0)
        Tcw = invert_T(cams)
        p = np.einsum("tij,tkj->tki", Tcw[:, :3, :3], coco) + Tcw[:, None, :3, 3]
        uv = p @ K.T
        kp = np.concatenate([uv[..., :2] / uv[..., 2:], np.ones((T, 17, 1))], -1)
        kp[:HIDDEN, ARM_COCO, 2] = 0.0  # neither view sees the right arm at the start
        views.append(ViewObservations(K, cams, kp, name))
    kp3d = coco.copy()
    kp3d[:HIDDEN, ARM_COCO] = np.nan
    # The start: the truth, but the right arm of the first frames swung off by an angle growing
    # linearly towards the first frame (what a straight-line extrapolation, a guess, leaves).
    pose = params.body_pose.copy()
    ramp = np.linspace(0.6, 0.0, HIDDEN)
    pose[:HIDDEN, 3 * 16 + 2] += ramp  # right shoulder (SMPL 17) about its z
    pose[:HIDDEN, 3 * 18 + 1] -= 0.5 * ramp  # right elbow (SMPL 19)
    init = SmplParams(params.betas, params.global_orient, pose, params.transl, FPS)
    return body, params, out.joints.numpy(), kp3d, views, init


@pytest.fixture(scope="module")
def scene():
    return _scene()


def _arm_err_mm(body, params, truth) -> float:
    j = body.from_params(params, dtype=torch.float64).joints.numpy()
    return 1000 * float(np.linalg.norm(j[:HIDDEN, ARM_SMPL] - truth[:HIDDEN, ARM_SMPL], axis=-1).mean())


def test_edge_velocity_keeps_an_unpinned_arm_with_the_frames_that_pin_it(scene):
    body, params, truth, kp3d, views, init = scene
    base = dict(device="cpu", phase1_iterations=20, phase2_iterations=150)
    conf = np.ones(kp3d.shape[:2])
    errs = {}
    for w in (0.0, SmplifyConfig().w_edge_vel):
        res = fit_world_smpl(body, kp3d, conf, views, init, None, SmplifyConfig(**base, w_edge_vel=w))
        errs[w] = _arm_err_mm(body, res.params, truth)
    start = _arm_err_mm(body, init, truth)
    assert SmplifyConfig().w_edge_vel > 0  # on by default
    # Without it the arm keeps most of its start's error; with it the arm follows the later frames.
    assert errs[SmplifyConfig().w_edge_vel] < 0.6 * errs[0.0], (start, errs)
