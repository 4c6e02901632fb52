"""BVH export of the SMPL 24-joint skeleton with the performer's own bone lengths.

Conventions of the file written (documented in ``docs/formats.md``):

- **Y up.** BVH has no up-axis field and Blender's importer assumes Y up, so the world is turned
  from our Z-up frame with ``p_yup = R_YUP_ZUP @ p_zup``, i.e. ``(x, y, z) -> (x, z, -y)``.
- **Rest pose = SMPL's T-pose** in SMPL's canonical frame (already Y up, facing +Z, left on +X),
  with the joint offsets of the fitted betas: ``OFFSET_j = J_j(betas) - J_parent(j)(betas)``. The
  root ``OFFSET`` is zero so that importers that add it to the position channels agree with those
  that do not.
- **Channels:** the root has ``Xposition Yposition Zposition Zrotation Xrotation Yrotation``, every
  other joint ``Zrotation Xrotation Yrotation``. Angles are degrees; the local rotation is
  ``R = Rz(z) @ Rx(x) @ Ry(y)`` (column vectors, BVH's usual order). A joint's world rotation is
  its parent's times its local one; its position is the parent's plus the parent's world rotation
  applied to ``OFFSET``.
- **Units:** centimetres by default (``units="m"`` writes metres). Frame time ``1 / fps``.
- Joint names are :data:`SMPL_JOINT_NAMES`; the hierarchy is written depth first (children in
  SMPL index order), which is also the order of the channels in each motion line.
- Leaf joints (head, feet, hands) end in an ``End Site`` half a parent bone long, continuing the
  bone's direction; it carries no data.
"""

from __future__ import annotations

import io
import logging
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.body.joints import SMPL_JOINT_NAMES
from embodmocap.geometry.transforms import R_ZUP_YUP
from embodmocap.io.atomic import write_text
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: Rotation from our Z-up world to BVH's (and glTF's) Y-up world: (x, y, z) -> (x, z, -y).
R_YUP_ZUP: NDArray[np.float64] = R_ZUP_YUP.T.copy()
#: Scale from metres to each supported BVH length unit.
UNIT_SCALE: dict[str, float] = {"cm": 100.0, "m": 1.0}
#: Euler order of every rotation channel (intrinsic; scipy's upper-case convention).
EULER_ORDER = "ZXY"


def depth_first_order(parents: NDArray | tuple[int, ...]) -> list[int]:
    """Joint indices in depth-first order from the root (children visited in index order)."""
    parents = [int(p) for p in parents]
    children: dict[int, list[int]] = {j: [] for j in range(-1, len(parents))}
    for j, p in enumerate(parents):
        children[p].append(j)
    order: list[int] = []
    stack = list(reversed(children[-1]))
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children[j]))
    return order


def _hierarchy(rest: NDArray, parents: NDArray, scale: float) -> str:
    """The HIERARCHY section for rest joints (24, 3) in SMPL's canonical (Y-up) frame."""
    children: dict[int, list[int]] = {j: [] for j in range(len(parents))}
    for j, p in enumerate(parents):
        if p >= 0:
            children[int(p)].append(j)
    lines = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        pad = "  " * depth
        p = int(parents[j])
        if p < 0:
            lines.append(f"{pad}ROOT {SMPL_JOINT_NAMES[j]}")
            offset = np.zeros(3)
            channels = "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"
        else:
            lines.append(f"{pad}JOINT {SMPL_JOINT_NAMES[j]}")
            offset = (rest[j] - rest[p]) * scale
            channels = "CHANNELS 3 Zrotation Xrotation Yrotation"
        lines.extend([f"{pad}{{", f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}", f"{pad}  {channels}"])
        for c in children[j]:
            emit(c, depth + 1)
        if not children[j]:
            # A leaf: an end site continuing the bone (only drawn by viewers; no channels).
            tip = 0.5 * (rest[j] - rest[p]) * scale if p >= 0 else np.array([0.0, 0.1 * scale, 0.0])
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {tip[0]:.6f} {tip[1]:.6f} {tip[2]:.6f}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(int(np.flatnonzero(np.asarray(parents) < 0)[0]), 0)
    return "\n".join(lines) + "\n"


def bvh_motion(params: SmplParams, rest_joints: NDArray, *, units: str = "cm") -> NDArray[np.float64]:
    """The (T, 6 + 23 * 3) motion channels, in SMPL joint order (not yet in file order).

    Columns: root position (3, scaled to ``units``, Y-up world), then per joint ``Z X Y`` Euler
    angles in degrees (root: the Y-up world rotation; others: SMPL's local rotations).
    ``rest_joints`` (24, 3) are the shaped rest joints (:meth:`BodyModel.rest_joints`).
    """
    scale = UNIT_SCALE[units]
    T = len(params)
    pelvis_world = np.asarray(rest_joints[0]) + params.transl  # (T, 3): SMPL rotates about J_0
    root_pos = pelvis_world @ R_YUP_ZUP.T * scale
    rotvecs = params.poses.reshape(T, 24, 3).copy()
    R = Rotation.from_rotvec(rotvecs.reshape(-1, 3)).as_matrix().reshape(T, 24, 3, 3)
    R[:, 0] = R_YUP_ZUP @ R[:, 0]  # the root's rotation, seen from the Y-up world
    with warnings.catch_warnings():
        # Near gimbal lock scipy still returns angles that rebuild the same matrix; it only warns.
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        euler = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler(EULER_ORDER, degrees=True).reshape(T, 24 * 3)
    return np.concatenate([root_pos, euler], axis=1)


def bvh_text(params: SmplParams, rest_joints: NDArray, parents: NDArray, *, units: str = "cm") -> str:
    """The whole BVH file for ``params`` (world, Z up) on the skeleton ``rest_joints`` (24, 3)."""
    if units not in UNIT_SCALE:
        raise ValueError(f"units must be one of {sorted(UNIT_SCALE)}, got {units!r}")
    rest = np.asarray(rest_joints, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.int64)
    channels = bvh_motion(params, rest, units=units)
    # File order: root position, then each joint's three angles in depth-first order.
    order = depth_first_order(parents)
    cols = np.concatenate([np.arange(3)] + [3 + 3 * j + np.arange(3) for j in order])
    buf = io.StringIO()
    np.savetxt(buf, channels[:, cols], fmt="%.6f", delimiter=" ")
    header = (
        _hierarchy(rest, parents, UNIT_SCALE[units])
        + f"MOTION\nFrames: {len(params)}\nFrame Time: {1.0 / float(params.fps):.8f}\n"
    )
    return header + buf.getvalue()


def write_bvh(path: str | Path, params: SmplParams, model, *, units: str = "cm", frames: NDArray | None = None) -> Path:
    """Write ``params`` (world, Z up) as BVH with the skeleton of ``model`` at ``params.betas``.

    ``model`` is a :class:`embodmocap.body.model.BodyModel`. ``frames`` (T,) are only checked for
    gaps: BVH has one fixed frame time, so a gap is logged as a warning (the file plays the kept
    frames back to back).
    """
    if frames is not None and len(frames) > 1 and np.any(np.diff(np.asarray(frames)) != 1):
        log.warning("%s: the sequence frames have gaps; BVH plays them back to back at %.3f fps", path, params.fps)
    text = bvh_text(params, model.rest_joints(params.betas), model.parents, units=units)
    write_text(path, text)
    log.info("wrote BVH %s (%d frames, %s)", path, len(params), units)
    return Path(path)
