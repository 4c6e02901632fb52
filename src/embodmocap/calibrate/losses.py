"""Stage III refinement losses: cross-view track, view-to-scene Chamfer, reprojection.

Every loss is a pure function of one view's offset parameters acting on the **world side** of
that view's cameras (as in the paper and the release's ``optim_human_cam.py``)::

    T_world_cam'[t] = D(yaw, t) @ T_world_cam[t],   D = [[Rz(yaw), t], [0, 1]]

where ``T_world_cam`` are the *initially aligned* cameras (after the registration offset), so the
parameters are the remaining correction and start at zero. Rotating about the world origin couples
yaw with translation when the cameras are metres away from it, which slows first-order solvers; so
the parameters rotate about a fixed per-view ``pivot`` (the mean camera centre) instead::

    p' = Rz(yaw) (p - pivot) + pivot + t_pivot

and :func:`world_side_translation` converts ``t_pivot`` into the world-side ``t`` above.

Observations are pre-computed in **camera coordinates** (back-projection with depth does not
depend on the offsets), so each loss evaluation is a handful of batched matrix products.

Residual blocks and their units:

- track: (N, 3) metres, the world-space difference of two views' back-projections of one point;
- chamfer: (M,) metres, the point-to-plane distance of a view's background point to its nearest
  scene point (neighbours found outside autograd with a KD-tree);
- reprojection: (P, 2) pixels, observed minus projected registered 2D-3D matches.

Each term is ``mean_i rho(|r_i|^2 / c^2)`` with a robust kernel ``rho`` and a robust scale ``c``
in the term's unit, so the terms are dimensionless and can be summed with plain weights. The same
blocks feed the Levenberg-Marquardt solver through IRLS weights ``rho'(s)``.

Pixel convention: pixel centres at integer coordinates (COLMAP's are +0.5 from ours).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np
import torch
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from embodmocap.geometry.keypoint_depth import (  # noqa: F401 (re-exported: shared with Stage IV's one-view lift)
    JOINT_DEPTH_BEHIND_SURFACE_M, backproject, sample_depth,
)
from embodmocap.geometry.robust import ROBUST_KINDS, irls_weight, robust_rho  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)

#: COCO-17 joints used for cross-view tracks by default: shoulders, elbows, wrists, hips, knees,
#: ankles. Face points (nose, eyes, ears) are left out: they are surface landmarks seen from the
#: front only, and a 2D detector guesses them when the head is turned away.
BODY_JOINTS: tuple[int, ...] = tuple(range(5, 17))



# ---------------------------------------------------------------------------------------------
# The offset
# ---------------------------------------------------------------------------------------------


def rz_torch(yaw: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation about +Z by a scalar tensor ``yaw`` (radians), differentiable."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    o, i = torch.zeros_like(yaw), torch.ones_like(yaw)
    return torch.stack([c, -s, o, s, c, o, o, o, i]).reshape(3, 3)


def offset_points(yaw: torch.Tensor, t: torch.Tensor, pivot: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Apply the offset to world points ``p`` (..., 3): ``Rz(yaw) (p - pivot) + pivot + t``."""
    return (p - pivot) @ rz_torch(yaw).T + pivot + t


def world_side_translation(yaw: float, t_pivot: NDArray, pivot: NDArray) -> NDArray:
    """World-side translation of the offset: ``pivot - Rz pivot + t_pivot`` (3,), metres."""
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(pivot) - Rz @ np.asarray(pivot) + np.asarray(t_pivot)


@dataclass(frozen=True)
class Cameras:
    """A view's initially aligned cameras as float64 tensors.

    R: (T, 3, 3) camera-to-world rotations. c: (T, 3) camera centres (world, metres).
    pivot: (3,) the rotation pivot of this view's offset (mean camera centre).
    """

    R: torch.Tensor
    c: torch.Tensor
    pivot: torch.Tensor

    @staticmethod
    def from_T(T_world_cam: NDArray) -> "Cameras":
        """From (T, 4, 4) camera-to-world matrices."""
        T = torch.as_tensor(np.asarray(T_world_cam, dtype=np.float64))
        c = T[:, :3, 3]
        return Cameras(R=T[:, :3, :3], c=c, pivot=c.mean(dim=0))


def cam_to_world(yaw, t, cams: Cameras, frames: torch.Tensor, p_cam: torch.Tensor) -> torch.Tensor:
    """Camera-space points (N, 3) of frames (N,) -> offset world points (N, 3)."""
    p_world = torch.einsum("nij,nj->ni", cams.R[frames], p_cam) + cams.c[frames]
    return offset_points(yaw, t, cams.pivot, p_world)


