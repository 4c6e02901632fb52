"""Depth-edge pixels of a depth map: a stand-in for the LiDAR confidence map a capture lacks.

ARKit marks a depth pixel low-confidence mostly where the surface jumps (object silhouettes, the
person against the wall) or is seen at a grazing angle: there a LiDAR sample mixes two surfaces
and lands between them ("flying pixels"). Stray Scanner and Record3D export that confidence map;
a Spectacular AI recording does not. For those, the same pixels are found from the depth alone: a
pixel whose 3x3 neighbourhood spans a large fraction of its own depth sits on an edge.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def relative_spread3(depth_m: NDArray) -> NDArray[np.float32]:
    """(h, w) ``(max - min) / depth`` over each pixel's 3x3 neighbourhood (image borders replicated).

    Pixels without depth (0 or not finite) are ``inf``; they are left out of their neighbours'
    windows (a hole is a missing reading, not a surface, and ARKit's dense depth has few).
    """
    d = np.asarray(depth_m, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth_m must be (h, w), got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    hi_src = np.where(valid, d, np.float32(0.0))  # missing neighbours never win the max or the min
    lo_src = np.where(valid, d, np.float32(np.inf))
    pad_hi = np.pad(hi_src, 1, mode="edge")
    pad_lo = np.pad(lo_src, 1, mode="edge")
    win_hi = np.lib.stride_tricks.sliding_window_view(pad_hi, (3, 3))  # (h, w, 3, 3), a view: no copy
    win_lo = np.lib.stride_tricks.sliding_window_view(pad_lo, (3, 3))
    hi = win_hi.max(axis=(2, 3))
    lo = win_lo.min(axis=(2, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = (hi - lo) / np.where(valid, d, np.float32(1.0))
    return np.where(valid & np.isfinite(spread), spread, np.float32(np.inf)).astype(np.float32)


def drop_depth_edges(depth_m: NDArray, max_rel_spread: float) -> NDArray[np.float32]:
    """(h, w) float32 depth with depth-edge pixels set to 0 (see the module docstring).

    Args:
        depth_m: (h, w) depth in metres, 0 (or not finite) where there is none. Not modified.
        max_rel_spread: pixels whose 3x3 relative spread exceeds this are dropped; 0 or less
            keeps every pixel (only non-finite values become 0).
    """
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if max_rel_spread <= 0:
        return d
    return np.where(relative_spread3(d) <= max_rel_spread, d, np.float32(0.0)).astype(np.float32)
