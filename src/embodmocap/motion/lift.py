"""Stage IV's one-phone path: one view's 2D keypoints lifted into the world with its LiDAR depth.

Two views triangulate each keypoint from two rays. One view has one ray per keypoint, but the phone
measured the depth along it: the view's depth map (Stage II's ``depth.npy``), read around the
keypoint's pixel only where the person mask says the person is (at a silhouette edge the LiDAR mixes
the body with the wall behind it), gives the body surface in front of the joint; the joint centre
lies a limb's half thickness further along the ray
(:data:`~embodmocap.geometry.keypoint_depth.JOINT_DEPTH_BEHIND_SURFACE_M`). The view's world camera
(Stage III) moves the point into the scene's world. The result has the layout of the triangulation
(``keypoints3d.npz``, with ``one_view`` true), so the fit that follows is Stage IV's own.

What one view cannot give, and what takes its place:

- a joint hidden behind another body part reads the depth of what hides it (an arm in front of the
  hip, the torso in front of the far arm): that depth is only a lower bound (a joint is at or behind
  the surface its pixel shows), so an unsure keypoint that breaks its bone is moved back along its
  ray to where its bone reaches it (``behind_occluder``); a point far from the rest of the body is
  dropped here (``max_from_body_m``), one that still breaks a bone length by the fit's bone check,
  and the fit follows the 2D keypoint, smoothness and the prior there;
- a joint outside the mask or hidden by furniture has no depth: no 3D point (short gaps are
  interpolated as the triangulation's are);
- no second view undoes a left/right swap of the detector: only the view's own label tracking
  (its trajectories, and the side of the body its depth puts each arm on:
  :attr:`~embodmocap.motion.label_track.LabelTrackConfig.depth_side_m`).

So one view is less accurate than two (the figures are in BENCHMARKS.md, session 7).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.keypoint_depth import JOINT_DEPTH_BEHIND_SURFACE_M, backproject, sample_depth
from embodmocap.geometry.triangulation import fill_gaps, projection_matrices

#: COCO-17 shoulders and hips: the body's depth a limb point is compared with.
_TORSO = (5, 6, 11, 12)


@dataclass(frozen=True)
class LiftConfig:
    """How one view's keypoints are lifted with its depth (one-phone sequences only)."""

    window_px: int = 1
    """Half size of the depth-pixel patch read around a keypoint (1 = 3x3); the median of its
    valid person pixels is the surface depth."""
    mask_erode_px: int = 1
    """The person mask, resized to the depth grid, is eroded by this many depth pixels: LiDAR
    samples on the silhouette mix the body with the background."""
    max_from_body_m: float = 0.8
    """A keypoint whose depth differs from the frame's torso depth (median of the lifted shoulders
    and hips) by more than this is dropped (the mask let the background or an occluder through)."""
    max_depth_m: float = 6.0
    """Depths beyond this are not trusted (the iPhone LiDAR's range is about 5 m)."""
    behind_surface_m: tuple[float, ...] = JOINT_DEPTH_BEHIND_SURFACE_M
    """Per COCO-17 joint, how far behind the surface seen at its pixel the joint centre lies, m."""
    behind_occluder: bool = True
    """Treat the depth of an unsure keypoint as a lower bound when it breaks a bone: a joint lies at
    or behind the surface its pixel shows, never in front of it. A keypoint below ``trusted_conf``
    whose lifted point is more than ``bone_tol`` off its bone length (from its parent, measured on
    trusted frames) read an occluder (the torso in front of the far arm): it is moved along its
    ray to where the bone reaches it, at or behind the occluder (see :func:`_behind_occluders`)."""
    trusted_conf: float = 0.7
    """Keypoints at or above this 2D confidence are taken as seen (their depth is the joint's);
    bone lengths are measured on them."""
    bone_tol: float = 0.15
    """Relative bone-length error above which an unsure keypoint's depth is taken as an occluder's."""


@dataclass(frozen=True)
class Lifted:
    """One view's keypoints in the world.

    Attributes:
        points: (T, 17, 3) world metres; NaN where there is no depth (short gaps filled).
        conf: (T, 17) the 2D confidence of each lifted point; 0 where none (and where filled).
        filled: (T, 17) True where the point was interpolated over a short gap.
        depth_found: (T, 17) True where a seen keypoint found valid person depth.
        dropped_far: (T, 17) True where its depth was too far from the torso's.
        long_gaps: (joint, first frame, one past the last) runs left NaN.
    """

    points: NDArray[np.float64]
    conf: NDArray[np.float64]
    filled: NDArray[np.bool_]
    depth_found: NDArray[np.bool_]
    dropped_far: NDArray[np.bool_]
    long_gaps: list


