"""Body surface a view measured at its detections that the fitted body leaves unexplained (issue 29, item 5).

Where a view detects a joint with confidence, its depth map measured the person's surface around
that pixel. A right fit has its mesh there (within the limb's thickness and the sensor's noise);
a fit whose wrist or ankle lies 15-20 cm along the view's ray (the view alone sees it, so the
keypoint figures cannot tell: the joint reprojects well) or beside it leaves that measured surface
far from every one of its vertices. The test is label-free on purpose: it asks whether *any* part
of the fitted body is where the view measured the person, so a detection the label tracker gave to
the other side, or that the fit followed to the other leg, says nothing against a fit that has a
limb there; and exchanged legs, which occupy the same space, pass (nothing in a view's depth
separates them).

Per frame, view and judged joint (:data:`SURFACE_JOINTS`, detected by the view's detector at
``min_conf`` or more): the depth pixels in a ``window`` x ``window`` neighbourhood of the
detection that the view's person mask covers (depth 0, unmeasured, never counts), lifted into the
world with the view's camera; the figure is the ``quantile`` of their distances to the nearest
fitted vertex (a low quantile, so that a window reaching over the limb's edge onto the mask's
bleed or another surface does not count: most of the measured points must be unexplained).

The same measured surface also bounds a joint from the front (:func:`joint_in_front`): a fitted
joint that a view detects on its ray lies inside the limb, behind the surface the view measured
around it; one well in front of that surface is in space the view saw through. The free-space test
(:mod:`embodmocap.motion.free_space`) asks this of the limbs' vertices and leaves the hands out
(the detector does not fix their turn); the joint itself has no turn, so a wrist held 10-15 cm
toward the one view that sees it is caught here.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

#: COCO-17 joints whose measured surface is judged: elbows, wrists, knees, ankles (the limb ends
#: a single view can hold at the wrong depth; the shoulders and hips sit on the torso, which the
#: fit places from both views).
SURFACE_JOINTS: tuple[int, ...] = (7, 8, 9, 10, 13, 14, 15, 16)

#: A detection with fewer measured person pixels in its window is not judged.
MIN_POINTS = 3

#: :func:`joint_in_front` judges a view where the fitted joint lies within this (metres) of the
#: view's ray through its detection (the view sees the joint where the fit has it, but for depth).
ON_RAY_M = 0.08


def surface_points(kp2d: NDArray, K: NDArray, T_world_cam: NDArray, rgb_size: tuple[int, int], depth_mm: NDArray,
                   masks: NDArray, min_conf: float, window: int) -> tuple[NDArray, NDArray]:
    """The person surface one view measured around its detections, in the world.

    Args:
        kp2d: (T, J, 3) the view's detections (pixels of the RGB image, confidence);
        K: (3, 3) RGB intrinsics; T_world_cam: (T, 4, 4) the view's cameras (OpenCV);
        rgb_size: (width, height) of the images ``K`` and the masks refer to (the depth map covers
            the same field at its own size); depth_mm: (T, h, w) uint16 millimetres, 0 = unmeasured
            (memory-mapped is fine); masks: (T, height, ceil(width / 8)) uint8, the person masks
            packed along the width (Stage II's ``masks.npy``, :func:`numpy.packbits`);
        min_conf: detections below it are not judged; window: the neighbourhood, depth pixels.

    Returns:
        ``(points, ok, z)``: (T, J, window**2, 3) world points, (T, J, window**2) bool, the
        measured person pixels, and their depth along the camera's axis, metres (``points`` and
        ``z`` are undefined where ``ok`` is False).
    """
    T = len(kp2d)
    W, H = rgb_size
    h, w = depth_mm.shape[1:]
    r = window // 2
    oy, ox = np.mgrid[-r:window - r, -r:window - r]
    with np.errstate(invalid="ignore"):
        xi = np.floor(np.nan_to_num(kp2d[..., 0], nan=-1e9) * (w / W))[..., None] + ox.ravel()  # (T, J, n)
        yi = np.floor(np.nan_to_num(kp2d[..., 1], nan=-1e9) * (h / H))[..., None] + oy.ravel()
    ok = (np.nan_to_num(kp2d[..., 2])[..., None] >= min_conf) & (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    xi, yi = np.where(ok, xi, 0).astype(np.int64), np.where(ok, yi, 0).astype(np.int64)
    ti = np.broadcast_to(np.arange(T)[:, None, None], xi.shape)
    z = depth_mm[ti, yi, xi] / 1000.0  # a gather: a memory-mapped stack is read where needed
    # The person mask at the depth pixel's centre (the mask is at the RGB image's size).
    X = np.minimum(((xi + 0.5) * (W / w)).astype(np.int64), W - 1)
    Y = np.minimum(((yi + 0.5) * (H / h)).astype(np.int64), H - 1)
    person = (masks[ti, Y, X // 8] >> (7 - X % 8)) & 1
    ok &= (z > 0) & (person > 0)
    pix = np.stack([(xi + 0.5) * (W / w), (yi + 0.5) * (H / h), np.ones(xi.shape)], axis=-1)
    cam = (pix @ np.linalg.inv(K).T) * z[..., None]
    points = np.einsum("tab,tjnb->tjna", T_world_cam[:T, :3, :3], cam) + T_world_cam[:T, None, None, :3, 3]
    return points, ok, z


def unexplained_surface(vertices: NDArray, K: NDArray, T_world_cam: NDArray, rgb_sizes: Sequence[tuple[int, int]],
                        depth_mm: Sequence[NDArray | None], masks: Sequence[NDArray | None], kp2d: NDArray,
                        min_conf: float, window: int = 5, quantile: float = 0.25) -> NDArray:
    """(T, V, J) how far (metres) the person surface each view measured around its detection of
    each :data:`SURFACE_JOINTS` joint lies from the fitted body (the module docstring); NaN where
    not judged (a detection under ``min_conf``, fewer than :data:`MIN_POINTS` measured person
    pixels, a view without depth or masks).

    Args:
        vertices: (T, N, 3) the fitted body's vertices, world metres; K: (V, 3, 3);
        T_world_cam: (T, V, 4, 4); rgb_sizes, depth_mm, masks: one per view (as
        :func:`surface_points`; None: the view has none); kp2d: (T, V, 17, 3) the views' detections;
        window: depth pixels; quantile: of the measured points' distances to the body.
    """
    from scipy.spatial import cKDTree

    T, V = kp2d.shape[:2]
    joints = list(SURFACE_JOINTS)
    out = np.full((T, V, len(joints)), np.nan)
    pts, oks = [], []
    for v in range(V):
        if depth_mm[v] is None or masks[v] is None:
            pts.append(None), oks.append(None)
            continue
        n = min(T, len(depth_mm[v]), len(masks[v]))
        p, ok, _ = surface_points(kp2d[:n, v][:, joints], K[v], T_world_cam[:n, v], rgb_sizes[v], depth_mm[v], masks[v],
                               min_conf, window)
        pts.append(p), oks.append(ok)
    dist = [None if p is None else np.full(o.shape, np.inf) for p, o in zip(pts, oks)]  # (n, J, window**2) each
    for t in range(T):
        sel = [v for v in range(V) if pts[v] is not None and t < len(pts[v]) and oks[v][t].any()]
        if sel:
            tree = cKDTree(np.asarray(vertices[t], dtype=np.float64), balanced_tree=False, compact_nodes=False)
            for v in sel:
                dist[v][t][oks[v][t]] = tree.query(pts[v][t][oks[v][t]])[0]
    for v in range(V):
        if dist[v] is not None:
            out[:len(dist[v]), v] = _quantile_of_finite(dist[v], oks[v].sum(-1), quantile)
    return out


def _quantile_of_finite(d: NDArray, n: NDArray, q: float) -> NDArray:
    """The ``q`` quantile (linear, as :func:`numpy.quantile`) along the last axis of ``d`` over its
    ``n`` finite values (the rest +inf); NaN where ``n`` < :data:`MIN_POINTS`. Vectorised: a
    per-row ``nanquantile`` costs more than the whole test."""
    s = np.sort(d, axis=-1)
    pos = q * np.maximum(n - 1, 0)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, np.maximum(n - 1, 0))
    a = np.take_along_axis(s, lo[..., None], -1)[..., 0]
    b = np.take_along_axis(s, hi[..., None], -1)[..., 0]
    with np.errstate(invalid="ignore"):
        val = a + (b - a) * (pos - lo)
    return np.where(n >= MIN_POINTS, val, np.nan)


def joint_in_front(fitted_kp: NDArray, K: NDArray, T_world_cam: NDArray, rgb_sizes: Sequence[tuple[int, int]],
                   depth_mm: Sequence[NDArray | None], masks: Sequence[NDArray | None], used2d: NDArray,
                   raw2d: NDArray, min_conf: float, window: int = 7) -> NDArray:
    """(T, V, J) how far (metres) each :data:`SURFACE_JOINTS` joint of the fit lies in front of the
    person surface each view measured around its pixel (the median depth of the person pixels in
    a ``window`` x ``window`` depth neighbourhood, less the joint's depth; positive: nearer the
    camera than anything the view measured there); NaN where not judged: the view detects the
    joint (the detector's or the fit's label, ``raw2d`` / ``used2d`` (T, V, 17, 3)) at ``min_conf``
    or more with the fitted joint within :data:`ON_RAY_M` of that detection's ray, and measured at
    least :data:`MIN_POINTS` person pixels there. ``fitted_kp`` (T, 17, 3) world metres; the rest
    as :func:`unexplained_surface`."""
    from embodmocap.motion.quality import ray_distance

    T, V = used2d.shape[:2]
    joints = list(SURFACE_JOINTS)
    out = np.full((T, V, len(joints)), np.nan)
    X = np.broadcast_to(fitted_kp[:, None, joints], (T, V, len(joints), 3))
    seen = np.zeros((T, V, len(joints)), dtype=bool)
    for k in (raw2d, used2d):
        k = k[:, :, joints]
        r = ray_distance(X, K, T_world_cam, np.nan_to_num(k[..., :2]))
        seen |= (np.nan_to_num(k[..., 2]) >= min_conf) & (r < ON_RAY_M)
    Rt = np.swapaxes(T_world_cam[..., :3, :3], -1, -2)
    cam = np.einsum("tvab,tvjb->tvja", Rt, X - T_world_cam[:, :, None, :3, 3])  # (T, V, J, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.einsum("vab,tvjb->tvja", K, cam)
        uv = uv[..., :2] / uv[..., 2:]
    for v in range(V):
        if depth_mm[v] is None or masks[v] is None:
            continue
        n = min(T, len(depth_mm[v]), len(masks[v]))
        pix = np.concatenate([uv[:n, v], np.where(seen[:n, v] & (cam[:n, v, :, 2] > 0), 1.0, 0.0)[..., None]], axis=-1)
        _, ok, z = surface_points(pix, K[v], T_world_cam[:n, v], rgb_sizes[v], depth_mm[v], masks[v], 0.5, window)
        judged = ok.sum(-1) >= MIN_POINTS
        with np.errstate(invalid="ignore"):
            med = np.nanmedian(np.where(ok, z, np.nan)[judged], axis=-1)
        block = np.full((n, len(joints)), np.nan)
        block[judged] = med - cam[:n, v][judged][:, 2]
        out[:n, v] = block
    return out
