"""World SMPL motion files (``smpl_world.npz``, ``smpl_fit.npz``): AMASS-like npz, version 1.

Keys (see docs/formats.md, "Stage IV outputs"):

    version          () int64, 1
    poses            (T, 72) float64 axis-angle: global_orient then joints 1..23, world frame
    trans            (T, 3) float64 SMPL ``transl``, metres (not the pelvis position)
    betas            (B,) float64 shape, one set for the sequence
    gender           () str
    mocap_framerate  () float64 frames per second (AMASS's name)
    framerate        () float64 the same value (the name issue 6 of the tracker uses)
    frames           (T,) int64 sequence frame of each row
    valid            (T,) bool whether the body could be placed in that frame (optional; absent =
                     all True): frames without enough triangulated joints are fitted from their
                     neighbours and flagged False

Per-frame quality (optional, all or none; Stage IV writes them, :mod:`embodmocap.motion.quality`):

    suspect          (T,) bool a limb joint further than the threshold from every view that sees it
    limb_off_m       (T,) float64 that distance of the worst limb joint, metres (NaN: none seen)
    reproj_px        (T, V) float64 each view's median reprojection error, pixels (NaN: none)
    kp3d_err_m       (T,) float64 median distance to the triangulated keypoints, metres (NaN: none)
    quality_views    (V,) str the views, the columns of reproj_px

AMASS's own files use the same key names (``poses``, ``trans``, ``betas``, ``gender``,
``mocap_framerate``), so tools that read AMASS SMPL motion read these.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_npz
from embodmocap.io.npz_file import load_npz
from embodmocap.types import SmplParams

SMPL_FILE_VERSION = 1
_KEYS = ("poses", "trans", "betas", "gender", "mocap_framerate", "frames")


#: The per-frame quality keys (all present or none).
QUALITY_KEYS = ("suspect", "limb_off_m", "reproj_px", "kp3d_err_m", "quality_views")


def write_smpl_npz(path: str | Path, params: SmplParams, frames: NDArray | None = None,
                   valid: NDArray | None = None, quality: Mapping[str, NDArray] | None = None,
                   one_view: bool = False) -> Path:
    """Write ``params`` (world frame) atomically; ``frames`` default to 0..T-1, ``valid`` (T,) bool
    to all True; ``quality``: the per-frame quality keys (:data:`QUALITY_KEYS`; None or empty: none);
    ``one_view``: fitted from one phone (no triangulation), stored as a () bool."""
    T = len(params)
    frames = np.arange(T, dtype=np.int64) if frames is None else np.asarray(frames, dtype=np.int64)
    if frames.shape != (T,):
        raise ValueError(f"frames must be ({T},), got {frames.shape}")
    valid = np.ones(T, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if valid.shape != (T,):
        raise ValueError(f"valid must be ({T},), got {valid.shape}")
    quality = dict(quality or {})
    if quality:
        if set(quality) != set(QUALITY_KEYS):
            raise ValueError(f"quality needs the keys {QUALITY_KEYS}, got {sorted(quality)}")
        for k in QUALITY_KEYS[:-1]:
            if len(quality[k]) != T:
                raise ValueError(f"quality {k} must have {T} rows, got {np.shape(quality[k])}")
    write_npz(path, version=np.int64(SMPL_FILE_VERSION), poses=params.poses, trans=np.asarray(params.transl),
              betas=np.asarray(params.betas), gender=np.array(params.gender),
              mocap_framerate=np.float64(params.fps), framerate=np.float64(params.fps), frames=frames, valid=valid,
              one_view=np.bool_(one_view), **quality)
    return Path(path)


def read_smpl_quality(path: str | Path) -> dict[str, NDArray]:
    """The per-frame quality keys of a world SMPL motion file (:data:`QUALITY_KEYS`); empty for a
    file written without them.

    Raises:
        InputError: as :func:`read_smpl_npz`, or only some of the keys, or rows that do not match.
    """
    params, _ = read_smpl_npz(path)
    data = load_npz(path, what="SMPL motion file", fix="", versions=None)
    have = [k for k in QUALITY_KEYS if k in data]
    if not have:
        return {}
    fix = "re-run `embodmocap motion` to write it again"
    if len(have) != len(QUALITY_KEYS):
        raise InputError(path, f"has the quality keys {have} but not {sorted(set(QUALITY_KEYS) - set(have))}", fix)
    out = {k: np.asarray(data[k]) for k in QUALITY_KEYS}
    if any(len(out[k]) != len(params) for k in QUALITY_KEYS[:-1]):
        raise InputError(path, f"quality keys do not have one row per frame ({len(params)})", fix)
    out["suspect"] = out["suspect"].astype(bool)
    return out


def read_smpl_suspect(path: str | Path) -> NDArray[np.bool_]:
    """(T,) the ``suspect`` flags of a world SMPL motion file (all False when the file has none)."""
    q = read_smpl_quality(path)
    return q["suspect"] if q else np.zeros(len(read_smpl_npz(path)[0]), dtype=bool)


def read_smpl_one_view(path: str | Path) -> bool:
    """Whether a world SMPL motion file was fitted from one phone (False for files without the key)."""
    data = load_npz(path, what="SMPL motion file", fix="", versions=None)
    return bool(data["one_view"]) if "one_view" in data else False


def read_smpl_valid(path: str | Path) -> NDArray[np.bool_]:
    """(T,) the ``valid`` flags of a world SMPL motion file (all True when the file has none).

    Raises:
        InputError: as :func:`read_smpl_npz`, or a ``valid`` array of the wrong shape.
    """
    params, _ = read_smpl_npz(path)
    data = load_npz(path, what="SMPL motion file", fix="", versions=None)
    if "valid" not in data:
        return np.ones(len(params), dtype=bool)
    valid = data["valid"]
    if valid.shape != (len(params),):
        raise InputError(path, f"valid has shape {valid.shape}, expected ({len(params)},)",
                         "re-run `embodmocap motion` to write it again")
    return valid.astype(bool)


def read_smpl_npz(path: str | Path) -> tuple[SmplParams, NDArray[np.int64]]:
    """Read a world SMPL motion file.

    Returns:
        (params, frames (T,) sequence frames).

    Raises:
        InputError: missing or unreadable file, missing keys, wrong shapes, non-finite values.
    """
    path = Path(path)
    fix = "re-run `embodmocap motion` to write it again"
    if not path.is_file():
        raise InputError(path, "SMPL motion file not found", "run `embodmocap motion SESSION --seq NAME` first")
    data = load_npz(path, what="SMPL motion file", required=_KEYS, versions=(SMPL_FILE_VERSION,),
                    fix="expected poses (T,72), trans (T,3), betas (B,), gender, mocap_framerate, frames (T,); " + fix)
    poses, trans, betas = data["poses"], data["trans"], data["betas"]
    T = len(poses)
    if poses.shape != (T, 72) or trans.shape != (T, 3) or betas.ndim != 1 or data["frames"].shape != (T,):
        raise InputError(path, f"shapes poses {poses.shape}, trans {trans.shape}, betas {betas.shape}, "
                         f"frames {data['frames'].shape} do not match the SMPL layout",
                         "expected poses (T,72), trans (T,3), betas (B,), frames (T,)")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all() and np.isfinite(betas).all()):
        raise InputError(path, "non-finite values in the motion", fix)
    params = SmplParams(betas, poses[:, :3], poses[:, 3:], trans, fps=float(data["mocap_framerate"]),
                        gender=str(data["gender"]))
    return params, data["frames"].astype(np.int64)