def person_depth(depth_at: Callable[[int], NDArray], mask_at: Callable[[int], NDArray] | None,
                 erode_px: int) -> Callable[[int], NDArray]:
    """A depth reader (frame -> (h, w) metres, 0 = invalid) that keeps only the person's pixels:
    the mask (H, W) bool at RGB size, resized to the depth grid (nearest pixel centre) and eroded
    by ``erode_px`` depth pixels. Without masks the depth is returned as it is."""
    if mask_at is None:
        return depth_at

    def read(t: int) -> NDArray:
        from scipy.ndimage import binary_erosion

        d = np.asarray(depth_at(t), dtype=np.float64)
        m = np.asarray(mask_at(t), dtype=bool)
        (h, w), (H, W) = d.shape, m.shape
        ys = np.clip(np.rint((np.arange(h) + 0.5) * H / h - 0.5).astype(np.int64), 0, H - 1)
        xs = np.clip(np.rint((np.arange(w) + 0.5) * W / w - 0.5).astype(np.int64), 0, W - 1)
        md = m[ys[:, None], xs[None, :]]
        if erode_px > 0:
            md = binary_erosion(md, iterations=erode_px)
        return np.where(md, d, 0.0)

    return read


def lift_keypoints(kp: NDArray, K: NDArray, T_world_cam: NDArray, depth_at: Callable[[int], NDArray],
                   rgb_size: tuple[int, int], cfg: LiftConfig = LiftConfig(), min_conf: float = 0.3,
                   max_gap_frames: int = 10) -> Lifted:
    """One view's COCO-17 keypoints lifted into the world with its depth.

    Args:
        kp: (T, 17, 3) pixels and confidence of the view.
        K: (3, 3) RGB intrinsics; T_world_cam: (>= T, 4, 4) the view's world cameras (OpenCV).
        depth_at: frame -> (h, w) depth in metres (0 = invalid), already restricted to the person
            (:func:`person_depth`); rgb_size: (width, height) of the images ``kp`` refers to.
        cfg: settings; min_conf: a keypoint below this confidence is not lifted;
        max_gap_frames: gaps up to this long between lifted frames are interpolated.
    """
    kp = np.asarray(kp, dtype=np.float64)
    T = len(kp)
    if kp.shape[1:] != (17, 3):
        raise ValueError(f"keypoints must be (T, 17, 3), got {kp.shape}")
    seen = (kp[..., 2] >= min_conf) & np.isfinite(kp[..., :2]).all(-1)
    t_idx, j_idx = np.nonzero(seen)
    d = sample_depth(depth_at, t_idx, kp[t_idx, j_idx, :2], rgb_size, cfg.window_px)
    z = np.zeros((T, 17))
    z[t_idx, j_idx] = np.where(d < cfg.max_depth_m, d, 0.0)
    found = z > 0
    # The torso's depth per frame: a limb point far from it read an occluder or the background.
    torso = np.where(found[:, _TORSO], z[:, _TORSO], np.nan)
    with warnings.catch_warnings():  # a frame with no lifted torso point has no reference: expected
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nanmedian(torso, axis=1)
    far = found & np.isfinite(ref)[:, None] & (np.abs(z - np.nan_to_num(ref)[:, None]) > cfg.max_from_body_m)
    ok = found & ~far
    t_ok, j_ok = np.nonzero(ok)
    behind = np.asarray(cfg.behind_surface_m, dtype=np.float64)
    cam = np.full((T, 17, 3), np.nan)
    cam[t_ok, j_ok] = backproject(kp[t_ok, j_ok, :2], z[t_ok, j_ok], K, behind[j_ok])
    if cfg.behind_occluder:
        cam = _behind_occluders(cam, kp, z, K, cfg)
    ok = np.isfinite(cam[..., 0])
    Tw = np.asarray(T_world_cam, dtype=np.float64)[:T]
    pts = np.einsum("tij,tkj->tki", Tw[:, :3, :3], cam) + Tw[:, None, :3, 3]
    points, filled = fill_gaps(pts, ok, max_gap_frames)
    long_gaps = _unfilled_runs(ok | filled)
    conf = np.where(ok, kp[..., 2], 0.0)
    return Lifted(points, conf, filled, found, far, long_gaps)


#: (joint, parent) in the order a chain is walked: a parent is settled before its children.
#: Shoulders and hips hang on their opposite partner (shoulder and hip width).
_CHAIN = ((5, 6), (6, 5), (11, 12), (12, 11), (7, 5), (8, 6), (13, 11), (14, 12), (9, 7), (10, 8), (15, 13), (16, 14))


