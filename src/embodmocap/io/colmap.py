"""COLMAP's pixel convention and camera parameters, converted to and from this package's.

This package puts the centre of the top-left pixel at (0, 0); COLMAP puts it at (0.5, 0.5). So
COLMAP's principal point is ours plus 0.5 and COLMAP keypoint coordinates are ours plus 0.5.
Focal lengths are the same. Stage I writes COLMAP models with these conversions and Stage III
reads them back with them, so they live here, in one place both use.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.types import Intrinsics

#: COLMAP's pixel coordinates minus ours: COLMAP puts the top-left pixel's centre at (0.5, 0.5).
COLMAP_PIXEL_OFFSET = 0.5


def colmap_camera_params(intrinsics: Intrinsics) -> NDArray[np.float64]:
    """COLMAP ``PINHOLE`` parameters ``[fx, fy, cx, cy]`` of our intrinsics (principal point + 0.5)."""
    k = intrinsics
    return np.array([k.fx, k.fy, k.cx + COLMAP_PIXEL_OFFSET, k.cy + COLMAP_PIXEL_OFFSET])


def intrinsics_from_colmap(params: Sequence[float], width: int, height: int) -> Intrinsics:
    """Our intrinsics from COLMAP ``PINHOLE`` parameters ``[fx, fy, cx, cy]`` (principal point - 0.5)."""
    fx, fy, cx, cy = (float(p) for p in params)
    return Intrinsics(fx, fy, cx - COLMAP_PIXEL_OFFSET, cy - COLMAP_PIXEL_OFFSET, int(width), int(height))


def pixels_from_colmap(xy: NDArray) -> NDArray[np.float64]:
    """(..., 2) COLMAP pixel coordinates (keypoints, projections) -> ours (top-left centre at 0, 0)."""
    return np.asarray(xy, dtype=np.float64) - COLMAP_PIXEL_OFFSET


def pixels_to_colmap(xy: NDArray) -> NDArray[np.float64]:
    """(..., 2) our pixel coordinates -> COLMAP's (top-left centre at 0.5, 0.5)."""
    return np.asarray(xy, dtype=np.float64) + COLMAP_PIXEL_OFFSET
