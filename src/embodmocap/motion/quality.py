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
  detection (the raw detector's or the one the fit used, labels tracked and swaps undone: a
  detection Stage IV's checks dropped is still the view's evidence), the smallest over the views
  that detect the joint at ``min_conf`` or more (a joint one view sees wrongly but another sees
  where the fit is does not count), the largest over the joints. A fitted limb on the other side's
  place (left and right exchanged in the fit) is as far from both views as any other wrong limb;
- ``suspect`` (T,): a limb joint further than ``suspect_m`` from every view that sees it, in the
  frame and in one of its neighbours (``limb_off_m`` says how far in the frame); or, with the views'
  depth maps, a limb part (thigh, lower leg, upper arm, forearm) whose vertices lie for more than
  ``free_space_share`` in space a view's depth saw empty (more than ``free_space_m`` in front of
  the measured surface: :mod:`embodmocap.motion.free_space`), in the frame and a neighbour. This
  catches what the rays cannot: a limb on one view's ray at the wrong depth, or held by smoothness
  where one view alone sees it; or, with the views' depth maps and person masks, a surface a view
  measured around its detection of an elbow, wrist, knee or ankle that lies (for three quarters of
  its pixels) more than ``surface_m`` from every vertex of the fitted body, in the frame and a
  neighbour (:mod:`embodmocap.motion.seen_surface`): the converse of the free-space test, it
  catches a wrist or ankle held 15-20 cm off along the ray of the one view that sees it; or such a
  joint, seen by a view on its ray, more than ``front_m`` in front of the surface that view measured
  around it, in the frame and a neighbour.

"In the frame and a neighbour" is the two-frame rule every test shares; at a sequence's first and
last frames (``edge_gap_frames``) the neighbour is the nearest frame where the view judged that
joint (a frame without its detection does not break a wrong start), and a suspect run grows over
the contradicted frames beside it (``grow_frames``).

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


@dataclass(frozen=True)
class QualityConfig:
    """How the per-frame quality of the fit is measured and when a frame is suspect."""

    min_conf: float = 0.6
    """Detections below this confidence are not a view's evidence. A detector's blunders (a far
    outlier, a hidden joint guessed elsewhere) come at middling confidence: on a hard studio
    session whose fit had no joint 15 cm off, 25 placeable frames had a limb joint more than 10 cm
    from its only detection at 0.3-0.6 (none at 0.6 or more that lasted two frames)."""
    suspect_m: float = 0.10
    """A frame is suspect when a limb joint is further than this (metres) from the ray of every
    view that detects it, in this frame and a neighbouring one (a drifting limb stays off; a
    detector's one-frame blunder does not make a frame suspect)."""
    free_space_m: float = 0.10
    """A fitted limb vertex more than this (metres) in front of the depth a view measured at its
    pixel (the nearest within ``free_space_window_px``) is in space the sensor saw empty. 0 = no
    depth test (the flag then rests on the keypoints alone). On the 10 hard studio seeds (6 s) the
    depth test took the frames with a joint > 15 cm off that no flag caught from 3.6 % to 1.7 %,
    flagging 3.4 % of the frames with every joint within 15 cm (most of them 7-13 cm off: a thin
    forearm 9 cm off lies wholly outside what a view saw) (benchmarks/history/2026-12-04-s9-flags.md)."""
    free_space_share: float = 0.4
    """A limb part is contradicted by a view's depth when more than this share of its measured
    vertices lie in empty space (``free_space_m``); lower flags more wrong frames and more right
    ones (on the studio seeds, 0.5: 2.1 % wrong unflagged and 2.5 % of the right frames flagged;
    0.3 with hands and feet judged too: 0.7 % and 60 %)."""
    free_space_window_px: int = 3
    """The depth-pixel neighbourhood whose nearest depth a vertex is held against: a vertex a
    pixel or two off a thin limb's measured silhouette is not in empty space (7: the thighs of
    studio seed 4's swapped legs, 5-10 cm off, passed too)."""
    surface_m: float = 0.09
    """A frame is suspect when the person surface a view measured around its detection of an
    elbow, wrist, knee or ankle (depth pixels under the person mask) lies further than this
    (metres, at the ``surface_quantile``) from every vertex of the fitted body, in the frame and a
    neighbour (:mod:`embodmocap.motion.seen_surface`). 0 = no such test. Chosen on hard studio
    seeds 0-4 and checked on 5-9 (6 s sessions): frames with a joint > 15 cm off that no flag
    caught 2.8 % -> 1.1 % (0-4) and 1.5 % -> 0.75 % (5-9), right frames flagged 4.2 % -> 4.35 %
    and 2.6 % -> 3.4 % (benchmarks/history/2026-12-05-s10-flags.md)."""
    surface_conf: float = 0.7
    """Detections below this confidence are not judged by the surface test (a hidden joint's
    guess points at whatever is in front of it)."""
    surface_window_px: int = 5
    """The depth-pixel neighbourhood around a detection whose measured person surface is judged."""
    surface_quantile: float = 0.25
    """The quantile of the measured points' distances to the fitted body that is held against
    ``surface_m``: most of the points must be unexplained, so that a window reaching over a thin
    limb's edge (mask bleed, mixed depth) does not count (the median flagged more right frames)."""
    front_m: float = 0.10
    """A frame is suspect when an elbow, wrist, knee or ankle that a view detects on its ray
    (at ``front_conf`` or more) lies further than this (metres) in front of the person surface the
    view measured around it, in the frame and a neighbour
    (:func:`embodmocap.motion.seen_surface.joint_in_front`). 0 = no such test. Added after seeing
    hard studio seed 5 (a wrist 12 cm toward its only view: 3 frames, now flagged); on seeds 0-4
    and 6-9 it flags no frame the other tests do not."""
    front_conf: float = 0.8
    """Detections below this confidence do not put a joint on a view's ray for ``front_m``."""
    front_window_px: int = 7
    """The depth-pixel neighbourhood whose person pixels' median depth bounds a joint from the
    front (5 flagged 4 right frames of studio seed 9 that 7 does not)."""
    edge_gap_frames: int = 4
    """In the first and last this many frames of a sequence, a column (a joint's ray, a limb
    part's free space, a detection's surface or front) off in a frame counts when it is off in the
    nearest frame before or after where it was judged, at most this many frames away, and the frames
    between two such frames where it was not judged count too (elsewhere: the frame and a
    neighbour). At an edge a frame has one neighbour, and one frame without a detection let a
    wrong start pass: hard studio seed 3 with one phone (issue 29), the right wrist 66 cm off its
    detection's ray in frame 0, undetected in frame 1 (31 cm off), off again from frame 2.
    Everywhere (not only at the edges) it flagged 3-frame runs around one-frame holes in
    mid-sequence on four of the ten hard two-phone seeds (right frames flagged 3.4 -> 4.2 %, 4.5 %
    with 4); at the edges only it flags none of their frames
    (benchmarks/history/2026-12-06-s13-onephone.md). 0 = the frame and a neighbour everywhere."""
    grow_frames: int = 2
    """A suspect run grows by up to this many frames at each end over frames that each have a
    contradicted column (any test, in that frame alone): a wrong limb beside a flagged run is not
    let through because each of its frames is contradicted by a different column. Seed 3 with one
    phone: frames 20-21 (the arms 15-22 cm off after the flagged run 2-19) were let through; grown
    without a limit the run took frames 22-23 too (4-9 cm off, each with another detector
    blunder). On the ten hard two-phone seeds: right frames flagged 53 -> 58 of 1550 (none of
    their frames is wrong and unflagged either way). 0 = off."""
    repair_frames: int = 0
    """At the edges of each run of placeable frames, a limb further than ``suspect_m`` from the
    views takes the local rotations of the first frame within this many where it is not, when
    that brings it closer to the views (:mod:`embodmocap.motion.edge_repair`). 0 = off, the
    default: aimed at issue 29's external sessions (a limb 30-36 cm off in the first frames), a
    failure the studio did not reproduce; with 15 on four hard studio sessions it changed one
    stretch, by +0.13 mm on its first five frames (BENCHMARKS.md, session 7)."""