def _behind_occluders(cam: NDArray, kp: NDArray, z: NDArray, K: NDArray, cfg: LiftConfig) -> NDArray:
    """Camera points (T, 17, 3) with unsure keypoints that read an occluder moved behind it.

    The depth at a keypoint's pixel is a lower bound on the joint's depth: the joint is that surface
    (seen) or behind it (hidden). For an unsure keypoint (confidence below ``trusted_conf``) whose
    lifted point breaks its bone length from its parent by more than ``bone_tol``, the point is
    placed on its ray (x = s * r, r = K^-1 [u, v, 1], s the z-depth) where the bone from the parent
    reaches it: the roots of |s r - p| = L, the nearest one at or beyond the surface depth ``z``;
    where the ray misses that sphere, its closest approach to it, never in front of the surface.
    Bone lengths L are per-sequence medians over frames where both ends are trusted; a joint whose
    parent has no point, or whose bone was never measured, keeps its lifted point.

    Args:
        cam: (T, 17, 3) lifted camera points (NaN = none); kp: (T, 17, 3) pixels and confidence;
        z: (T, 17) the surface depth read at each pixel (0 = none); K: (3, 3) intrinsics.
    """
    cam = cam.copy()
    conf = kp[..., 2]
    rays = np.stack([(kp[..., 0] - K[0, 2]) / K[0, 0], (kp[..., 1] - K[1, 2]) / K[1, 1], np.ones(conf.shape)], -1)
    for j, p in _CHAIN:
        trusted = (conf[:, j] >= cfg.trusted_conf) & (conf[:, p] >= cfg.trusted_conf)
        d = np.linalg.norm(cam[:, j] - cam[:, p], axis=-1)
        lengths = d[trusted & np.isfinite(d)]
        if len(lengths) < 5:  # too few trusted frames to know the bone
            continue
        L = float(np.median(lengths))
        broke = (conf[:, j] < cfg.trusted_conf) & np.isfinite(d) & (np.abs(d - L) > cfg.bone_tol * L)
        if not broke.any():
            continue
        r, P, zs = rays[broke, j], cam[broke, p], z[broke, j]
        a, b = (r * r).sum(-1), (r * P).sum(-1)
        disc = b * b - a * ((P * P).sum(-1) - L * L)
        root = np.sqrt(np.maximum(disc, 0.0))
        near, far = (b - root) / a, (b + root) / a
        s = np.where(near >= zs, near, far)  # the nearest root at or behind the surface
        s = np.where(disc < 0, b / a, s)  # the ray misses the sphere: its closest approach
        cam[broke, j] = r * np.maximum(s, zs)[:, None]
    return cam


def reprojection_px(points: NDArray, K: NDArray, T_world_cam: NDArray, kp: NDArray) -> NDArray[np.float64]:
    """(T, 17, 1) pixel distance between the view's keypoints (T, 17, 3) and the projection of
    ``points`` (T, 17, 3) world; NaN where either is missing (0 on lifted points, by construction)."""
    P = projection_matrices(np.asarray(K)[None], np.asarray(T_world_cam)[: len(points), None])[:, 0]  # (T, 3, 4)
    X = np.concatenate([points, np.ones(points.shape[:2] + (1,))], -1)
    x = np.einsum("tij,tkj->tki", P, X)
    with np.errstate(all="ignore"):
        uv = x[..., :2] / x[..., 2:3]
        err = np.linalg.norm(uv - kp[..., :2], axis=-1)
    return np.where(kp[..., 2] > 0, err, np.nan)[..., None]


def _unfilled_runs(have: NDArray[np.bool_]) -> list[tuple[int, int, int]]:
    """(joint, first, one past the last) of each run of frames without a point."""
    out = []
    for j in range(have.shape[1]):
        miss = np.concatenate([[0], (~have[:, j]).astype(np.int8), [0]])
        d = np.diff(miss)
        out += [(j, int(a), int(b)) for a, b in zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0])]
    return out


def lift_figures(lifted: Lifted, kp: NDArray, min_conf: float) -> Mapping[str, float]:
    """The manifest figures of a lift: shares of the seen keypoints with person depth and dropped."""
    seen = np.asarray(kp)[..., 2] >= min_conf
    n = max(int(seen.sum()), 1)
    return {"lift_depth_found_fraction": round(float((lifted.depth_found & seen).sum() / n), 4),
            "lift_dropped_far_fraction": round(float((lifted.dropped_far & seen).sum() / n), 4)}
