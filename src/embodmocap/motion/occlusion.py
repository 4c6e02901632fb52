"""Which 2D keypoints are hidden from their camera by the scene: a detection of a joint that lies
behind the scene's geometry (furniture, a wall edge) is the detector's guess, not a measurement.

Stage IV knows the scene (Stage I's mesh) and every camera (Stage III) in one world, so for each
frame, view and joint it casts the segment from the camera centre to the joint's 3D position
(:func:`embodmocap.geometry.raycast.cast_rays`): when the scene is hit more than ``margin_m``
before the joint, that view cannot see the joint. Detectors still output such joints, guessed from
context, often with a middling confidence, and a guess triangulated with the other view's good
detection lies along the good view's ray at a wrong depth with no reprojection error. So hidden
detections lose their confidence (times ``conf_scale``) before triangulating and fitting: the other
view, the neighbouring frames and the body's smoothness carry the joint there.

The joint's 3D position for the test comes from the keypoints themselves: a first triangulation,
through a running median over ``median_frames`` frames (a wrong guess lasting a few frames does not
move it), gaps filled where the triangulation fills them. Joints never triangulated are not tested.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class OcclusionConfig:
    """How 2D keypoints hidden by the scene are found and down-weighted."""

    enabled: bool = True
    """Test each view's keypoints against the scene mesh (False: keep every detection as it is)."""
    margin_m: float = 0.1
    """A joint counts as hidden when the scene is hit more than this before it along the ray from
    the camera (metres): joints lie inside the body, a few cm from its skin, and a reconstructed
    mesh is a few cm off; a piece of furniture in front is further."""
    conf_scale: float = 0.0
    """Confidence of a hidden detection is multiplied by this (0: dropped)."""
    median_frames: int = 15
    """Frames of the running median of the first triangulation that places the joints for the test."""


def scene_hidden(scene, centres: NDArray, points: NDArray, margin_m: float) -> NDArray[np.bool_]:
    """(T, V, J) True where the segment from camera ``centres`` (T, V, 3) to ``points`` (T, J, 3)
    hits the scene (a :func:`embodmocap.geometry.raycast.raycasting_scene`) more than ``margin_m``
    before the point. NaN points are never hidden."""
    from embodmocap.geometry.raycast import cast_rays

    centres = np.asarray(centres, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    T, V = centres.shape[:2]
    J = points.shape[1]
    d = points[:, None] - centres[:, :, None]  # (T, V, J, 3)
    dist = np.linalg.norm(d, axis=-1)
    ok = np.isfinite(dist) & (dist > margin_m)
    hidden = np.zeros((T, V, J), dtype=bool)
    if not ok.any():
        return hidden
    o = np.broadcast_to(centres[:, :, None], d.shape)[ok]
    u = d[ok] / dist[ok][:, None]
    t_hit = cast_rays(scene, o, u)["t_hit"]
    hidden[ok] = t_hit < dist[ok] - margin_m
    return hidden


def drop_scene_hidden(scene, P: NDArray, T_world_cam: NDArray, kp: NDArray, tri_cfg, cfg: OcclusionConfig = OcclusionConfig()
                      ) -> tuple[NDArray, NDArray[np.bool_]]:
    """``kp`` (T, V, J, 3) with the confidence of the detections the scene hides from their view
    scaled by ``cfg.conf_scale`` (a new array), and those (T, V, J) flags.

    Args:
        scene: :func:`embodmocap.geometry.raycast.raycasting_scene` of the scene mesh (world frame).
        P: (T, V, 3, 4) projection matrices of the views (world -> pixels).
        T_world_cam: (T, V, 4, 4) the views' camera-to-world poses.
        kp: (T, V, J, 3) pixels and confidence.
        tri_cfg: :class:`embodmocap.geometry.triangulation.TriangulationConfig` of the first
            triangulation (the one Stage IV uses).
        cfg: settings.
    """
    from embodmocap.geometry.triangulation import triangulate

    kp = np.asarray(kp, dtype=np.float64)
    hidden = np.zeros(kp.shape[:3], dtype=bool)
    if not cfg.enabled:
        return kp.copy(), hidden
    tri = triangulate(P, kp[..., :2], kp[..., 2], tri_cfg)
    points = _running_median(tri.points, cfg.median_frames)
    hidden = scene_hidden(scene, np.asarray(T_world_cam)[..., :3, 3], points, cfg.margin_m)
    hidden &= kp[..., 2] > 0
    out = kp.copy()
    out[..., 2] = np.where(hidden, cfg.conf_scale * out[..., 2], out[..., 2])
    return out, hidden


def _running_median(points: NDArray, frames: int) -> NDArray:
    """(T, J, 3) points through a centred running median over ``frames`` frames ignoring NaN;
    NaN where the window holds no point."""
    if frames <= 1:
        return points
    import warnings

    from numpy.lib.stride_tricks import sliding_window_view

    h = frames // 2
    nan = np.full((h,) + points.shape[1:], np.nan)
    win = sliding_window_view(np.concatenate([nan, points, nan]), 2 * h + 1, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(win, axis=-1)
