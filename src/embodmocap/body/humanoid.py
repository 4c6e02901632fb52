"""The SMPL humanoid of MimicKit-style simulators: its bodies (one per SMPL joint kept), their axes,
its skeleton and motion frames. Shared by the MimicKit export (:mod:`embodmocap.export.mimickit`),
the robot retargeting and the simulator, below all three."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.types import SmplParams

#: Version of the skeleton record :func:`humanoid_skeleton` returns (the export's ``skeleton.json``).
HUMANOID_SKELETON_VERSION = 1

#: Bodies of the SMPL humanoid (MJCF names, depth-first order, root first) and their SMPL joints.
SMPL_HUMANOID_BODIES: tuple[tuple[str, int], ...] = (
    ("Pelvis", 0),
    ("L_Hip", 1), ("L_Knee", 4), ("L_Ankle", 7), ("L_Toe", 10),
    ("R_Hip", 2), ("R_Knee", 5), ("R_Ankle", 8), ("R_Toe", 11),
    ("Torso", 3), ("Spine", 6), ("Chest", 9), ("Neck", 12), ("Head", 15),
    ("L_Thorax", 13), ("L_Shoulder", 16), ("L_Elbow", 18), ("L_Wrist", 20), ("L_Hand", 22),
    ("R_Thorax", 14), ("R_Shoulder", 17), ("R_Elbow", 19), ("R_Wrist", 21), ("R_Hand", 23),
)
#: SMPL joint index of each humanoid body, in the humanoid's order.
HUMANOID_TO_SMPL: NDArray[np.int64] = np.array([j for _, j in SMPL_HUMANOID_BODIES])

#: Change of axes from SMPL's canonical frame (x left, y up, z forward) to the humanoid's body
#: frame (x forward, y left, z up): x_h = z_smpl, y_h = x_smpl, z_h = y_smpl.
R_HUMANOID_SMPL: NDArray[np.float64] = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

FRAME_DIM = 3 + 3 + 3 * (len(SMPL_HUMANOID_BODIES) - 1)



def mimickit_frames(params: SmplParams, rest_joints: NDArray) -> NDArray[np.float64]:
    """(T, 75) MimicKit frames for ``params`` (world, Z up); ``rest_joints`` (24, 3) at its betas."""
    T = len(params)
    C = R_HUMANOID_SMPL
    R = Rotation.from_rotvec(params.poses.reshape(-1, 3)).as_matrix().reshape(T, 24, 3, 3)
    root_pos = np.asarray(rest_joints)[0] + params.transl
    root_rot = R[:, 0] @ C.T
    local = C @ R[:, HUMANOID_TO_SMPL[1:]] @ C.T  # (T, 23, 3, 3)
    exp = Rotation.from_matrix(np.concatenate([root_rot[:, None], local], axis=1).reshape(-1, 3, 3)).as_rotvec()
    return np.concatenate([root_pos, exp.reshape(T, -1)], axis=1)


def humanoid_skeleton(rest_joints: NDArray, parents: NDArray) -> dict:
    """Body names, SMPL joints, parents (humanoid indices) and local rest offsets (m, humanoid axes)."""
    rest = np.asarray(rest_joints, dtype=np.float64)
    smpl_to_h = {int(j): i for i, j in enumerate(HUMANOID_TO_SMPL)}
    h_parents = [-1] + [smpl_to_h[int(parents[j])] for j in HUMANOID_TO_SMPL[1:]]
    offsets = np.zeros((len(HUMANOID_TO_SMPL), 3))
    offsets[1:] = (rest[HUMANOID_TO_SMPL[1:]] - rest[np.asarray(parents)[HUMANOID_TO_SMPL[1:]]]) @ R_HUMANOID_SMPL.T
    return {
        "version": HUMANOID_SKELETON_VERSION,
        "body_names": [n for n, _ in SMPL_HUMANOID_BODIES],
        "smpl_joints": HUMANOID_TO_SMPL.tolist(),
        "parents": h_parents,
        "local_pos_m": offsets.tolist(),
        "axes": "x forward, y left, z up (body frames); world Z up, metres",
    }