# ---------------------------------------------------------------------------------------------
# Track loss (cross-view correspondences on the performer)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Correspondences:
    """Pixel correspondences between two views on the performer.

    frames: (N,) int sequence frame of each pair (both views share sequence frames).
    xy_a, xy_b: (N, 2) float pixel positions (our convention) in view a and view b RGB images.
    weight: (N,) float in [0, 1], the pair's confidence (min of the two views' confidences).
    behind_surface_m: (N,) float, how far behind the depth-map surface the point lies along the
        viewing ray, metres (0 for surface tracks such as a dense tracker's; joint radii for
        skeleton keypoints).
    track: (N,) int or None: which point each pair is (the same value in two frames is the same
        point of the performer, e.g. the joint index), so that its motion between frames is known.
    """

    frames: NDArray[np.int64]
    xy_a: NDArray[np.float64]
    xy_b: NDArray[np.float64]
    weight: NDArray[np.float64]
    behind_surface_m: NDArray[np.float64]
    track: NDArray[np.int64] | None = None


class CorrespondenceSource(Protocol):
    """The pluggable "dense tracker" role: anything that yields cross-view pixel correspondences.

    The default is :class:`KeypointCorrespondences` (matched 2D keypoints); a learned tracker
    (VGGT, CoTracker ...) implements the same method and returns surface tracks with
    ``behind_surface_m = 0``.
    """

    def correspondences(self) -> Correspondences:
        """The pairs, in RGB pixel coordinates of each view."""
        ...


@dataclass(frozen=True)
class KeypointCorrespondences:
    """Matched COCO-17 keypoints of the same performer in both views as correspondences.

    keypoints_a, keypoints_b: (T, 17, 3) (x, y, confidence) per sequence frame, pixels.
    """

    keypoints_a: NDArray
    keypoints_b: NDArray
    min_confidence: float = 0.5
    """A keypoint takes part only when its confidence in *both* views is above this."""
    joints: tuple[int, ...] = BODY_JOINTS
    """COCO-17 joint indices used."""
    depth_behind_surface_m: tuple[float, ...] = JOINT_DEPTH_BEHIND_SURFACE_M
    """Per-joint distance from the seen surface to the joint centre along the ray, metres."""

    def correspondences(self) -> Correspondences:
        ka = np.asarray(self.keypoints_a, dtype=np.float64)
        kb = np.asarray(self.keypoints_b, dtype=np.float64)
        n = min(len(ka), len(kb))
        j = np.asarray(self.joints, dtype=np.int64)
        ka, kb = ka[:n, j], kb[:n, j]
        conf = np.minimum(ka[..., 2], kb[..., 2])
        ok = (conf > self.min_confidence) & np.isfinite(ka).all(-1) & np.isfinite(kb).all(-1)
        t_idx, j_idx = np.nonzero(ok)
        behind = np.asarray(self.depth_behind_surface_m, dtype=np.float64)[j]
        return Correspondences(
            frames=t_idx.astype(np.int64),
            xy_a=ka[t_idx, j_idx, :2],
            xy_b=kb[t_idx, j_idx, :2],
            weight=conf[t_idx, j_idx],
            behind_surface_m=behind[j_idx],
            track=j[j_idx],
        )


@dataclass(frozen=True)
class TrackPairs:
    """Cross-view point pairs in each view's camera coordinates (float64 tensors).

    view_a, view_b: the two views' names. frames: (N,) sequence frame (indexes both views'
    cameras). p_a, p_b: (N, 3) camera-space points, metres. weight: (N,) confidences.
    steps: (N, 2) int or None: the index of the same point's pair in the nearest earlier and later
        frame that has it (-1: none), from which the refinement takes the point's motion.
    """

    view_a: str
    view_b: str
    frames: torch.Tensor
    p_a: torch.Tensor
    p_b: torch.Tensor
    weight: torch.Tensor
    steps: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.frames.shape[0])


