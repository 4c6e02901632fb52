"""MimicKit-style motion files for the SMPL humanoid, and the scene as a physics asset.

**Motion** (``.pkl``, what MimicKit's ``anim.motion.load_motion`` reads): a pickled dict

    loop_mode  int    0 = clamp, 1 = wrap
    fps        float  frames per second
    frames     list of T lists of D = 3 + 3 + 23 * 3 = 75 floats (plain Python floats, as
               MimicKit's own ``Motion.save`` writes, so loading needs no particular numpy)

Each frame is ``root position (3, m, Z-up world) | root rotation (3, exponential map) | one
exponential map (3) per non-root body`` in the body order of the SMPL humanoid MJCF
(:data:`SMPL_HUMANOID_BODIES`, depth first: left leg, right leg, spine and head, left arm, right
arm). MimicKit merges each body's three hinge joints into one spherical joint whose DOFs are an
exponential map, so a body's 3 values are its rotation relative to its parent.

The humanoid's body frame is **x forward, y left, z up**, while SMPL's canonical frame is x left,
y up, z forward. With ``C = R_HUMANOID_SMPL`` (the fixed change of axes):

    root_pos   = J_0(betas) + transl                 (the pelvis, world, metres)
    root_rot   = R(global_orient) @ C^T              (world orientation of the pelvis body)
    joint_rot  = C @ R(pose_j) @ C^T                 (local rotation, humanoid axes)

With the motion's frame flags, a sidecar ``<name>_frames.json`` says per motion frame which
sequence frame it is (``frames``) and whether the fit placed it (``valid``) or a view contradicts it
(``suspect``), so a training set can leave those frames out (MimicKit reads only the pkl).

Body offsets for the performer's own bone lengths go in a sidecar ``<name>_skeleton.json``
(``body_names``, ``smpl_joints``, ``parents``, ``local_pos_m``: each body's rest position in its
parent's frame, humanoid axes), so a humanoid MJCF can be scaled to the performer.

**Scene**: a Wavefront OBJ of the scene mesh (Z up, metres, as MuJoCo / Isaac use) and a height map
npz (:class:`HeightMap`) from which :func:`egocentric_heightmap` samples the paper's 11 x 11
egocentric grid (2 m x 2 m around the character, 0.2 m apart, nearest cell).
"""

from __future__ import annotations

import io
import logging
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.errors import InputError
# HeightMap and scene_heightmap live in the shared geometry package; re-exported here for callers of the export API.
from embodmocap.geometry.heightmap import HeightMap, scene_heightmap, support_heightmap  # noqa: F401
from embodmocap.io.atomic import atomic_dir, write_bytes, write_json, write_npz, write_text
from embodmocap.io.npz_file import load_npz
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: Version of the height-map and skeleton files this module writes.
MIMICKIT_EXPORT_VERSION = 1
#: MimicKit's loop modes.
LOOP_MODES: dict[str, int] = {"clamp": 0, "wrap": 1}

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


# ------------------------------------------------------------------------------------ motion


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
        "version": MIMICKIT_EXPORT_VERSION,
        "body_names": [n for n, _ in SMPL_HUMANOID_BODIES],
        "smpl_joints": HUMANOID_TO_SMPL.tolist(),
        "parents": h_parents,
        "local_pos_m": offsets.tolist(),
        "axes": "x forward, y left, z up (body frames); world Z up, metres",
    }


def write_mimickit_motion(path: str | Path, params: SmplParams, rest_joints: NDArray, *, loop_mode: str = "clamp") -> Path:
    """Write the MimicKit motion pickle (dict of ``loop_mode``, ``fps``, ``frames``); returns the path."""
    if loop_mode not in LOOP_MODES:
        raise ValueError(f"loop_mode must be one of {sorted(LOOP_MODES)}, got {loop_mode!r}")
    frames = mimickit_frames(params, rest_joints)
    doc = {"loop_mode": LOOP_MODES[loop_mode], "fps": float(params.fps), "frames": frames.tolist()}
    write_bytes(path, pickle.dumps(doc, protocol=4))
    return Path(path)


