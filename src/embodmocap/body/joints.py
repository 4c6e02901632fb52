"""SMPL's 24-joint skeleton and the SMPL -> COCO-17 keypoint mapping.

SMPL canonical frame (the frame SMPL parameters and model files live in): Y up, the body faces +Z,
its **left** side is on **+X**, metres.

COCO-17 keypoints (order :data:`embodmocap.types.COCO17_NAMES`) come from three sources:

- nose, eyes, ears: single surface vertices (ids per topology; :data:`SMPL_FACE_VERTEX_IDS` for the
  official 6,890-vertex SMPL mesh, stored in the file for the generated test model);
- shoulders, elbows, wrists, knees, ankles: SMPL joints 16-21 and 4, 5, 7, 8 as they are;
- hips: the SMPL hip joints (1, 2) moved by a fixed blend, because COCO annotators mark the hip
  lower and further out (around the greater trochanter) than SMPL's hip joint, which sits at the
  centre of the femoral head:
  ``hip_coco = hip + HIP_OUTWARD * (hip - pelvis) + HIP_DOWN * (knee - hip)``.
  The first term pushes the point outward and down along the pelvis -> hip direction, the second
  slides it along the thigh, so the offset follows the thigh when the leg moves.

Because every COCO point is a fixed linear combination of SMPL joints and 5 surface vertices, the
mapping is one constant (17, 29) matrix (:func:`coco17_matrix`), applied the same way to numpy
arrays and (differentiable) torch tensors.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.types import COCO17_NAMES

#: SMPL's 24 joint names, in SMPL order.
SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
)

#: Parent of each SMPL joint (-1 for the root), i.e. row 0 of SMPL's ``kintree_table``.
SMPL_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)

#: Names of the surface keypoints, in the order smplx's vertex-joint selector uses them.
FACE_KEYPOINT_NAMES: tuple[str, ...] = ("nose", "reye", "leye", "rear", "lear")

#: Vertex ids of the face keypoints on the official SMPL / SMPL-H topology (6,890 vertices), as
#: smplx lists them. SMPL's left is +X; the lower id of each symmetric pair is the left one.
SMPL_FACE_VERTEX_IDS: dict[str, int] = {"nose": 332, "reye": 6260, "leye": 2800, "rear": 4071, "lear": 583}

#: Fraction of the pelvis -> hip vector added to the SMPL hip joint (outward and down), COCO hips.
HIP_OUTWARD: float = 0.3
#: Fraction of the hip -> knee vector added to the SMPL hip joint (down the thigh), COCO hips.
HIP_DOWN: float = 0.1

#: Where each keypoint layout's hips sit on the SMPL body: layout -> (outward, down) fractions of
#: ``hip_kp = hip + outward * (hip - pelvis) + down * (knee - hip)`` (all other COCO-17 points are
#: the same SMPL joints / face vertices for every layout). The one table the 2D and 3D keypoint
#: terms of Stage IV use, chosen by the layout that produced the keypoints (``keypoints2d.npz``'s
#: ``layout``). Why three different points:
#:
#: ============ ========= ====== ===============================================================
#: layout       outward   down   the detector's hip
#: ============ ========= ====== ===============================================================
#: ``COCO17``   0.30      0.10   COCO annotators mark the hip at the greater trochanter: lower
#:                               and further out than the centre of the femoral head
#: ``COCO18``   0.30      0.10   OpenPose's COCO model, trained on those annotations
#: ``BODY_25B`` 0.30      0.10   openpose_train's BODY_25B, COCO annotations for the hips
#: ``BODY_25``  0.10      0.00   OpenPose BODY_25 (trained with a mid-hip point on a different
#:                               hip definition): close to SMPL's hip joint, slightly outward,
#:                               not down the thigh
#: ``SMPL``     0.00      0.00   SMPL's own hip joints (keypoints made from SMPL / mocap joints)
#: ============ ========= ====== ===============================================================
HIP_DEFINITIONS: dict[str, tuple[float, float]] = {
    "COCO17": (HIP_OUTWARD, HIP_DOWN),
    "COCO18": (HIP_OUTWARD, HIP_DOWN),
    "BODY_25B": (HIP_OUTWARD, HIP_DOWN),
    "BODY_25": (0.1, 0.0),
    "SMPL": (0.0, 0.0),
}

# COCO keypoint -> SMPL joint taken as is.
_COCO_FROM_JOINT: dict[str, int] = {
    "left_shoulder": 16, "right_shoulder": 17, "left_elbow": 18, "right_elbow": 19,
    "left_wrist": 20, "right_wrist": 21, "left_knee": 4, "right_knee": 5,
    "left_ankle": 7, "right_ankle": 8,
}
# COCO keypoint -> face keypoint name (a column 24 + FACE_KEYPOINT_NAMES.index(name)).
_COCO_FROM_FACE: dict[str, str] = {
    "nose": "nose", "left_eye": "leye", "right_eye": "reye", "left_ear": "lear", "right_ear": "rear",
}
# COCO hip -> (SMPL hip, SMPL knee).
_COCO_HIPS: dict[str, tuple[int, int]] = {"left_hip": (1, 4), "right_hip": (2, 5)}

if TYPE_CHECKING:
    import torch

Array = Any  # NDArray[np.floating] or torch.Tensor


def coco17_matrix(layout: str = "COCO17") -> NDArray[np.float64]:
    """The (17, 29) matrix mapping [24 SMPL joints; 5 face vertices] to COCO-17 keypoints.

    Columns 0-23 are SMPL joints, 24-28 the face vertices in :data:`FACE_KEYPOINT_NAMES` order.
    Every row sums to 1 (the mapping commutes with rigid motions and translations). ``layout``
    picks the hip definition of the detector that produced the keypoints
    (:data:`HIP_DEFINITIONS`; the points are in COCO-17 order whatever the layout).

    Raises:
        ValueError: an unknown layout.
    """
    if layout not in HIP_DEFINITIONS:
        raise ValueError(f"no SMPL keypoint definition for layout {layout!r}; known: {sorted(HIP_DEFINITIONS)}")
    outward, down = HIP_DEFINITIONS[layout]
    A = np.zeros((17, 29))
    for k, name in enumerate(COCO17_NAMES):
        if name in _COCO_FROM_JOINT:
            A[k, _COCO_FROM_JOINT[name]] = 1.0
        elif name in _COCO_FROM_FACE:
            A[k, 24 + FACE_KEYPOINT_NAMES.index(_COCO_FROM_FACE[name])] = 1.0
        else:
            hip, knee = _COCO_HIPS[name]
            A[k, hip] += 1.0 + outward - down
            A[k, 0] -= outward
            A[k, knee] += down
    return A


def face_vertex_ids(vertex_ids: Mapping[str, int] | Sequence[int]) -> NDArray[np.int64]:
    """The 5 face-keypoint vertex ids in :data:`FACE_KEYPOINT_NAMES` order.

    ``vertex_ids`` is a mapping with the keys nose, reye, leye, rear, lear, or a sequence already
    in that order.
    """
    if isinstance(vertex_ids, Mapping):
        missing = [n for n in FACE_KEYPOINT_NAMES if n not in vertex_ids]
        if missing:
            raise KeyError(f"vertex_ids lacks {missing}")
        return np.array([int(vertex_ids[n]) for n in FACE_KEYPOINT_NAMES], dtype=np.int64)
    ids = np.asarray(vertex_ids, dtype=np.int64)
    if ids.shape != (5,):
        raise ValueError(f"expected 5 face vertex ids, got shape {ids.shape}")
    return ids


def smpl_to_coco17(joints24: Array, vertices: Array, vertex_ids: Mapping[str, int] | Sequence[int],
                   layout: str = "COCO17") -> Array:
    """COCO-17 keypoints (..., 17, 3) from SMPL joints (..., 24, 3) and vertices (..., V, 3).

    Works on numpy arrays or torch tensors (differentiable; dtype and device kept). The result
    lives in whatever frame the inputs are in. ``layout``: whose hips (:data:`HIP_DEFINITIONS`).
    """
    ids = face_vertex_ids(vertex_ids)
    A = coco17_matrix(layout)
    # A tensor can only exist once torch is imported; checking sys.modules keeps this module (and
    # the test-model generator that uses it) free of the torch import.
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(joints24, torch.Tensor):
        face = vertices[..., torch.as_tensor(ids, device=vertices.device), :]
        src = torch.cat([joints24[..., :24, :], face], dim=-2)
        return torch.einsum("kj,...jc->...kc", torch.as_tensor(A, dtype=src.dtype, device=src.device), src)
    joints24 = np.asarray(joints24)
    src = np.concatenate([joints24[..., :24, :], np.asarray(vertices)[..., ids, :]], axis=-2)
    return np.einsum("kj,...jc->...kc", A, src)


def subtree(joint: int, parents: Sequence[int] = SMPL_PARENTS) -> list[int]:
    """``joint`` and all its descendants in the kinematic tree ``parents``."""
    out = [joint]
    for j in range(len(parents)):
        # Parents come before children in SMPL order, so one forward pass collects the subtree.
        if parents[j] in out and j not in out:
            out.append(j)
    return out