@dataclass(frozen=True)
class FrameQuality:
    """Per-frame quality of a fitted motion (see the module docstring); ``views`` names the
    columns of ``reproj_px``; ``joint_off_m`` (T, 17) each joint's distance from the closest view
    that sees it (NaN: none does); ``free_space`` (T, P) the largest share over the views of each
    limb part in empty space (:func:`embodmocap.motion.free_space.free_space_limbs`; None: no depth
    test); ``surface`` (T, V, J) how far each view's measured surface at its detections lies from
    the body (:func:`embodmocap.motion.seen_surface.unexplained_surface`; None: no such test);
    ``front`` (T, V, J) how far each joint a view sees lies in front of the surface it measured
    (:func:`embodmocap.motion.seen_surface.joint_in_front`; None: no such test); none of them is
    written to the files."""

    reproj_px: NDArray
    kp3d_err_m: NDArray
    limb_off_m: NDArray
    suspect: NDArray
    views: tuple[str, ...]
    joint_off_m: NDArray | None = None
    free_space: NDArray | None = None
    surface: NDArray | None = None
    front: NDArray | None = None

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
                  cfg: QualityConfig = QualityConfig(), free_space: NDArray | None = None,
                  surface: NDArray | None = None, front: NDArray | None = None) -> FrameQuality:
    """The per-frame quality of a fit (module docstring).

    Args:
        fitted_kp: (T, 17, 3) the fitted body's keypoints (the detector's layout), world metres;
        K: (V, 3, 3); T_world_cam: (T, V, 4, 4) the cameras the fit used;
        used2d: (T, V, 17, 3) the 2D keypoints the fit used (labels tracked, swaps undone,
            guesses dropped); raw2d: (T, V, 17, 3) the detector's, on the same instants;
        points: (T, 17, 3) triangulated keypoints (NaN = none); filled: (T, 17) bool gap-filled
            points (not measured; None = none filled); views: the view names;
        free_space: (T, P) each limb part's share of vertices in a view's empty space
            (:func:`embodmocap.motion.free_space.free_space_limbs`; None: no depth test);
        surface: (T, V, J) the views' measured surface at their detections, its distance from the
            body (:func:`embodmocap.motion.seen_surface.unexplained_surface`; None: no such test);
        front: (T, V, J) the seen joints in front of the measured surface
            (:func:`embodmocap.motion.seen_surface.joint_in_front`; None: no such test).
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
    joint = joint_offsets(fitted_kp, K, T_world_cam, used2d, raw2d, cfg.min_conf)
    per_joint = joint[:, list(LIMB_JOINTS)]
    limb = np.where(np.isfinite(per_joint).any(-1), np.nanmax(np.nan_to_num(per_joint, nan=-1.0), axis=-1), np.nan)
    # Each test: (T, K) figures (NaN: not judged there) and the threshold above which a column is off.
    tests = [(per_joint, cfg.suspect_m)]
    if free_space is not None:
        tests.append((free_space, cfg.free_space_share))
    if surface is not None and cfg.surface_m > 0:
        tests.append((np.reshape(surface, (T, -1)), cfg.surface_m))
    if front is not None and cfg.front_m > 0:
        tests.append((np.reshape(front, (T, -1)), cfg.front_m))
    suspect = np.zeros(T, dtype=bool)
    off_any = np.zeros(T, dtype=bool)
    for fig, limit in tests:
        judged = np.isfinite(fig)
        off = judged & (np.nan_to_num(fig, nan=0.0) > limit)
        suspect |= _lasting(off, judged, cfg.edge_gap_frames)
        off_any |= off.any(-1)
    for _ in range(cfg.grow_frames):  # suspect runs grown over contradicted frames beside them
        suspect = suspect | (off_any & (np.concatenate([[False], suspect[:-1]]) | np.concatenate([suspect[1:], [False]])))
    return FrameQuality(reproj, kp3d, limb, suspect, tuple(views), joint, free_space, surface, front)


def _lasting(off: NDArray, judged: NDArray | None = None, edge: int = 0) -> NDArray:
    """(T,) frames where some column of ``off`` (T, K) bool holds in the frame and a neighbour (a
    drifting limb stays off; a one-frame blunder of a detector or a depth map does not count).
    In the first and last ``edge`` frames, the neighbour is the nearest frame before or after
    where that column was judged (``judged`` (T, K) bool; None: every frame), at most ``edge``
    frames away, and frames where it was not judged that lie between two of its off frames there
    count too (:attr:`QualityConfig.edge_gap_frames`)."""
    T = len(off)
    judged = np.ones(off.shape, dtype=bool) if judged is None else np.asarray(judged, dtype=bool)
    off = off & judged
    before = np.concatenate([np.zeros_like(off[:1]), off[:-1]])
    after = np.concatenate([off[1:], np.zeros_like(off[:1])])
    out = (off & (before | after)).any(-1)
    if edge <= 0 or T < 2:
        return out
    t = np.arange(T)[:, None]
    last = np.maximum.accumulate(np.where(judged, t, -1), axis=0)  # last judged frame <= t
    first = np.minimum.accumulate(np.where(judged, t, T)[::-1], axis=0)[::-1]  # next judged frame >= t
    prev = np.concatenate([np.full((1, off.shape[1]), -1), last[:-1]])  # last judged frame < t
    nxt = np.concatenate([first[1:], np.full((1, off.shape[1]), T)])  # next judged frame > t
    col = np.arange(off.shape[1])[None]
    prev_off = (prev >= 0) & (t - prev <= edge) & off[np.clip(prev, 0, T - 1), col]
    next_off = (nxt < T) & (nxt - t <= edge) & off[np.clip(nxt, 0, T - 1), col]
    between = ~judged & (nxt - prev <= edge) & prev_off & next_off
    at_edge = (np.arange(T) < edge) | (np.arange(T) >= T - edge)
    return out | (at_edge & ((off & (prev_off | next_off)) | between).any(-1))


def joint_offsets(fitted_kp: NDArray, K: NDArray, T_world_cam: NDArray, used2d: NDArray, raw2d: NDArray,
                  min_conf: float) -> NDArray:
    """(T, 17) each fitted joint's distance (metres) from the ray of the view closest to it among
    those that detect it at ``min_conf`` or more, the raw detection or the one the fit used
    (NaN: no view does). Shapes as :func:`frame_quality`."""
    T, V = used2d.shape[:2]
    X = np.broadcast_to(fitted_kp[:, None], (T, V, 17, 3))
    dist = np.full((T, V, 17), np.inf)
    for k in (raw2d, used2d):
        ok = np.nan_to_num(k[..., 2]) >= min_conf
        r = ray_distance(X, K, T_world_cam, np.nan_to_num(k[..., :2]))
        dist = np.where(ok & (r < dist), r, dist)
    best = dist.min(axis=1)
    return np.where(np.isfinite(best), best, np.nan)


def _nanmedian(a: NDArray, axis: int) -> NDArray:
    """NaN-ignoring median along ``axis``; NaN where every value is NaN (no warning)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=axis)
