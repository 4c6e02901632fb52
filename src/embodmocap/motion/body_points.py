"""SMPL joints and COCO-17 keypoints of whole motions without skinning the mesh.

Stage IV's passes and its align step compare fitted or started motions with the 3D keypoints
frame by frame; they need the 24 joints and the 17 keypoints only. :class:`BodyModel.forward`
skins every vertex of every frame for that (about 3 s for a 60 s session's 1,792 frames, five
times per run: issue 30); :class:`embodmocap.motion.smplify.KeypointBody` gives the same points
(float64, within 1e-7 m: rounding of the rotations) from the joints and the five face vertices alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.types import SmplParams


def body_keypoints(model, params: SmplParams, layout: str = "COCO17") -> tuple[NDArray, NDArray]:
    """(T, 24, 3) joints and (T, 17, 3) COCO-17 keypoints (``layout``'s hips) of ``params`` (its
    betas shared by every frame), world metres, float64; what ``model.from_params(params)`` gives as
    ``joints`` and :func:`embodmocap.body.joints.smpl_to_coco17` of it. A model without the face
    vertex ids goes through the full body model (and fails there as before)."""
    import torch

    from embodmocap.motion.smplify import KeypointBody

    body = KeypointBody(model, torch.float64, "cpu", layout)
    t = lambda x: torch.from_numpy(np.array(x, dtype=np.float64))  # noqa: E731  (a copy: inputs may be read-only memory maps)
    with torch.no_grad():
        if not body.has_face or len(params) == 0:
            from embodmocap.body.joints import smpl_to_coco17

            out = model.from_params(params, dtype=torch.float64)
            return out.joints.numpy(), smpl_to_coco17(out.joints, out.vertices, model.vertex_ids, layout).numpy()
        joints, coco = body(t(params.betas), t(params.global_orient).reshape(-1, 3), t(params.body_pose).reshape(-1, 69),
                            t(params.transl).reshape(-1, 3))
    return joints.numpy(), coco.numpy()
