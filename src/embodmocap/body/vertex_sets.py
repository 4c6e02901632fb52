"""Named vertex sets of a body model: the feet (contact, foot-ground checks) and the face keypoints.

The face keypoint vertices (nose, eyes, ears) are stored in the model file and read by
:func:`embodmocap.body.joints.face_vertex_ids` (re-exported here). The feet are found from the
model's own rest pose, so they work for SMPL and the generated test model alike.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.body.joints import face_vertex_ids  # noqa: F401 (one place to find every vertex set)

#: SMPL joints of the (left, right) foot: ankle and foot (toe base).
FOOT_JOINTS: tuple[tuple[int, int], tuple[int, int]] = ((7, 10), (8, 11))
#: How far above the lower ankle joint a vertex may be and still count as foot, metres.
FOOT_ABOVE_ANKLE_M = 0.02


def foot_vertex_ids(body, betas: NDArray | None = None) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Vertex ids of the (left, right) feet: rest-pose vertices nearest to an ankle or foot joint
    and below the ankle (plus :data:`FOOT_ABOVE_ANKLE_M`).

    Args:
        body: a body model (:class:`~embodmocap.body.model.BodyModel`); its rest pose is in the
            model's own Y-up frame.
        betas: (B,) shape; None = the mean shape.
    """
    out = body.forward(np.zeros(body.num_betas) if betas is None else betas, np.zeros((1, 3)), np.zeros((1, 69)))
    v = out.vertices[0].detach().cpu().numpy().astype(np.float64)
    j = out.joints[0].detach().cpu().numpy().astype(np.float64)
    nearest = np.argmin(np.linalg.norm(v[:, None] - j[None], axis=-1), axis=1)
    (la, lf), (ra, rf) = FOOT_JOINTS
    below = v[:, 1] < np.minimum(j[la, 1], j[ra, 1]) + FOOT_ABOVE_ANKLE_M
    left = np.nonzero(np.isin(nearest, (la, lf)) & below)[0]
    right = np.nonzero(np.isin(nearest, (ra, rf)) & below)[0]
    return left, right
