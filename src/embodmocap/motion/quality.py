"""Per-frame quality of the fitted motion, and the frames whose fit is suspect (issue 29).

A fit can be placeable (``valid``) and still wrong: a limb that Stage IV's keypoint checks took
from one view and the other view sees weakly is held only by smoothness, and at the start of a
sequence it can end up 30 cm from where both views see it. Nothing but the views can say so, so per
frame of the fitted motion:

- ``reproj_px`` (T, V): each view's median reprojection error of the fitted keypoints against the
  2D keypoints the fit used (those above ``min_conf``), pixels;
- ``kp3d_err_m`` (T,): the median distance of the fitted keypoints from the triangulated ones
  (not the gap-filled), metres;
- ``limb_off_m`` (T,): the limb joint (shoulders to ankles) furthest from what the views see:
  per joint and view, the distance in metres from the fitted joint to the view's ray through its
  detection (the raw detector's, with either side's label, or the one the fit used: a left/right
  confusion or a detection Stage IV's checks dropped is still the view's evidence), the smallest
  over the views that detect the joint at ``min_conf`` or more (a joint one view sees wrongly but
  another sees where the fit is does not count), the largest over the joints;
- ``suspect`` (T,): ``limb_off_m`` above ``suspect_m``.

Ray distances are metric where pixels are not (a limb 3 m from the camera is half as many pixels
off as at 1.5 m), and a view says nothing about depth along its own ray, which is why a joint is
judged by the view it is closest to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: COCO-17 joints judged for the suspect flag: shoulders, elbows, wrists, hips, knees, ankles
#: (the face points sit on SMPL vertices that a detector places differently).
LIMB_JOINTS: tuple[int, ...] = tuple(range(5, 17))
#: COCO-17 index of each joint's other-side twin (the face and limbs mirrored, the nose itself).
MIRROR: tuple[int, ...] = (0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15)


@dataclass(frozen=True)
class QualityConfig:
    """How the per-frame quality of the fit is measured and when a frame is suspect."""

    min_conf: float = 0.3
    """Detections below this confidence are not a view's evidence."""
    suspect_m: float = 0.10
    """A frame is suspect when a limb joint is further than this (metres) from the ray of every
    view that detects it."""


@dataclass(frozen=True)
class FrameQuality:
    """Per-frame quality of a fitted motion (see the module docstring); ``views`` names the
    columns of ``reproj_px``."""

    reproj_px: NDArray
    kp3d_err_m: NDArray
    limb_off_m: NDArray
    suspect: NDArray
    views: tuple[str, ...]

    def arrays(self) -> dict[str, NDArray]:
        """The keys written into ``smpl_fit.npz`` / ``smpl_world.npz`` (docs/formats.md)."""
        return {"reproj_px": np.asarray(self.reproj_px, np.float64), "kp3d_err_m": np.asarray(self.kp3d_err_m, np.float64),
                "limb_off_m": np.asarray(self.limb_off_m, np.float64), "suspect": np.asarray(self.suspect, bool),
                "quality_views": np.array(self.views)}


def ray_distance(points: NDArray, K: NDArray, T_world_cam: NDArray, uv: NDArray) -> NDArray:
    """Distance (metres) of world points from the camera rays through pixels ``uv``.

    Args:
        points: (T, V, J, 3) world points; K: (V, 3, 3); T_world_cam: (T, V, 4, 4) OpenCV cameras;
        uv: (T, V, J, 2) pixels. Returns (T, V, J); a point behind the camera is its distance
        from the camera centre (the ray starts there).
    """
    Kinv = np.linalg.inv(K)  # (V, 3, 3)
    pix = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1)
    d_cam = np.einsum("vab,tvjb->tvja", Kinv, pix)
    d = np.einsum("tvab,tvjb->tvja", T_world_cam[..., :3, :3], d_cam)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    rel = points - T_world_cam[:, :, None, :3, 3]
    along = np.maximum((rel * d).sum(-1, keepdims=True), 0.0)
    return np.linalg.norm(rel - along * d, axis=-1)


def frame_quality(fitted_kp: NDArray, K: NDArray, T_world_cam: NDArray, used2d: NDArray, raw2d: NDArray,
                  points: NDArray, filled: NDArray | None, views: tuple[str, ...],
                  cfg: QualityConfig = QualityConfig()) -> FrameQuality:
    """The per-frame quality of a fit (module docstring).

    Args:
        fitted_kp: (T, 17, 3) the fitted body's keypoints (the detector's layout), world metres;
        K: (V, 3, 3); T_world_cam: (T, V, 4, 4) the cameras the fit used;
        used2d: (T, V, 17, 3) the 2D keypoints the fit used (labels tracked, swaps undone,
            guesses dropped); raw2d: (T, V, 17, 3) the detector's, on the same instants;
        points: (T, 17, 3) triangulated keypoints (NaN = none); filled: (T, 17) bool gap-filled
            points (not measured; None = none filled); views: the view names.
    """
    T, V = used2d.shape[:2]
    X = np.broadcast_to(fitted_kp[:, None], (T, V, 17, 3))
    Rt = np.swapaxes(T_world_cam[..., :3, :3], -1, -2)
    cam = np.einsum("tvab,tvjb->tvja", Rt, X - T_world_cam[:, :, None, :3, 3])
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = np.einsum("vab,tvjb->tvja", K, cam)
        uv = proj[..., :2] / proj[..., 2:]
    c_used = np.nan_to_num(used2d[..., 2])
    e = np.where(c_used >= cfg.min_conf, np.linalg.norm(uv - used2d[..., :2], axis=-1), np.nan)
    reproj = _nanmedian(e, axis=-1)  # (T, V)
    seen3 = np.isfinite(points).all(-1) & (np.ones(points.shape[:2], bool) if filled is None else ~np.asarray(filled, bool))
    d3 = np.where(seen3, np.linalg.norm(fitted_kp - np.nan_to_num(points), axis=-1), np.nan)
    kp3d = _nanmedian(d3, axis=-1)
    # Each view's evidence for each joint: its raw detection under either label, or the one the fit used.
    cands = [(raw2d, np.arange(17)), (raw2d, np.asarray(MIRROR)), (used2d, np.arange(17))]
    dist = np.full((T, V, 17), np.inf)
    for kp, idx in cands:
        k = kp[:, :, idx]
        ok = np.nan_to_num(k[..., 2]) >= cfg.min_conf
        r = ray_distance(X, K, T_world_cam, np.nan_to_num(k[..., :2]))
        dist = np.where(ok & (r < dist), r, dist)
    per_joint = dist.min(axis=1)[:, list(LIMB_JOINTS)]  # (T, 12): the view closest to the fit
    per_joint = np.where(np.isfinite(per_joint), per_joint, np.nan)
    limb = np.where(np.isfinite(per_joint).any(-1), np.nanmax(np.nan_to_num(per_joint, nan=-1.0), axis=-1), np.nan)
    suspect = np.nan_to_num(limb, nan=0.0) > cfg.suspect_m
    return FrameQuality(reproj, kp3d, limb, suspect, tuple(views))


def _nanmedian(a: NDArray, axis: int) -> NDArray:
    """NaN-ignoring median along ``axis``; NaN where every value is NaN (no warning)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=axis)
