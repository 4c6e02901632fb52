"""Limb joints that only one view sees, placed with that view's LiDAR depth (two-view sequences).

A joint needs two views at the triangulation's confidence to be triangulated. Where one view sees
an elbow, wrist, knee or ankle clearly and the other does not (occluded by the body or a piece of
furniture, outside its image), the triangulation has nothing there, or a point filled over the
gap, interpolated between frames the joint was triangulated in; the fit then has that view's 2D
keypoint, which fixes the joint's ray but not where along it, and the smoothness and the pose
prior choose the depth. On the hard studio sessions of issue 29 that choice was 10-17 cm off for
runs of frames: outdoor seed 5's right wrist in frames 129-137 (view 2 sees it at confidence
below 0.3, view 1 clearly), the fitted wrist 12-16 cm behind the truth along view 1's ray, exactly
where W-MPJPE's second chunk is anchored (frames 133-134: that chunk's error 72 mm against the
first chunk's 28).

The view that sees the joint measured its depth: its depth map, on the person mask, around the
keypoint's pixel gives the body surface in front of the joint, and the joint centre lies a limb's
half thickness further along the ray (as the one-phone path lifts every joint:
:mod:`embodmocap.motion.lift`). Here only the (frame, joint) pairs that one view sees at
``min_conf`` or more while every other view's detection is below ``other_max_conf`` are lifted
(for the legs by default the triangulation's threshold: a point triangulated from two views is
not replaced; for the arms ``arm_other_max_conf``, higher: an arm joint the other view only guessed
is placed by the view that sees it). The lifted point carries the view's confidence
times ``conf_scale``: it is measured along one ray only. The bone-length gate that follows
(:mod:`embodmocap.motion.ik`) drops one that read an occluder or the background (a point away
from its parent joint).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.keypoint_depth import JOINT_DEPTH_BEHIND_SURFACE_M, backproject
from embodmocap.geometry.transforms import apply_T
from embodmocap.motion.seen_surface import surface_points

#: COCO-17 elbows, wrists, knees, ankles: the joints one view's depth may place.
LIMB_JOINTS = (7, 8, 9, 10, 13, 14, 15, 16)
#: COCO-17 elbows and wrists (``arm_other_max_conf`` applies to them).
ARM_JOINTS = (7, 8, 9, 10)


@dataclass(frozen=True)
class DepthPointsConfig:
    """Which one-view limb joints are placed with the seeing view's depth (two views)."""

    min_conf: float = 0.5
    """A limb joint that one view detects at this confidence or more, and no other view at
    ``other_max_conf`` or more, is placed with that view's depth on the person mask; 0 = off (the
    fit places it from that view's ray, the smoothness and the pose prior). Hard studio seeds
    (issue 29, in memory, main -> on): indoor 4 W-MPJPE c100 68.4 -> 34.6 mm (with
    ``SwapConfig.bone_continuity``), outdoor 5 41.9 -> 28.7, outdoor 1 28.0 -> 29.3 (its
    every-start median 28.8 -> 27.3, worst 45.3 -> 35.1, WA 21.0 -> 19.5); 0.3 and 0.7 gave the
    same within 1 mm on seeds 4 and 5."""
    other_max_conf: float = 0.1
    """The other view's detection must be below this confidence (at the triangulation's
    ``min_conf``, 0.1 by default, it is not used there: the joint has no triangulated point). Higher:
    a point triangulated with a weak second view (a hidden joint's guess, jittered several times
    more than a seen one) is replaced too."""
    arm_other_max_conf: float = 0.5
    """The same bound for the elbows and wrists. A hidden arm joint is guessed by the hard detector
    at confidence 0.1-0.5 about 20 px off; the Stage IV fit leaves such a point out of its 3D term
    (``MotionConfig.kp3d_min_view_conf``), and here the view that sees the joint places it with its
    depth instead. 10 hard studio seeds (issue 29, with ``track_phase`` on), 0.1 -> 0.5: W-MPJPE c100
    median 32.5 -> 28.3 mm, worst 42.9 -> 38.2, WA 18.96 -> 18.64, PA 16.51 -> 16.16. The legs keep
    ``other_max_conf``: at 0.5 for every limb a foot neither view sees well went 1.5-2 cm further
    into a chair's side (``sim check`` 5.9 cm on seed 6)."""
    conf_scale: float = 0.5
    """The placed point's confidence is the view's times this (one ray and one depth reading,
    against a triangulated point's two rays)."""
    window_px: int = 3
    """Side of the depth-pixel window read around the keypoint (odd); the median depth of its
    person pixels is the surface in front of the joint."""
    min_pixels: int = 3
    """Fewest person pixels with depth in the window (fewer: the joint is not placed)."""
    max_depth_m: float = 6.0
    """Depths beyond this are not trusted (the LiDAR's range)."""


