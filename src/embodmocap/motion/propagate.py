"""Temporal propagation of the starting limbs where the 2D and 3D evidence reject them.

The per-frame start (analytic IK on the triangulated points, or a regressor's pose) is only as good
as the frame's points. A point triangulated in the wrong place (a detector's wrong guess in one
view that lies along the epipolar line: no reprojection error, so nothing flags it) bends the
limb the wrong way; the world SMPLify, whose robust terms write off keypoints that are far away,
then keeps that limb in a wrong basin for as long as the bad points last, and longer through the
smoothness terms. Early frames of a sequence are hit hardest: they have no earlier frames to lean
on.

Here every limb of every frame is scored against all its evidence: the robust 3D residual of its
middle and end keypoints (elbow and wrist, knee and ankle) and their robust reprojection
residuals in every view, with the kernels and scales of the fit (:mod:`embodmocap.motion.terms`).
Frames where a limb agrees with its evidence (mean robust cost at most ``reliable_cost`` over at
least ``min_observations`` observations) are *reliable*; in the others, the limb's local rotations
(the root and hinge joints, e.g. shoulder and elbow) interpolated from the neighbouring reliable
frames are a second candidate, taken when its summed robust cost is lower by ``min_gain``. The
trunk is shared by both candidates, so the four limbs are decided independently.

No ground truth and no information beyond the inputs of the fit are used.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from numpy.typing import NDArray

from embodmocap.motion import terms as TM
from embodmocap.motion.ik import LIMBS


@dataclass(frozen=True)
class PropagateConfig:
    """When a limb's start is replaced by the one carried over from reliable frames."""

    reliable_cost: float = 0.35
    """A limb is reliable in a frame when the mean robust cost (Geman-McClure, 0..1) of its
    observations is at most this (about a residual of 0.7 robust scales)."""
    min_observations: int = 3
    """...and it has at least this many observations (3D points and 2D points in all views)."""
    min_gain: float = 0.5
    """The carried-over limb is taken when its summed robust cost is lower by at least this (half
    an observation's worth)."""


def limb_costs(body, params, points: NDArray, conf3: NDArray, K: NDArray, T_world_cam: NDArray, kp2d: NDArray,
               scale3_m: float, scale2_px: float, min_conf: float) -> tuple[NDArray, NDArray]:
    """Summed robust cost (T, 4) and number of observations (T, 4) of the four limbs of ``params``.

    Args:
        body: a :class:`embodmocap.motion.smplify.KeypointBody` (the keypoint layout's points).
        params: SmplParams, T frames.
        points, conf3: (T, 17, 3) triangulated keypoints (NaN = missing) and (T, 17) confidence.
        K: (V, 3, 3); T_world_cam: (T, V, 4, 4); kp2d: (T, V, 17, 3) pixels and confidence.
        scale3_m, scale2_px: the robust scales; min_conf: weaker observations are ignored.
    """
    tt = lambda x: torch.as_tensor(np.array(x, dtype=np.float64), dtype=torch.float64)  # noqa: E731 (a copy: inputs may be read-only)
    with torch.no_grad():
        _, coco = body(tt(params.betas), tt(params.global_orient), tt(params.body_pose), tt(params.transl))
        s3 = ((coco - tt(np.nan_to_num(points))) ** 2).sum(-1)  # (T, 17)
        r3 = (s3 / (s3 + scale3_m ** 2)).numpy()
        uv, z = TM.project(coco, tt(K), tt(T_world_cam))  # (T, V, 17, 2), (T, V, 17)
        s2 = ((uv - tt(np.nan_to_num(kp2d[..., :2]))) ** 2).sum(-1)
        r2 = (s2 / (s2 + scale2_px ** 2)).numpy()
        z = z.numpy()
    ok3 = np.isfinite(points).all(-1) & (np.nan_to_num(conf3) >= min_conf)
    c2 = np.nan_to_num(kp2d[..., 2])
    ok2 = np.isfinite(kp2d[..., :2]).all(-1) & (c2 >= min_conf) & (z > 0.05)
    cost = np.zeros((len(points), len(LIMBS)))
    count = np.zeros((len(points), len(LIMBS)), dtype=np.int64)
    for i, (_, _, _, k_mid, k_end, _) in enumerate(LIMBS):
        ks = [k_mid, k_end]
        cost[:, i] = np.where(ok3[:, ks], r3[:, ks], 0).sum(1) + np.where(ok2[:, :, ks], r2[:, :, ks], 0).sum((1, 2))
        count[:, i] = ok3[:, ks].sum(1) + ok2[:, :, ks].sum((1, 2))
    return cost, count


def propagate_limbs(body, params, points: NDArray, conf3: NDArray, K: NDArray, T_world_cam: NDArray, kp2d: NDArray,
                    scale3_m: float, scale2_px: float, min_conf: float,
                    cfg: PropagateConfig = PropagateConfig()) -> tuple[object, NDArray[np.bool_]]:
    """``params`` with each limb's start replaced, frame by frame, by the one interpolated from the
    frames where the limb is reliable, where that fits the evidence better (module docstring).

    Returns the new params and (T, 4) bool: which (frame, limb) starts were replaced.
    """
    from embodmocap.motion.fill import fill_rotations

    cost, count = limb_costs(body, params, points, conf3, K, T_world_cam, kp2d, scale3_m, scale2_px, min_conf)
    reliable = (count >= cfg.min_observations) & (cost <= cfg.reliable_cost * np.maximum(count, 1))
    pose = np.array(params.body_pose, dtype=np.float64).reshape(len(points), 23, 3)
    carried = pose.copy()
    for i, (root, hinge, _, _, _, _) in enumerate(LIMBS):
        ok = reliable[:, i]
        if ok.all() or not ok.any():
            continue
        idx = [root - 1, hinge - 1]
        carried[:, idx] = fill_rotations(pose[:, idx], ok)
    cand = replace(params, body_pose=carried.reshape(len(points), 69))
    cost_b, _ = limb_costs(body, cand, points, conf3, K, T_world_cam, kp2d, scale3_m, scale2_px, min_conf)
    take = ~reliable & (cost_b < cost - cfg.min_gain)
    out = pose.copy()
    for i, (root, hinge, _, _, _, _) in enumerate(LIMBS):
        t = take[:, i]
        out[t, root - 1] = carried[t, root - 1]
        out[t, hinge - 1] = carried[t, hinge - 1]
    return replace(params, body_pose=out.reshape(len(points), 69)), take