def track_pairs_from_depth(
    corr: Correspondences,
    views: tuple[str, str],
    depth_at: tuple[Callable[[int], NDArray], Callable[[int], NDArray]],
    K: tuple[NDArray, NDArray],
    rgb_size: tuple[tuple[int, int], tuple[int, int]],
    max_depth_m: float = 6.0,
) -> TrackPairs:
    """Back-project correspondences with each view's depth; pairs without valid depth in both are dropped.

    ``K`` are the RGB intrinsics (pixels of ``corr``), ``rgb_size`` the (width, height) of each
    view's RGB images, ``depth_at`` each view's depth reader (see :func:`sample_depth`).
    """
    da = sample_depth(depth_at[0], corr.frames, corr.xy_a, rgb_size[0])
    db = sample_depth(depth_at[1], corr.frames, corr.xy_b, rgb_size[1])
    ok = (da > 0) & (db > 0) & (da < max_depth_m) & (db < max_depth_m)
    log.debug("track pairs: %d of %d have valid depth in both views", int(ok.sum()), len(ok))
    pa = backproject(corr.xy_a[ok], da[ok], K[0], corr.behind_surface_m[ok])
    pb = backproject(corr.xy_b[ok], db[ok], K[1], corr.behind_surface_m[ok])
    track = None if corr.track is None else np.asarray(corr.track)[ok]
    return make_track_pairs(views, corr.frames[ok], pa, pb, corr.weight[ok], track)


def make_track_pairs(views: tuple[str, str], frames, p_a, p_b, weight=None, track=None) -> TrackPairs:
    """Build :class:`TrackPairs` from numpy arrays (frames (N,), p_a/p_b (N, 3), weight (N,);
    track (N,): each pair's point identity, see :class:`Correspondences`, which gives ``steps``)."""
    f = torch.as_tensor(np.asarray(frames, dtype=np.int64))
    w = np.ones(len(f)) if weight is None else np.asarray(weight, dtype=np.float64)
    as64 = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64).reshape(-1, 3))  # noqa: E731
    steps = None if track is None else torch.as_tensor(track_steps(np.asarray(frames), np.asarray(track)))
    return TrackPairs(views[0], views[1], f, as64(p_a), as64(p_b), torch.as_tensor(w), steps)


def track_steps(frames: NDArray, track: NDArray) -> NDArray[np.int64]:
    """(N, 2) for each pair the index of the same track's pair in its nearest earlier and later
    frame (-1 where there is none). ``frames``, ``track``: (N,) ints."""
    frames = np.asarray(frames, dtype=np.int64)
    track = np.asarray(track, dtype=np.int64)
    out = np.full((len(frames), 2), -1, dtype=np.int64)
    order = np.lexsort((frames, track))  # by track, then frame
    same = track[order][1:] == track[order][:-1]
    later = frames[order][1:] > frames[order][:-1]
    link = same & later
    out[order[1:][link], 0] = order[:-1][link]
    out[order[:-1][link], 1] = order[1:][link]
    return out


def track_residuals(params_a, params_b, cams_a: Cameras, cams_b: Cameras, pairs: TrackPairs) -> torch.Tensor:
    """(N, 3) world-space difference between the two views' points, metres.

    params_*: (yaw scalar tensor, t (3,) tensor) of each view.
    """
    qa = cam_to_world(params_a[0], params_a[1], cams_a, pairs.frames, pairs.p_a)
    qb = cam_to_world(params_b[0], params_b[1], cams_b, pairs.frames, pairs.p_b)
    return qa - qb


def track_loss(params_a, params_b, cams_a, cams_b, pairs: TrackPairs, kind="huber", scale=0.05):
    """Weighted robust mean of the track residuals; returns (loss, diagnostics dict)."""
    r = track_residuals(params_a, params_b, cams_a, cams_b, pairs)
    s = (r * r).sum(-1)
    loss = (pairs.weight * robust_rho(s, kind, scale)).sum() / pairs.weight.sum().clamp(min=1e-12)
    return loss, _diagnostics(s, pairs.weight)


# ---------------------------------------------------------------------------------------------
# Chamfer (view background cloud -> scene mesh points)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScenePoints:
    """Fixed points sampled on the Stage I mesh, with unit normals, and a KD-tree on them.

    points, normals: (S, 3) float64 tensors (world, metres).
    """

    points: torch.Tensor
    normals: torch.Tensor
    tree: cKDTree = field(repr=False)

    @staticmethod
    def from_arrays(points: NDArray, normals: NDArray) -> "ScenePoints":
        p = np.asarray(points, dtype=np.float64)
        n = np.asarray(normals, dtype=np.float64)
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return ScenePoints(torch.as_tensor(p), torch.as_tensor(n), cKDTree(p))

    @staticmethod
    def from_mesh(vertices: NDArray, faces: NDArray, n_points: int = 50000, seed: int = 0) -> "ScenePoints":
        """Area-weighted uniform samples on a triangle mesh with the faces' normals."""
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        # Areas of all (millions of) faces in float32, only to draw faces; the drawn faces' points
        # and normals in float64 below. A fraction of the float64 gathers' time and memory.
        tri = v.astype(np.float32)[f]
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
        keep = area > 1e-12
        if not keep.any():
            raise ValueError("the scene mesh has no triangle with a non-zero area")
        rng = np.random.default_rng(seed)
        # Inverse-CDF draw of faces by area (Generator.choice with p is several times slower on
        # the millions of faces of a room mesh); zero-area faces have no CDF step, so are never drawn.
        cdf = np.cumsum(np.where(keep, area, 0.0).astype(np.float64))
        idx = np.minimum(np.searchsorted(cdf, rng.random(n_points) * cdf[-1], side="right"), len(f) - 1)
        r1, r2 = rng.random(n_points), rng.random(n_points)
        a, b, c = v[f[idx, 0]], v[f[idx, 1]], v[f[idx, 2]]
        s = np.sqrt(r1)  # uniform barycentric sampling
        pts = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
        return ScenePoints.from_arrays(pts, np.cross(b - a, c - a))


