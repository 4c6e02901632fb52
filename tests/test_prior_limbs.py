"""A body prior's limb that the 3D keypoints contradict is taken from the keypoint start
(embodmocap.motion.prior_limbs): known truth, a prior whose left arm is bent elsewhere."""

from __future__ import annotations

import numpy as np
import torch

from embodmocap.body.joints import smpl_to_coco17
from embodmocap.body.model import load_body_model
from embodmocap.motion.prior_limbs import gate_prior_limbs, limb_columns
from embodmocap.types import SmplParams

T = 6


def _truth(body):
    rng = np.random.default_rng(0)
    pose = rng.normal(0, 0.15, (T, 69))
    return SmplParams(np.zeros(10), np.tile([0.0, 0.0, 0.3], (T, 1)), pose, np.tile([0.1, 0.2, 0.9], (T, 1)), 30.0)


def _coco(body, p):
    with torch.no_grad():
        out = body.from_params(p, dtype=torch.float64)
        return smpl_to_coco17(out.joints, out.vertices, body.vertex_ids, "COCO17").numpy()


def test_the_contradicted_limb_is_taken_from_the_keypoints_and_nothing_else():
    body = load_body_model(None)
    truth = _truth(body)
    points = _coco(body, truth)
    conf = np.full((T, 17), 0.9)
    prior = truth.body_pose.copy()
    prior[:, 3 * 15:3 * 16] += [0.0, 0.0, 1.4]   # left shoulder (SMPL 16) swung ~80 deg
    prior[:, 3 * 17:3 * 18] += [0.0, -1.2, 0.0]  # left elbow (SMPL 18) bent the other way
    prior[:, 3 * 4:3 * 5] += 0.02                  # right knee: a small error, within the margin
    kp_init = SmplParams(truth.betas, truth.global_orient, truth.body_pose + 0.01, truth.transl, 30.0)
    init = SmplParams(truth.betas, truth.global_orient, prior, truth.transl, 30.0)
    out, gated = gate_prior_limbs(body, prior, init, kp_init, points, conf, 0.1, 0.1)
    assert gated[:, 0].all() and not gated[:, 1:].any()  # left arm only
    cols = limb_columns(gated)
    np.testing.assert_allclose(out[cols], kp_init.body_pose[cols])
    np.testing.assert_array_equal(out[~cols], prior[~cols])  # the rest of the prior untouched
    # The gated pose puts the left wrist back where its 3D keypoint is.
    wrist = _coco(body, SmplParams(truth.betas, truth.global_orient, out, truth.transl, 30.0))[:, 9]
    assert np.linalg.norm(wrist - points[:, 9], axis=-1).max() < 0.03
    # Without 3D keypoints on the arm there is nothing to contradict the prior.
    none = points.copy()
    none[:, [7, 9]] = np.nan
    _, g2 = gate_prior_limbs(body, prior, init, kp_init, none, conf, 0.1, 0.1)
    assert not g2[:, 0].any()
