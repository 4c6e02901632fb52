"""A body prior's limbs that the 3D keypoints contradict are not pulled towards (issue 29).

Stage IV pulls the fit towards a body prior's pose (a monocular regressor's, one view) frame by
frame, and drops the pull in frames whose prior-started body is far from the triangulated points
(:func:`embodmocap.motion.init.prefer_keypoints`: the median over the frame's joints). A single
limb the regressor got wrong (an arm the prior's view does not see) leaves that median alone, so
the pull stays on the whole pose and bends the limb away from where both views put it: on the
studio's hard outdoor seed 3 the left wrist sat 10-20 cm off for 10 frames where its 3D keypoints
were 3-9 cm off, and 2-5 cm off with no prior at all.

Here each limb (shoulder or hip down to hand or foot) is judged on its own: in the frames where the
prior body's elbow and wrist (knee and ankle) are more than ``margin_m`` further from their 3D
keypoints than the keypoint-started body's (mean over the limb's seen keypoints), the prior's local
rotations of that limb are replaced by the keypoint-started body's, so the pull there goes to what
the views see. Frames or limbs with no triangulated keypoint keep the prior (Stage IV passes only
the points triangulated in the frame, not those filled over a gap: where both ends of a gap were
wrong the filled points contradict a right prior, as on the studio's indoor seed 2's left ankle).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from embodmocap.motion.body_points import body_keypoints
from embodmocap.motion.edge_repair import LIMBS


def gate_prior_limbs(model, prior_pose: NDArray, init, kp_init, points: NDArray, conf: NDArray, min_conf: float,
                     margin_m: float, layout: str = "COCO17") -> tuple[NDArray, NDArray[np.bool_]]:
    """``prior_pose`` (T, 69) with the limbs the 3D keypoints contradict taken from ``kp_init``,
    and those (T, 4) bool (limbs in :data:`embodmocap.motion.edge_repair.LIMBS` order).

    Args:
        model: the body model; prior_pose: (T, 69) the prior's body pose (axis-angle per SMPL joint
            1..23); init: the prior-started params (their orientation, translation and betas place
            the prior's pose); kp_init: the keypoint-started params; points: (T, 17, 3) the 3D
            keypoints (COCO-17, world, metres; NaN = none); conf: (T, 17) their confidences;
            min_conf: a keypoint below it is not evidence; margin_m: how much further the prior's
            limb must be, metres; layout: the keypoints' SMPL layout.
    """
    prior_pose = np.asarray(prior_pose, dtype=np.float64)
    seen = np.isfinite(points).all(-1) & (np.nan_to_num(conf) >= min_conf)

    def coco(p):
        return body_keypoints(model, p, layout)[1]

    kp_same = replace(kp_init, betas=init.betas,
                      transl=np.asarray(kp_init.transl) + model.pelvis_offset(kp_init.betas) - model.pelvis_offset(init.betas))
    d_prior = np.linalg.norm(coco(replace(init, body_pose=prior_pose)) - np.nan_to_num(points), axis=-1)
    d_kp = np.linalg.norm(coco(kp_same) - np.nan_to_num(points), axis=-1)
    out = prior_pose.copy()
    gated = np.zeros((len(prior_pose), len(LIMBS)), dtype=bool)
    for i, (coco_joints, smpl_joints) in enumerate(LIMBS.values()):
        s = seen[:, list(coco_joints)]
        n = s.sum(1)
        mean = lambda d: np.where(s, d[:, list(coco_joints)], 0.0).sum(1) / np.maximum(n, 1)  # noqa: E731
        gated[:, i] = (n > 0) & (mean(d_prior) > mean(d_kp) + margin_m)
        cols = np.concatenate([np.arange(3 * (j - 1), 3 * j) for j in smpl_joints])
        out[np.ix_(gated[:, i], cols)] = np.asarray(kp_same.body_pose, dtype=np.float64)[np.ix_(gated[:, i], cols)]
    return out, gated


def limb_columns(gated: NDArray) -> NDArray[np.bool_]:
    """(T, 69) bool: the body-pose entries of the (frame, limb) pairs ``gated`` (T, 4) marks."""
    cols = np.zeros((len(gated), 69), dtype=bool)
    for i, (_, smpl_joints) in enumerate(LIMBS.values()):
        for j in smpl_joints:
            cols[:, 3 * (j - 1):3 * j] |= np.asarray(gated[:, i], dtype=bool)[:, None]
    return cols