@dataclass(frozen=True)
class BackgroundCloud:
    """A view's background points in its camera coordinates (float64 tensors).

    frames: (M,) sequence frame of each point. p_cam: (M, 3) camera-space points, metres.
    """

    frames: torch.Tensor
    p_cam: torch.Tensor

    def __len__(self) -> int:
        return int(self.frames.shape[0])


def background_cloud(
    depth_at: Callable[[int], NDArray],
    mask_at: Callable[[int], NDArray] | None,
    frames: NDArray,
    K_depth: NDArray,
    points_per_frame: int = 500,
    max_depth_m: float = 5.0,
    mask_dilate_px: int = 4,
    seed: int = 0,
) -> BackgroundCloud:
    """Back-project the background of some frames' depth maps into camera coordinates.

    depth_at(t) -> (h, w) metres (0 = invalid); mask_at(t) -> (H, W) bool person mask at RGB
    resolution (or None): it is resized to the depth grid by nearest neighbour and dilated by
    ``mask_dilate_px`` depth pixels, since depth at the silhouette mixes person and background.
    ``K_depth``: intrinsics of the depth grid. Far points are dropped (LiDAR noise grows with
    range). At most ``points_per_frame`` random valid pixels are kept per frame.
    """
    from scipy.ndimage import binary_dilation

    rng = np.random.default_rng(seed)
    Kd = np.asarray(K_depth, dtype=np.float64)
    all_f, all_p = [], []
    for t in np.asarray(frames, dtype=np.int64):
        d = np.asarray(depth_at(int(t)), dtype=np.float64)
        h, w = d.shape
        valid = (d > 0) & (d < max_depth_m) & np.isfinite(d)
        if mask_at is not None:
            m = np.asarray(mask_at(int(t)), dtype=bool)
            H, W = m.shape
            rows = np.clip(((np.arange(h) + 0.5) * H / h).astype(np.int64), 0, H - 1)
            cols = np.clip(((np.arange(w) + 0.5) * W / w).astype(np.int64), 0, W - 1)
            m = m[rows][:, cols]
            if mask_dilate_px > 0 and m.any():
                m = binary_dilation(m, iterations=mask_dilate_px)
            valid &= ~m
        v, u = np.nonzero(valid)
        if len(u) > points_per_frame:
            pick = rng.choice(len(u), size=points_per_frame, replace=False)
            v, u = v[pick], u[pick]
        xy = np.stack([u, v], -1).astype(np.float64)
        all_p.append(backproject(xy, d[v, u], Kd))
        all_f.append(np.full(len(u), t, dtype=np.int64))
    p = np.concatenate(all_p) if all_p else np.zeros((0, 3))
    f = np.concatenate(all_f) if all_f else np.zeros(0, dtype=np.int64)
    return BackgroundCloud(torch.as_tensor(f), torch.as_tensor(p))


def nearest_scene(scene: ScenePoints, p_world: torch.Tensor, max_distance_m: float = np.inf) -> torch.Tensor:
    """(M,) index of the nearest scene point of each world point, -1 where none is within
    ``max_distance_m``; found outside autograd.

    The bound also keeps the KD-tree fast: a query far from all data (a point on an object the mesh
    lacks) would otherwise visit much of the tree.
    """
    # One thread: a query is ~10^4 points, less work than starting and joining a pool each call.
    _, idx = scene.tree.query(p_world.detach().cpu().numpy(), distance_upper_bound=max_distance_m, workers=1)
    idx = np.asarray(idx, dtype=np.int64)
    return torch.as_tensor(np.where(idx >= len(scene.tree.data), -1, idx))