def read_mimickit_motion(path: str | Path) -> tuple[float, int, NDArray[np.float64]]:
    """Read a MimicKit motion pickle: ``(fps, loop_mode, frames (T, D))``. Trusted files only
    (pickle runs code): use it on files this package wrote."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            doc = pickle.load(f)
        return float(doc["fps"]), int(doc["loop_mode"]), np.asarray(doc["frames"], dtype=np.float64)
    except (OSError, KeyError, TypeError, pickle.UnpicklingError) as err:
        raise InputError(path, f"not a MimicKit motion file ({err})", "write it again with the mimickit export") from err


# ------------------------------------------------------------------------------------ scene


def obj_text(vertices: NDArray, faces: NDArray) -> str:
    """A Wavefront OBJ (``v x y z`` lines, then 1-based ``f a b c`` lines), coordinates as given."""
    buf = io.StringIO()
    buf.write("# embodmocap scene mesh: Z up, metres\n")
    np.savetxt(buf, np.asarray(vertices, dtype=np.float64), fmt="v %.6f %.6f %.6f")
    np.savetxt(buf, np.asarray(faces, dtype=np.int64) + 1, fmt="f %d %d %d")
    return buf.getvalue()


def write_heightmap(path: str | Path, hm: HeightMap) -> Path:
    """Write ``heights`` (H, W) float32, ``origin`` (2,), ``cell_m`` (), ``version`` () as npz."""
    write_npz(path, heights=hm.heights, origin=hm.origin, cell_m=np.array(hm.cell_m), version=np.array(MIMICKIT_EXPORT_VERSION))
    return Path(path)


def read_heightmap(path: str | Path) -> HeightMap:
    """Read a height map npz written by :func:`write_heightmap`."""
    path = Path(path)
    z = load_npz(path, what="height map", fix="write it again with the mimickit export",
                 required=("heights", "origin", "cell_m"), versions=(MIMICKIT_EXPORT_VERSION,))
    return HeightMap(heights=z["heights"], origin=z["origin"], cell_m=float(z["cell_m"]))


def egocentric_heightmap(heightmap: HeightMap, xy: NDArray, yaw: NDArray, size: int = 11, spacing: float = 0.2,
                         fill: float = np.nan) -> NDArray[np.float32]:
    """Sample a ``size x size`` grid of heights around root positions, turning with the heading.

    Args:
        heightmap: the scene's :class:`HeightMap`.
        xy: (..., 2) root positions, world metres.
        yaw: (...) heading about +Z, radians (0 = facing +X).
        size: grid points per side (the paper: 11).
        spacing: distance between grid points, metres (the paper: 0.2, i.e. 2 m x 2 m).
        fill: value where the grid leaves the map or the cell is empty.

    Returns:
        (..., size, size) heights, world z in metres; ``out[..., i, k]`` is at ``(i - c) *
        spacing`` ahead of the root and ``(k - c) * spacing`` to its left, ``c = (size - 1) / 2``,
        read from the nearest cell.
    """
    xy = np.asarray(xy, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    offs = (np.arange(size) - (size - 1) / 2.0) * spacing
    fwd, left = np.meshgrid(offs, offs, indexing="ij")  # (size, size)
    c, s = np.cos(yaw)[..., None, None], np.sin(yaw)[..., None, None]
    x = xy[..., 0, None, None] + c * fwd - s * left
    y = xy[..., 1, None, None] + s * fwd + c * left
    col = np.floor((x - heightmap.origin[0]) / heightmap.cell_m).astype(np.int64)
    row = np.floor((y - heightmap.origin[1]) / heightmap.cell_m).astype(np.int64)
    H, W = heightmap.heights.shape
    inside = (row >= 0) & (row < H) & (col >= 0) & (col < W)
    out = heightmap.heights[np.clip(row, 0, H - 1), np.clip(col, 0, W - 1)]
    out = np.where(inside, out, np.float32(fill))
    return np.where(np.isnan(out), np.float32(fill), out).astype(np.float32)


# ------------------------------------------------------------------------------------ bundle

#: Surfaces higher than the performer's highest joint plus this are no support (ceilings, lamps),
#: metres: the head joint sits ~0.1 m below the top of the head, and a raised arm stays below it.
SUPPORT_CAP_ABOVE_JOINTS_M = 0.5


def motion_support_heightmap(vertices: NDArray, faces: NDArray, params: SmplParams, model, *,
                             cell_m: float = 0.05) -> HeightMap:
    """The scene's support height map for a motion: :func:`support_heightmap` capped at the
    performer's highest joint over the motion plus :data:`SUPPORT_CAP_ABOVE_JOINTS_M`.

    The plain :func:`scene_heightmap` keeps the highest surface per cell, which indoors is the
    ceiling everywhere: a policy would see a flat world 2.5-3 m up.
    """
    joints = model.from_params(params).joints.detach().cpu().numpy() if len(params) else np.zeros((1, 24, 3))
    return support_heightmap(vertices, faces, float(np.max(joints[..., 2])) + SUPPORT_CAP_ABOVE_JOINTS_M, cell_m=cell_m)



def write_mimickit(out_dir: str | Path, params: SmplParams, model, scene: tuple | None = None, *, name: str = "motion",
                   loop_mode: str = "clamp", cell_m: float = 0.05, frames: NDArray | None = None,
                   flags: tuple[NDArray, NDArray] | None = None) -> Path:
    """Write the whole MimicKit bundle into the folder ``out_dir`` (replaced atomically).

    Files: ``<name>.pkl`` (motion), ``<name>_skeleton.json`` (bodies and fitted offsets), with
    ``flags`` ((valid, suspect) (T,) bool each) ``<name>_frames.json``, and with a scene
    ``(vertices, faces, ...)``: ``scene.obj`` and ``scene_heightmap.npz``.
    """
    if frames is not None and len(frames) > 1 and np.any(np.diff(np.asarray(frames)) != 1):
        log.warning("%s: the sequence frames have gaps; MimicKit plays them back to back at %.3f fps", out_dir, params.fps)
    rest = model.rest_joints(params.betas)
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        write_mimickit_motion(tmp / f"{name}.pkl", params, rest, loop_mode=loop_mode)
        write_json(tmp / f"{name}_skeleton.json", humanoid_skeleton(rest, model.parents))
        if flags is not None:
            T = len(params)
            fr = np.arange(T) if frames is None else np.asarray(frames, dtype=np.int64)
            valid, suspect = (np.asarray(x, dtype=bool) for x in flags)
            if valid.shape != (T,) or suspect.shape != (T,):
                raise ValueError(f"flags must be two ({T},) arrays, got {valid.shape}, {suspect.shape}")
            write_json(tmp / f"{name}_frames.json", {"frames": fr.tolist(), "valid": valid.tolist(),
                                                     "suspect": suspect.tolist()})
        if scene is not None:
            write_text(tmp / "scene.obj", obj_text(scene[0], scene[1]))
            write_heightmap(tmp / "scene_heightmap.npz", motion_support_heightmap(scene[0], scene[1], params, model, cell_m=cell_m))
    log.info("wrote MimicKit bundle %s (%d frames)", out_dir, len(params))
    return out_dir
