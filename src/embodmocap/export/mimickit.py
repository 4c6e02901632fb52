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
npz (:class:`HeightMap`) from which :func:`~embodmocap.geometry.heightmap.egocentric_heightmap` samples the paper's 11 x 11
egocentric grid (2 m x 2 m around the character, 0.2 m apart, nearest cell).
"""

from __future__ import annotations

import io
import logging
import pickle
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.body.humanoid import (  # noqa: F401 (the humanoid's skeleton, shared with robot and sim)
    HUMANOID_TO_SMPL, R_HUMANOID_SMPL, SMPL_HUMANOID_BODIES, humanoid_skeleton, mimickit_frames,
)
# HeightMap and scene_heightmap live in the shared geometry package; re-exported here for callers of the export API.
from embodmocap.geometry.heightmap import HeightMap, scene_heightmap, support_heightmap  # noqa: F401
from embodmocap.io.atomic import atomic_dir, write_bytes, write_json, write_text
from embodmocap.io.heightmap_file import write_heightmap
from embodmocap.io.mesh_file import obj_text
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: MimicKit's loop modes.
LOOP_MODES: dict[str, int] = {"clamp": 0, "wrap": 1}

# ------------------------------------------------------------------------------------ motion


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