def chamfer_world_points(params, cams: Cameras, cloud: BackgroundCloud) -> torch.Tensor:
    """(M, 3) the view's background points in the world under its current offset."""
    return cam_to_world(params[0], params[1], cams, cloud.frames, cloud.p_cam)


def chamfer_residuals(params, cams: Cameras, cloud: BackgroundCloud, scene: ScenePoints, nbr: torch.Tensor) -> torch.Tensor:
    """(M,) signed point-to-plane distance to each point's scene neighbour ``nbr`` (M,), metres.

    Points without a neighbour (``nbr == -1``) get residual 0; callers weight them out.

    One-directional (view -> scene): a view sees only part of the room, so the scene -> view
    direction would pull the view's cloud towards parts of the scene it never saw. Point-to-plane
    rather than point-to-point: the scene samples are ~1-2 cm apart, and sliding along a wall must
    not cost anything.
    """
    p = chamfer_world_points(params, cams, cloud)
    valid = nbr >= 0
    j = nbr.clamp(min=0)
    return torch.where(valid, ((p - scene.points[j]) * scene.normals[j]).sum(-1), torch.zeros_like(p[:, 0]))


def chamfer_loss(params, cams, cloud, scene, nbr=None, kind="huber", scale=0.03, max_distance_m=np.inf):
    """Robust mean point-to-plane distance over points with a neighbour; neighbours re-found
    (within ``max_distance_m``) when ``nbr`` is None."""
    if nbr is None:
        nbr = nearest_scene(scene, chamfer_world_points(params, cams, cloud), max_distance_m)
    r = chamfer_residuals(params, cams, cloud, scene, nbr)[nbr >= 0]
    s = r * r
    return robust_rho(s, kind, scale).mean(), _diagnostics(s, None)


# ---------------------------------------------------------------------------------------------
# Reprojection of registered 2D-3D matches
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Matches2D3D:
    """Registered 2D-3D matches of a view (float64 tensors).

    frames: (P,) sequence frame. xy: (P, 2) observed pixels (our convention: pixel centres at
    integers; subtract 0.5 from COLMAP's). xyz: (P, 3) scene points (world, metres).
    """

    frames: torch.Tensor
    xy: torch.Tensor
    xyz: torch.Tensor

    @staticmethod
    def from_arrays(frames, xy, xyz) -> "Matches2D3D":
        return Matches2D3D(
            torch.as_tensor(np.asarray(frames, dtype=np.int64)),
            torch.as_tensor(np.asarray(xy, dtype=np.float64).reshape(-1, 2)),
            torch.as_tensor(np.asarray(xyz, dtype=np.float64).reshape(-1, 3)),
        )

    def __len__(self) -> int:
        return int(self.frames.shape[0])


def reproj_residuals(params, cams: Cameras, K: torch.Tensor, m: Matches2D3D) -> torch.Tensor:
    """(P, 2) observed minus projected pixels under the view's current offset.

    The offset cameras are R' = Rz R and c' = Rz (c - pivot) + pivot + t; a world point X is seen
    at R'^T (X - c'), which equals R^T (X'' - c) with X'' the point moved by the inverse offset, so
    the points are moved instead of the (many) cameras.
    """
    yaw, t = params
    Rz = rz_torch(yaw)
    # inverse offset on the points: X'' = Rz^T (X - pivot - t) + pivot
    x_back = (m.xyz - cams.pivot - t) @ Rz + cams.pivot
    p_cam = torch.einsum("nji,nj->ni", cams.R[m.frames], x_back - cams.c[m.frames])
    z = p_cam[:, 2].clamp(min=1e-6)
    u = K[0, 0] * p_cam[:, 0] / z + K[0, 2]
    v = K[1, 1] * p_cam[:, 1] / z + K[1, 2]
    return m.xy - torch.stack([u, v], -1)


def reproj_loss(params, cams, K, m: Matches2D3D, kind="huber", scale=3.0):
    """Robust mean reprojection error of the registered matches; returns (loss, diagnostics)."""
    r = reproj_residuals(params, cams, K, m)
    s = (r * r).sum(-1)
    return robust_rho(s, kind, scale).mean(), _diagnostics(s, None)


def _diagnostics(s: torch.Tensor, weight: torch.Tensor | None) -> dict[str, float]:
    """RMS and median residual norm (term's unit) and the count."""
    s = s.detach()
    if s.numel() == 0:
        return {"rms": float("nan"), "median": float("nan"), "n": 0}
    return {"rms": float(s.mean().sqrt()), "median": float(s.median().sqrt()), "n": int(s.numel())}
