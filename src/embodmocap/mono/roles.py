"""The monocular pipeline's two roles and their backends (like perception's roles).

=========== ====================== ======================================================
role        protocol               backends (``embodmocap mono`` options)
=========== ====================== ======================================================
scene       :class:`SceneModel`    ``precomputed`` (npz per chunk, Pi3 layout), ``vio``
human       :class:`HumanModel`    ``precomputed`` (camera-space SMPL npz), ``prior``
=========== ====================== ======================================================

A scene model gives, per chunk of frames, camera-to-world poses (N, 4, 4), local point maps
(N, H, W, 3) and confidences (N, H, W) in an arbitrary scale and frame of its own
(:class:`~embodmocap.mono.files.ChunkPrediction`); a human model gives camera-space SMPL per frame
(:class:`~embodmocap.mono.files.HumanSeq`). Backends read files only: models (Pi3, VGGT, MASt3R,
VIMO, ...) run elsewhere and their outputs are brought in the documented layouts.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from embodmocap.mono.files import ChunkPrediction, HumanSeq, chunk_file_name, human_from_rows, read_chunk, read_human_npz


@runtime_checkable
class SceneModel(Protocol):
    """Cameras and point maps of a chunk of consecutive frames."""

    name: str

    def predict(self, frames: NDArray[np.int64]) -> ChunkPrediction:
        """The chunk's prediction for sequence ``frames`` (N,), in time order."""
        ...


@runtime_checkable
class HumanModel(Protocol):
    """Camera-space SMPL per frame."""

    name: str

    def estimate(self, T: int) -> HumanSeq:
        """Estimates for sequence frames ``0..T-1`` (frames without one: ``valid`` False)."""
        ...


class PrecomputedScene:
    """Reads ``<folder>/chunk_<first frame:06d>.npz`` (see :func:`~embodmocap.mono.files.read_chunk`)."""

    name = "precomputed"

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def predict(self, frames: NDArray[np.int64]) -> ChunkPrediction:
        return read_chunk(self.folder / chunk_file_name(int(frames[0])), np.asarray(frames, dtype=np.int64))


class VioScene:
    """The phone's own metric, gravity-aligned VIO poses and its depth back-projected as point maps
    (confidence 1 where there is depth): what a perfect metric scene model would give (ablation).

    Args:
        T_world_cam: (T, 4, 4) Stage II's VIO poses.
        K_depth: (3, 3) intrinsics of the depth maps.
        depth_path: Stage II's ``depth.npy`` ((T, h, w) uint16 mm).
    """

    name = "vio"

    def __init__(self, T_world_cam: NDArray, K_depth: NDArray, depth_path: str | Path) -> None:
        self.T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        self.K = np.asarray(K_depth, dtype=np.float64)
        self.depth = np.load(depth_path, mmap_mode="r")

    def predict(self, frames: NDArray[np.int64]) -> ChunkPrediction:
        d = np.asarray(self.depth[frames], dtype=np.float32) / 1000.0  # (N, h, w) metres
        N, h, w = d.shape
        u = (np.arange(w) - self.K[0, 2]) / self.K[0, 0]
        v = (np.arange(h) - self.K[1, 2]) / self.K[1, 1]
        pts = np.empty((N, h, w, 3), dtype=np.float32)
        pts[..., 0] = u[None, None, :] * d
        pts[..., 1] = v[None, :, None] * d
        pts[..., 2] = d
        return ChunkPrediction(np.asarray(frames, dtype=np.int64), self.T_world_cam[frames], pts,
                               (d > 0).astype(np.float32), metric=True)


class PriorHuman:
    """Stage II's camera-space body prior (``<view>/body_prior.npz``, one row per sequence frame)."""

    name = "prior"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def estimate(self, T: int) -> HumanSeq:
        from embodmocap.io.body_prior import read_body_prior

        p = read_body_prior(self.path)
        keep = p.frame_ids < T  # Stage II writes one row per sequence frame; a longer file is cut
        return human_from_rows(self.path, p.frame_ids[keep], p.global_orient_cam[keep], p.body_pose[keep],
                               p.betas[keep], p.transl_cam[keep], T)


class PrecomputedHuman:
    """A camera-space SMPL file (``mono_human.npz``: VIMO / TRAM / GVHMR output; see
    :func:`~embodmocap.mono.files.read_human_npz`)."""

    name = "precomputed"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def estimate(self, T: int) -> HumanSeq:
        return read_human_npz(self.path, T)