def one_view_pairs(kp2d: NDArray, cfg: DepthPointsConfig) -> NDArray:
    """(T, 17) int: the view that alone sees each limb joint (``cfg.min_conf`` or more, every
    other view below ``cfg.other_max_conf``, for the arms ``cfg.arm_other_max_conf``), -1 elsewhere.
    kp2d: (T, V, 17, 3)."""
    c = np.nan_to_num(kp2d[..., 2])  # (T, V, 17)
    seeing = (c >= cfg.min_conf).sum(axis=1) == 1
    bound = np.full(kp2d.shape[2], min(cfg.other_max_conf, cfg.min_conf))
    bound[list(ARM_JOINTS)] = min(cfg.arm_other_max_conf, cfg.min_conf)
    others = (c >= bound[None, None]).sum(axis=1)  # views detecting the joint at their bound or more
    alone = seeing & (others == 1)
    limb = np.zeros(kp2d.shape[2], dtype=bool)
    limb[list(LIMB_JOINTS)] = True
    alone &= limb[None]
    view = np.argmax(c, axis=1)
    return np.where(alone, view, -1)


def place_one_view_joints(points: NDArray, conf: NDArray, filled: NDArray | None, kp2d: NDArray, K: NDArray,
                          T_world_cam: NDArray, depth: Sequence[tuple | None],
                          cfg: DepthPointsConfig) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The one-view limb joints placed with the seeing view's depth.

    Args:
        points: (T, 17, 3) triangulated world points (NaN: none); conf: (T, 17) their confidence;
        filled: (T, 17) bool, points filled over a gap (None: none recorded);
        kp2d: (T, V, 17, 3) the views' keypoints (pixels, confidence) as triangulated;
        K: (V, 3, 3); T_world_cam: (T, V, 4, 4) OpenCV cameras;
        depth: per view ``(depth_mm (T', h, w) uint16, (width, height), masks)`` (Stage II's depth
            and packed person masks, :func:`embodmocap.motion.stage.quality_depth`), None where
            the view has no depth or no masks (its joints are not placed);
        cfg: settings.

    Returns:
        ``(points, conf, filled, placed)``: new arrays with the placed joints (``filled`` False
        there) and (T, 17) bool where a joint was placed.
    """
    T = len(points)
    view = one_view_pairs(kp2d, cfg)
    out_p, out_c = points.copy(), conf.copy()
    out_f = np.zeros((T, points.shape[1]), dtype=bool) if filled is None else filled.copy()
    placed = np.zeros((T, points.shape[1]), dtype=bool)
    behind = np.asarray(JOINT_DEPTH_BEHIND_SURFACE_M, dtype=np.float64)
    for i, got in enumerate(depth):  # two views: a loop over views, not frames
        if got is None or len(got) < 3 or got[2] is None:
            continue
        depth_mm, rgb_size, masks = got[0], got[1], got[2]
        n = min(T, len(depth_mm), len(masks))
        sel = view[:n] == i
        if not sel.any():
            continue
        kp = np.where(sel[..., None], kp2d[:n, i], np.nan)  # only the pairs this view alone sees
        kp[..., 2] = np.where(sel, kp2d[:n, i, :, 2], 0.0)
        _, ok, z = surface_points(kp, K[i], T_world_cam[:n, i], rgb_size, depth_mm, masks, cfg.min_conf,
                                  cfg.window_px)
        ok = ok & (z < cfg.max_depth_m)
        count = ok.sum(axis=-1)  # (n, 17)
        zs = np.where(ok, z, np.nan)
        with warnings.catch_warnings():  # a window without person pixels: expected, not placed
            warnings.simplefilter("ignore", RuntimeWarning)
            zmed = np.nanmedian(zs, axis=-1)
        good = sel & (count >= cfg.min_pixels) & np.isfinite(zmed)
        t_idx, j_idx = np.nonzero(good)
        if not len(t_idx):
            continue
        cam = backproject(kp2d[t_idx, i, j_idx, :2], zmed[t_idx, j_idx], K[i], behind[j_idx])
        world = apply_T(T_world_cam[t_idx, i], cam[:, None])[:, 0]
        out_p[t_idx, j_idx] = world
        out_c[t_idx, j_idx] = cfg.conf_scale * kp2d[t_idx, i, j_idx, 2]
        out_f[t_idx, j_idx] = False
        placed[t_idx, j_idx] = True
    return out_p, out_c, out_f, placed


def depth_of_views(depth: Mapping | None, names: Sequence[str]) -> list[tuple | None]:
    """Per view (in ``names``' order) its ``(depth_mm, rgb_size, masks)`` from a fit's ``depth``
    mapping, None where it has none."""
    depth = depth or {}
    return [depth.get(v) for v in names]
