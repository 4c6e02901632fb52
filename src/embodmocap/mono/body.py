"""The camera-space body moved into the stitched, metric world, frame by frame.

For frame ``t`` with metric camera pose ``(R_t, c_t)`` and camera-space SMPL ``(Phi_t, gamma_t,
beta_t)``: the pelvis ``p_t = J_0(beta_t) + gamma_t`` goes to ``R_t p_t + c_t`` and the root
rotation to ``R_t Phi_t``; the world file keeps one shape, the median of the valid frames'
betas, so ``transl_t = R_t p_t + c_t - J_0(beta)``. Frames without an estimate are filled (the
nearest valid frame's rotations, ``transl`` interpolated linearly) and flagged ``valid = False``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.mono.files import HumanSeq
from embodmocap.types import SmplParams


def world_motion(human: HumanSeq, T_world_cam: NDArray, model, fps: float) -> tuple[SmplParams, NDArray[np.bool_]]:
    """World SMPL params (T frames) and their ``valid`` flags; raises ValueError with no valid frame."""
    valid = np.asarray(human.valid, dtype=bool)
    if not valid.any():
        raise ValueError("the human model gave no frame")
    T = len(valid)
    betas = np.median(human.betas[valid], axis=0)
    p_cam = model.pelvis_offset(human.betas) + human.transl
    R = T_world_cam[:, :3, :3]
    p_w = np.einsum("tij,tj->ti", R, p_cam) + T_world_cam[:, :3, 3]
    go = (Rotation.from_matrix(R) * Rotation.from_rotvec(np.array(human.global_orient))).as_rotvec()
    transl = p_w - model.pelvis_offset(betas)
    pose = np.array(human.body_pose)
    if not valid.all():
        idx = np.flatnonzero(valid)
        t = np.arange(T)
        near = idx[np.clip(np.searchsorted(idx, t), 0, len(idx) - 1)]
        prev = idx[np.clip(np.searchsorted(idx, t) - 1, 0, len(idx) - 1)]
        near = np.where(np.abs(prev - t) < np.abs(near - t), prev, near)
        go[~valid], pose[~valid] = go[near[~valid]], pose[near[~valid]]
        transl = np.stack([np.interp(t, idx, transl[idx, k]) for k in range(3)], axis=1)
    return SmplParams(betas, go, pose, transl, fps=float(fps)), valid
