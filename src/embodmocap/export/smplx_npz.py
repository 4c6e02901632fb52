"""SMPL-X-compatible ``.npz`` motion: the keys ``smplx.SMPLX`` takes (and AMASS's SMPL-X layout),
for tools built on SMPL-X.

The fit is SMPL; SMPL-X shares SMPL's first 22 joints (pelvis to wrists, same order, same
axis-angle convention), so the pose maps joint for joint: ``body_pose`` is SMPL's joints 1..21;
SMPL's two hand joints (22, 23) have no SMPL-X counterpart and are dropped; jaw, eyes and the
fingers are zero (a flat hand). World Z up, metres, as the AMASS export.

Keys written (format version 1), T frames::

    global_orient     (T, 3)    axis-angle of the pelvis
    body_pose         (T, 63)   21 body joints, SMPL-X order (= SMPL joints 1..21)
    jaw_pose          (T, 3)    zero
    leye_pose         (T, 3)    zero
    reye_pose         (T, 3)    zero
    left_hand_pose    (T, 45)   zero, 15 joints in full axis-angle (``use_pca=False``)
    right_hand_pose   (T, 45)   zero
    transl            (T, 3)    SMPL ``transl``, metres
    betas             (B,)      SMPL's shape coefficients (see the caveat below)
    num_betas         ()        B
    gender            () str    "neutral" | "male" | "female"
    mocap_frame_rate  ()        frames per second
    poses             (T, 165)  AMASS's SMPL-X layout: the poses above concatenated
    trans             (T, 3)    = transl (AMASS's name)
    frames            (T,)      sequence frame of each row
    valid             (T,) bool the fit's flags (False: the body was filled in from neighbours)
    suspect           (T,) bool the fit's ``suspect`` flags (a view contradicts a limb; all False when not given)
    surface_model_type () str   "smplx"
    source_model      () str    "smpl": the model the values were fitted with
    version           () int64  1

Caveat: SMPL-X's shape space and joint template differ from SMPL's, so ``betas`` and ``transl``
place an SMPL-X body close to, not exactly on, the fitted SMPL surface; the pose is exact. For an
exact surface, fit SMPL-X to the SMPL mesh (e.g. the smplx repository's model transfer tool).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.io.atomic import write_npz
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

SMPLX_NPZ_VERSION = 1
#: SMPL-X's body joints after the pelvis (``smplx.SMPLX.NUM_BODY_JOINTS``) and per hand.
SMPLX_BODY_JOINTS = 21
SMPLX_HAND_JOINTS = 15


def smplx_arrays(params: SmplParams) -> dict[str, NDArray]:
    """The per-frame SMPL-X pose arrays of ``params`` (see the module docstring)."""
    T = len(params)
    zeros = lambda n: np.zeros((T, n), dtype=np.float64)  # noqa: E731
    body = np.asarray(params.body_pose, dtype=np.float64)[:, : 3 * SMPLX_BODY_JOINTS]
    return {"global_orient": np.asarray(params.global_orient, dtype=np.float64), "body_pose": body,
            "jaw_pose": zeros(3), "leye_pose": zeros(3), "reye_pose": zeros(3),
            "left_hand_pose": zeros(3 * SMPLX_HAND_JOINTS), "right_hand_pose": zeros(3 * SMPLX_HAND_JOINTS)}


def write_smplx(path: str | Path, params: SmplParams, *, frames: NDArray | None = None,
                valid: NDArray | None = None, suspect: NDArray | None = None) -> Path:
    """Write ``params`` (world, Z up) as an SMPL-X-compatible npz (atomically); returns the path."""
    T = len(params)
    frames = np.arange(T, dtype=np.int64) if frames is None else np.asarray(frames, dtype=np.int64)
    valid = np.ones(T, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    suspect = np.zeros(T, dtype=bool) if suspect is None else np.asarray(suspect, dtype=bool)
    if frames.shape != (T,) or valid.shape != (T,) or suspect.shape != (T,):
        raise ValueError(f"frames, valid and suspect must be ({T},), got {frames.shape}, {valid.shape}, {suspect.shape}")
    pose = smplx_arrays(params)
    transl = np.asarray(params.transl, dtype=np.float64)
    betas = np.asarray(params.betas, dtype=np.float64).reshape(-1)
    order = ("global_orient", "body_pose", "jaw_pose", "leye_pose", "reye_pose", "left_hand_pose", "right_hand_pose")
    write_npz(path, **pose, transl=transl, betas=betas, num_betas=np.int64(len(betas)), gender=np.array(params.gender),
              mocap_frame_rate=np.float64(params.fps), poses=np.concatenate([pose[k] for k in order], axis=1),
              trans=transl, frames=frames, valid=valid, suspect=suspect, surface_model_type=np.array("smplx"),
              source_model=np.array("smpl"), version=np.int64(SMPLX_NPZ_VERSION))
    log.info("wrote SMPL-X-compatible motion %s (%d frames; hands, jaw and eyes zero)", path, T)
    return Path(path)
