"""The camera-space body prior of one view: what a VIMO/HMR-style regressor gives per frame.

File format (``body_prior.npz``, version 1; see ``docs/formats.md``):

============== ========= ======= ===============================================================
key            shape     dtype   meaning
============== ========= ======= ===============================================================
version        ()        int64   format version, 1
frame_ids      (T,)      int64   frame index (in the view's frame numbering) of each row
global_orient  (T, 3)    float64 root rotation, axis-angle, **camera frame** (OpenCV axes)
body_pose      (T, 69)   float64 23 SMPL body joints x axis-angle (SMPL joint order 1..23)
betas          (T, B)    float64 per-frame shape coefficients (B = 10 usually)
transl         (T, 3)    float64 SMPL ``transl`` in the camera frame, metres (pelvis_cam minus
                                 the rest-pose pelvis offset of that frame's betas)
============== ========= ======= ===============================================================
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_npz
from embodmocap.io.npz_file import load_npz

log = logging.getLogger(__name__)

#: Version of the file this module writes; readers accept this one only.
BODY_PRIOR_VERSION = 1

_KEYS = ("version", "frame_ids", "global_orient", "body_pose", "betas", "transl")


@dataclass(frozen=True)
class BodyPriorSeq:
    """Per-frame camera-space SMPL estimates of one view (arrays read-only).

    Attributes:
        global_orient_cam: (T, 3) axis-angle root rotation in the camera frame (OpenCV axes).
        body_pose: (T, 69) axis-angle of SMPL joints 1..23.
        betas: (T, B) shape coefficients, one set per frame (a regressor sees each frame alone).
        transl_cam: (T, 3) SMPL ``transl`` in the camera frame, metres.
        frame_ids: (T,) frame index of each row.
    """

    global_orient_cam: NDArray[np.float64]
    body_pose: NDArray[np.float64]
    betas: NDArray[np.float64]
    transl_cam: NDArray[np.float64]
    frame_ids: NDArray[np.int64]

    def __post_init__(self) -> None:
        for name in ("global_orient_cam", "body_pose", "betas", "transl_cam", "frame_ids"):
            dtype = np.int64 if name == "frame_ids" else np.float64
            a = np.array(getattr(self, name), dtype=dtype, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        T = len(self.frame_ids)
        shapes = {
            "global_orient_cam": (T, 3), "body_pose": (T, 69), "transl_cam": (T, 3),
        }
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"{name} must be {shape}, got {getattr(self, name).shape}")
        if self.betas.ndim != 2 or len(self.betas) != T:
            raise ValueError(f"betas must be (T={T}, B), got {self.betas.shape}")
        if self.frame_ids.shape != (T,):
            raise ValueError(f"frame_ids must be (T,), got {self.frame_ids.shape}")

    def __len__(self) -> int:
        return len(self.frame_ids)


def write_body_prior(path: str | Path, prior: BodyPriorSeq) -> Path:
    """Write ``prior`` to ``path`` (npz, atomic); returns the path."""
    path = Path(path)
    write_npz(
        path,
        version=np.int64(BODY_PRIOR_VERSION),
        frame_ids=prior.frame_ids,
        global_orient=prior.global_orient_cam,
        body_pose=prior.body_pose,
        betas=prior.betas,
        transl=prior.transl_cam,
    )
    return path


def read_body_prior(path: str | Path) -> BodyPriorSeq:
    """Read a body prior written by :func:`write_body_prior`.

    Raises:
        InputError: missing or unreadable file, wrong version, missing key, bad shape, non-finite
            values.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "body prior file not found", "run the perception step or give the right path")
    data = load_npz(path, what="body prior", required=_KEYS, versions=(BODY_PRIOR_VERSION,), default_version=None,
                    fix=f"re-create the body prior (keys {list(_KEYS)}, version {BODY_PRIOR_VERSION})")
    try:
        prior = BodyPriorSeq(
            global_orient_cam=data["global_orient"], body_pose=data["body_pose"], betas=data["betas"],
            transl_cam=data["transl"], frame_ids=data["frame_ids"],
        )
    except (ValueError, TypeError) as err:
        raise InputError(path, f"malformed body prior: {err}", "re-create the body prior") from err
    finite = all(np.all(np.isfinite(a)) for a in (prior.global_orient_cam, prior.body_pose, prior.betas, prior.transl_cam))
    if not finite:
        raise InputError(path, "body prior holds NaN or infinite values", "re-create the body prior")
    return prior


def body_priors_by_frame(paths: Mapping[str, Path], T: int, min_fraction: float,
                         label: str = "") -> dict[str, tuple[BodyPriorSeq, NDArray[np.bool_]]]:
    """Stage II's body priors of the views, one row per sequence frame ``0..T-1``.

    Args:
        paths: view -> ``body_prior.npz`` (views whose file does not exist are left out).
        T: frames wanted.
        min_fraction: views whose prior has an estimate on fewer of the frames are left out.
        label: the sequence, for the log line naming a view left out.

    Returns:
        view -> (prior with rows ``0..T-1``, zeros where no estimate; (T,) bool has-estimate).
    """
    found = {}
    for v, path in paths.items():
        if not Path(path).is_file():
            continue
        prior = read_body_prior(path)
        rows = np.full(T, -1)
        idx = np.asarray(prior.frame_ids)
        keep = (idx >= 0) & (idx < T)
        rows[idx[keep]] = np.flatnonzero(keep)
        has = rows >= 0
        # Stage II writes zeros for frames with no estimate.
        r = np.maximum(rows, 0)
        has &= np.any(prior.body_pose[r] != 0, axis=1) | np.any(prior.transl_cam[r] != 0, axis=1)
        if has.mean() < min_fraction:
            log.info("%s %s: body prior covers only %.0f%% of frames; not used", label, v, 100 * has.mean())
            continue
        z = lambda a: np.where(has.reshape((-1,) + (1,) * (a.ndim - 1)), a[r], 0.0)  # noqa: E731
        found[v] = (BodyPriorSeq(z(prior.global_orient_cam), z(prior.body_pose), z(prior.betas), z(prior.transl_cam),
                                 np.arange(T)), has)
    return found
