"""AMASS-style ``.npz`` motion: the layout AMASS, and most tools trained on it, read.

The file holds SMPL parameters in a Z-up world in metres, exactly as AMASS does, so no axis change
is needed: our world is already Z up. Stage IV's ``smpl_world.npz`` uses the same keys, which is
why :func:`read_amass` reads both.

Keys written (format version 1)::

    poses            (T, 72) float64  axis-angle, global_orient then SMPL joints 1..23
                     (T, 156) with ``hands=True``: SMPL+H layout, 22 body joints (66) then
                     30 zero hand joints (90); SMPL's joints 22, 23 (hands) are dropped there
    trans            (T, 3) float64   SMPL ``transl``, metres (not the pelvis position)
    betas            (B,) float64     shape coefficients
    gender           () str           "neutral" | "male" | "female"
    mocap_framerate  () float64       frames per second
    frames           (T,) int64       sequence frame of each row
    surface_model_type () str         "smpl" or "smplh"
    version          () int64         1
    valid, suspect   (T,) bool        the motion's frame flags (``smpl_world.npz``), when given:
                     a frame the body could not be placed in / whose fit a view contradicts
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_npz
from embodmocap.io.npz_file import load_npz
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: Version of the AMASS-style files this module writes.
AMASS_VERSION = 1
#: Axis-angle values per frame in SMPL (24 joints) and SMPL+H (22 body + 30 hand joints) layouts.
SMPL_POSE_DIM = 72
SMPLH_POSE_DIM = 156
_SMPLH_BODY_DIM = 66


def _frames_or_range(frames: NDArray | None, T: int) -> NDArray[np.int64]:
    if frames is None:
        return np.arange(T, dtype=np.int64)
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    if frames.shape != (T,):
        raise ValueError(f"frames must be ({T},), got {frames.shape}")
    return frames


def write_amass(path: str | Path, params: SmplParams, *, frames: NDArray | None = None, hands: bool = False,
                flags: tuple[NDArray, NDArray] | None = None) -> Path:
    """Write ``params`` (world, Z up) as an AMASS-style npz; returns the path.

    Args:
        path: destination ``.npz`` (written atomically).
        params: world SMPL parameters, T frames.
        frames: (T,) sequence frame of each row; default ``0..T-1``.
        hands: write the (T, 156) SMPL+H pose layout (zero hands) instead of SMPL's (T, 72).
        flags: (valid, suspect) (T,) bool each, written as ``valid`` and ``suspect`` (None: not written).
    """
    T = len(params)
    poses = params.poses
    if hands:
        # SMPL+H keeps SMPL's first 22 joints and replaces the two hand joints by 30 finger joints.
        poses = np.concatenate([poses[:, :_SMPLH_BODY_DIM], np.zeros((T, SMPLH_POSE_DIM - _SMPLH_BODY_DIM))], axis=1)
    write_npz(
        path,
        poses=np.asarray(poses, dtype=np.float64),
        trans=np.asarray(params.transl, dtype=np.float64),
        betas=np.asarray(params.betas, dtype=np.float64),
        gender=np.array(params.gender),
        mocap_framerate=np.array(float(params.fps)),
        frames=_frames_or_range(frames, T),
        surface_model_type=np.array("smplh" if hands else "smpl"),
        version=np.array(AMASS_VERSION, dtype=np.int64),
        **_flag_arrays(flags, T),
    )
    log.info("wrote AMASS-style motion %s (%d frames, %d pose values)", path, T, poses.shape[1])
    return Path(path)


def _flag_arrays(flags: tuple[NDArray, NDArray] | None, T: int) -> dict[str, NDArray]:
    if flags is None:
        return {}
    valid, suspect = (np.asarray(x, dtype=bool) for x in flags)
    if valid.shape != (T,) or suspect.shape != (T,):
        raise ValueError(f"flags must be two ({T},) arrays, got {valid.shape}, {suspect.shape}")
    return {"valid": valid, "suspect": suspect}


def read_amass(path: str | Path) -> tuple[SmplParams, NDArray[np.int64]]:
    """Read an AMASS-style npz (ours, Stage IV's ``smpl_world.npz`` or an AMASS file).

    Returns the parameters and the (T,) sequence frames (``0..T-1`` when the file has none).
    SMPL+H poses (T, 156) keep their 22 body joints; SMPL's hand joints 22, 23 are set to zero.
    Raises :class:`InputError` naming the file for a missing key, a wrong shape or NaN values.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "motion file not found", "check the path")
    # Any version: AMASS files from other tools carry none.
    data = load_npz(path, what="AMASS-style motion", fix="write it with poses, trans, betas",
                    required=("poses", "trans", "betas"), versions=None)
    poses = np.asarray(data["poses"], dtype=np.float64)
    trans = np.asarray(data["trans"], dtype=np.float64)
    betas = np.asarray(data["betas"], dtype=np.float64).reshape(-1)
    if poses.ndim != 2 or poses.shape[1] not in (SMPL_POSE_DIM, SMPLH_POSE_DIM) or trans.shape != (len(poses), 3):
        raise InputError(
            path, f"poses {poses.shape} / trans {trans.shape} are not (T, 72 or 156) / (T, 3)",
            "write SMPL (72) or SMPL+H (156) axis-angle poses with one translation per frame",
        )
    if not (np.isfinite(poses).all() and np.isfinite(trans).all() and np.isfinite(betas).all()):
        raise InputError(path, "poses, trans or betas contain NaN or infinite values", "fix the fit that wrote it")
    if poses.shape[1] == SMPLH_POSE_DIM:
        poses = np.concatenate([poses[:, :_SMPLH_BODY_DIM], np.zeros((len(poses), 6))], axis=1)
    fps_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data), None)
    fps = float(data[fps_key]) if fps_key else 30.0
    if not fps > 0:
        raise InputError(path, f"frame rate {fps} is not positive", "write a positive mocap_framerate")
    gender = str(data["gender"]) if "gender" in data else "neutral"
    frames = data.get("frames")
    if frames is not None and np.asarray(frames).shape != (len(poses),):
        raise InputError(path, f"frames {np.asarray(frames).shape} does not match {len(poses)} poses", "write one frame per pose")
    params = SmplParams(betas=betas, global_orient=poses[:, :3], body_pose=poses[:, 3:], transl=trans, fps=fps, gender=gender)
    return params, _frames_or_range(frames, len(poses))
