"""Limbs of the fitted body that a view's depth map sees as empty space (issue 29, item 5).

A limb fitted on the right ray of one view at the wrong depth, or held by smoothness where one
view alone sees it, reprojects well and sits close to the view's rays, so the keypoint figures of
:mod:`embodmocap.motion.quality` cannot tell it from a right one. Each phone also measured depth:
a surface point of the fitted body that lies well in front of what the view's depth map saw at its
pixel is in space the sensor saw through, so the body is not there. The test is one-sided on
purpose: a body point *behind* the measured surface may be hidden by something in front of it (a
chair, the other arm), which says nothing.

Per frame, view and limb part (:data:`LIMB_PARTS`, the mesh vertices skinned mostly to those SMPL
joints) the share of the part's vertices that project into the view's depth map and lie more than
``tol_m`` in front of the nearest depth in a ``window`` x ``window`` pixel neighbourhood (the
nearest, so that a vertex a pixel off a thin limb's silhouette does not count; depth 0 is
unmeasured and never counts). Hands and feet are left out: the detector's keypoints do not fix
their turn, and a right fit's hand lies outside the measured hand often.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

#: Limb parts judged, as the SMPL joints their vertices are skinned to most: left/right thigh,
#: lower leg, upper arm, forearm.
LIMB_PARTS: dict[str, tuple[int, ...]] = {
    "left_thigh": (1,), "right_thigh": (2,), "left_lower_leg": (4,), "right_lower_leg": (5,),
    "left_upper_arm": (16,), "right_upper_arm": (17,), "left_forearm": (18,), "right_forearm": (19,)}

#: A part with fewer of its vertices inside a view's depth map is not judged in that view.
MIN_VERTICES = 20


def vertex_parts(lbs_weights: NDArray) -> NDArray:
    """(N,) int: each vertex's index into :data:`LIMB_PARTS`, -1 for the rest of the body
    (``lbs_weights`` (N, 24): the vertex's skinning weights)."""
    main = np.asarray(lbs_weights).argmax(axis=1)
    out = np.full(len(main), -1, dtype=np.int64)
    for i, joints in enumerate(LIMB_PARTS.values()):
        out[np.isin(main, joints)] = i
    return out


def free_space_share(vertices: NDArray, parts: NDArray, K: NDArray, T_world_cam: NDArray, rgb_size: tuple[int, int],
                     depth_mm: NDArray, tol_m: float, window: int = 3, chunk: int = 256) -> NDArray:
    """(T, P) the share of each limb part's vertices that one view's depth sees as empty space.

    Args:
        vertices: (T, N, 3) the fitted body's vertices, world metres; parts: (N,) :func:`vertex_parts`;
        K: (3, 3) RGB intrinsics; T_world_cam: (T, 4, 4) the view's cameras (OpenCV);
        rgb_size: (width, height) of the images ``K`` refers to (the depth map covers the same field
            at its own size); depth_mm: (T', h, w) uint16 millimetres, 0 = unmeasured (Stage II's
            ``depth.npy``, memory-mapped is fine; frames from T' on are not judged);
        tol_m: how far in front of the measured surface counts; window: the neighbourhood (depth
            pixels) whose nearest depth a vertex is held against; chunk: frames read at once.

    Returns:
        (T, P) share in [0, 1]; NaN where fewer than :data:`MIN_VERTICES` of the part were measured.
    """
    T, P = len(vertices), len(LIMB_PARTS)
    out = np.full((T, P), np.nan)
    sel = parts >= 0
    pv = parts[sel]
    W, H = rgb_size
    for t0 in range(0, min(T, len(depth_mm)), chunk):
        t1 = min(T, len(depth_mm), t0 + chunk)
        d = np.asarray(depth_mm[t0:t1])
        h, w = d.shape[1:]
        Tw = np.asarray(T_world_cam[t0:t1])
        cam = (vertices[t0:t1][:, sel] - Tw[:, None, :3, 3]) @ Tw[:, :3, :3]  # (t, n, 3) camera frame
        z = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.floor((K[0, 0] * cam[..., 0] / z + K[0, 2]) * (w / W))
            y = np.floor((K[1, 1] * cam[..., 1] / z + K[1, 2]) * (h / H))
        inside = (z > 0) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
        ti, xi, yi = (np.broadcast_to(np.arange(t1 - t0)[:, None], z.shape)[inside], x[inside].astype(np.int64),
                      y[inside].astype(np.int64))
        # The nearest measured depth in the window around each vertex's pixel (0, unmeasured, never counts).
        near = np.full(len(ti), np.iinfo(np.uint16).max, dtype=np.uint16)
        r = window // 2
        for dy in range(-r, window - r):
            for dx in range(-r, window - r):
                got = d[ti, np.clip(yi + dy, 0, h - 1), np.clip(xi + dx, 0, w - 1)]
                near = np.where(got > 0, np.minimum(near, got), near)
        obs = np.full(z.shape, np.iinfo(np.uint16).max, dtype=np.uint16)
        obs[inside] = near
        measured = obs < np.iinfo(np.uint16).max
        empty = measured & (obs / 1000.0 - z > tol_m)
        onehot = np.eye(P)[pv]  # (n, P) the vertices of each part
        n, k = measured @ onehot, empty @ onehot
        out[t0:t1] = np.where(n >= MIN_VERTICES, k / np.maximum(n, 1), np.nan)
    return out


def free_space_limbs(vertices: NDArray, lbs_weights: NDArray, K: NDArray, T_world_cam: NDArray,
                     rgb_sizes: Sequence[tuple[int, int]], depth_mm: Sequence[NDArray | None],
                     tol_m: float, window: int = 3) -> NDArray:
    """(T, P) the largest share over the views of each limb part's vertices in measured empty space
    (:func:`free_space_share`; NaN: no view measured the part). ``K`` (V, 3, 3), ``T_world_cam``
    (T, V, 4, 4), ``rgb_sizes`` and ``depth_mm`` one per view (None: the view has no depth)."""
    parts = vertex_parts(lbs_weights)
    shares = [free_space_share(vertices, parts, K[i], T_world_cam[:, i], rgb_sizes[i], d, tol_m, window)
              for i, d in enumerate(depth_mm) if d is not None]
    if not shares:
        return np.full((len(vertices), len(LIMB_PARTS)), np.nan)
    s = np.stack(shares)
    return np.where(np.isfinite(s).any(0), np.nanmax(np.nan_to_num(s, nan=-1.0), axis=0), np.nan)
