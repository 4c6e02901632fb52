"""The joints and COCO-17 keypoints of a whole motion without skinning the mesh equal the full
body model's, for both keypoint layouts (issue 30: Stage IV's passes and align step use them)."""

from __future__ import annotations

import numpy as np
import torch

from embodmocap.body.joints import smpl_to_coco17
from embodmocap.body.model import load_body_model
from embodmocap.motion.body_points import body_keypoints
from embodmocap.synth.motion import script_motion
from embodmocap.synth.scene import build_scene


def test_body_keypoints_equal_the_skinned_body_model():
    body = load_body_model(None)
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    betas = np.random.default_rng(1).normal(size=10) * 0.8
    params = script_motion(spec, body, betas, 2.0, 30.0, np.random.default_rng(2)).params
    out = body.from_params(params, dtype=torch.float64)
    for layout in ("COCO17", "BODY_25", "SMPL"):
        joints, coco = body_keypoints(body, params, layout)
        assert joints.shape == (len(params), 24, 3) and coco.shape == (len(params), 17, 3)
        np.testing.assert_allclose(joints, out.joints.numpy(), atol=1e-7)
        np.testing.assert_allclose(coco, smpl_to_coco17(out.joints, out.vertices, body.vertex_ids, layout).numpy(),
                                   atol=1e-7)
