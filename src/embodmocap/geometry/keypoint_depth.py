"""Keypoints with depth: a depth map read at RGB pixels, and pixels lifted to camera points.

Shared by Stage III (cross-view track pairs, :mod:`embodmocap.calibrate.losses`) and Stage IV's
one-view path (one view's keypoints lifted with its LiDAR depth, :mod:`embodmocap.motion.lift`).
Camera points are OpenCV (x right, y down, z forward), metres; pixel centres at integer
coordinates.
"""

from __future__ import annotations

import warnings
from typing import Callable

import numpy as np
from numpy.typing import NDArray

#: Approximate depth of each COCO-17 joint centre behind the body surface seen at its pixel,
#: metres (index = COCO joint). The depth map at a keypoint pixel gives the surface *in front of*
#: the joint; both views see different surfaces, so the raw back-projections of one joint differ by
#: about a limb thickness. Pushing each point this far further along its own viewing ray puts both
#: near the joint centre, whatever the body's orientation (a per-joint median offset in the world
#: would only be right while the performer does not turn).
JOINT_DEPTH_BEHIND_SURFACE_M: tuple[float, ...] = (
    0.0, 0.0, 0.0, 0.0, 0.0,  # nose, eyes, ears: surface landmarks
    0.05, 0.05,  # shoulders
    0.04, 0.04,  # elbows
    0.03, 0.03,  # wrists
    0.08, 0.08,  # hips
    0.05, 0.05,  # knees
    0.04, 0.04,  # ankles
)


def sample_depth(
    depth_at: Callable[[int], NDArray],
    frames: NDArray,
    xy: NDArray,
    rgb_size: tuple[int, int],
    window: int = 1,
) -> NDArray[np.float64]:
    """Depth (N,) in metres at RGB pixels ``xy`` (N, 2) of ``frames`` (N,); 0 where invalid.

    depth_at(t) -> (h, w) float metres (0 = invalid) of sequence frame t, at depth resolution.
    rgb_size: (width, height) of the RGB images ``xy`` refers to. The pixel is rescaled to the
    depth grid (centres at integers in both) and the median of the valid values in a
    (2 window + 1)^2 neighbourhood is taken, so one missing LiDAR sample does not lose a pair.
    """
    frames = np.asarray(frames, dtype=np.int64)
    xy = np.asarray(xy, dtype=np.float64)
    out = np.zeros(len(frames))
    W, H = rgb_size
    offs = np.arange(-window, window + 1)
    for t in np.unique(frames):  # one depth read per frame, vectorised over its pixels
        sel = np.nonzero(frames == t)[0]
        d = np.asarray(depth_at(int(t)), dtype=np.float64)
        h, w = d.shape
        u = np.rint((xy[sel, 0] + 0.5) * w / W - 0.5).astype(np.int64)
        v = np.rint((xy[sel, 1] + 0.5) * h / H - 0.5).astype(np.int64)
        uu = np.clip(u[:, None, None] + offs[None, None, :], 0, w - 1)
        vv = np.clip(v[:, None, None] + offs[None, :, None], 0, h - 1)
        patch = d[vv, uu].reshape(len(sel), -1)
        patch = np.where((patch > 0) & np.isfinite(patch), patch, np.nan)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        with warnings.catch_warnings():  # an all-invalid patch is expected, not a problem
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(patch, axis=1)
        out[sel] = np.where(inside & np.isfinite(med), med, 0.0)
    return out


def backproject(xy: NDArray, depth: NDArray, K: NDArray, behind_surface_m: NDArray | float = 0.0) -> NDArray:
    """Pixels (N, 2) with z-depth (N,) -> camera points (N, 3), pushed ``behind_surface_m`` along the ray."""
    xy = np.asarray(xy, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    rays = np.stack([(xy[:, 0] - K[0, 2]) / K[0, 0], (xy[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(xy))], -1)
    p = rays * np.asarray(depth, dtype=np.float64)[:, None]
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return p + unit * np.asarray(behind_surface_m, dtype=np.float64).reshape(-1, 1)
