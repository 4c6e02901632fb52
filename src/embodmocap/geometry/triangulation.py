"""Multi-view triangulation of 2D keypoints into world-space 3D keypoints (stage IV).

The paper's stage IV estimates each 3D keypoint ``Y_tj`` by minimising the confidence-weighted
reprojection error ``sum_v c_vtj ||y_vtj - P_v Y_tj||^2``, solved as a weighted linear least
squares problem (a DLT whose two rows per view are scaled by that view's confidence). This module
solves it for all frames, joints and views at once, then adds what the paper's release lacks:

- views whose 2D confidence is below ``min_conf`` are ignored (not seen);
- with three or more views, a view whose reprojection error is too large is dropped (the worst
  one first) and the point re-solved, so one bad detection cannot drag the point away;
- short gaps (a joint seen by fewer than ``min_views`` views for a few frames) are filled by linear
  interpolation and flagged; longer gaps stay NaN and are listed.

Shapes: ``T`` frames, ``V`` views, ``J`` joints. Cameras follow the package convention (OpenCV
axes, ``T_world_cam`` camera-to-world), so ``P = K [R^T | -R^T c]`` maps homogeneous world points
to homogeneous pixels. Points are in the world frame (metres); pixels in the image of each view.

:func:`triangulate_loop` is the plain per-point DLT of the paper's release (one SVD per frame and
joint, no weights, no rejection), kept as a reference and for the benchmark.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

F = NDArray[np.float64]


@dataclass(frozen=True)
class TriangulationConfig:
    """Settings of :func:`triangulate` (defaults follow Pose2Sim's, which suit ViTPose too)."""

    min_conf: float = 0.3
    """A 2D keypoint whose confidence is below this counts as not seen by that view."""

    reject_px: float = 15.0
    """With 3+ views: when a point's largest reprojection error over its used views exceeds this
    (pixels), its worst view is dropped and the point re-solved; repeated while more than
    ``min_views`` views remain. The worst view is the one whose removal leaves the smallest
    largest error (leave-one-out). With 2 views nothing is dropped. ``inf`` disables it."""

    max_gap_frames: int = 10
    """Gaps (runs of frames where a joint could not be triangulated) up to this many frames long,
    with a triangulated frame on both sides, are filled by linear interpolation; longer gaps (and
    gaps touching the first or last frame) stay NaN and are listed in ``long_gaps``. 0 disables
    filling."""

    min_views: int = 2
    """Fewest views (at ``min_conf`` or above) needed to triangulate a point; at least 2."""

    drop_unresolved: bool = True
    """A point still above ``reject_px`` once no view can be dropped (always the case with 2
    views: the rays do not meet, so at least one 2D keypoint is wrong, e.g. a swapped or
    misplaced limb) counts as not triangulated, and is gap-filled like a missing one. False
    keeps it (with its error in ``reproj_err_px``)."""


@dataclass(frozen=True)
class Triangulation:
    """Result of :func:`triangulate`.

    ``conf`` is the mean confidence of the views used, times (views used / V): the mean says how
    much the detector trusted the 2D points, the factor says how constrained the point is (two
    rays of four are a weaker fix than four). It lies in [0, 1] when 2D confidences do, and is 0
    where the point was not triangulated, including frames filled by interpolation (they are not
    measurements; use ``filled`` to tell them apart from missing ones).
    """

    points: F
    """(T, J, 3) world points, metres; NaN where not triangulated and not filled."""
    conf: F
    """(T, J) confidence of each triangulated point (see the class docstring); 0 elsewhere."""
    reproj_err_px: F
    """(T, J, V) pixel distance between each view's 2D point and the projection of ``points``
    (filled points included); NaN where the view did not see the joint or there is no point."""
    used: NDArray[np.bool_]
    """(T, J, V) True where the view took part in the final solve."""
    filled: NDArray[np.bool_]
    """(T, J) True where the point was filled by interpolation across a short gap."""
    long_gaps: list[tuple[int, int, int]] = field(default_factory=list)
    """Gaps left NaN, as (joint, first frame, one past the last frame): longer than
    ``max_gap_frames``, or touching the start or end of the sequence (nothing to interpolate
    from)."""


# --------------------------------------------------------------------------------------------
# cameras
# --------------------------------------------------------------------------------------------


def projection_matrices(K: F, T_world_cam: F) -> F:
    """Projection matrices ``P = K [R^T | -R^T c]`` from intrinsics and camera-to-world poses.

    Args:
        K: (3, 3) shared intrinsics or (V, 3, 3) one per view.
        T_world_cam: (..., V, 4, 4) camera-to-world transforms (OpenCV camera axes); the leading
            axes (e.g. frames) are kept.

    Returns:
        (..., V, 3, 4) matrices mapping homogeneous world points to homogeneous pixels.
    """
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.ndim < 3 or T.shape[-2:] != (4, 4):
        raise ValueError(f"T_world_cam must be (..., V, 4, 4), got {T.shape}")
    if K.shape != (3, 3) and (K.ndim != 3 or K.shape[1:] != (3, 3) or K.shape[0] != T.shape[-3]):
        raise ValueError(f"K must be (3, 3) or (V, 3, 3) with V = {T.shape[-3]}, got {K.shape}")
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)  # world -> camera rotation
    t = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    return np.einsum("...ij,...jk->...ik", K, np.concatenate([Rt, t[..., None]], axis=-1))


# --------------------------------------------------------------------------------------------
# triangulation
# --------------------------------------------------------------------------------------------


def triangulate(P: F, points2d: F, conf: F, cfg: TriangulationConfig | None = None) -> Triangulation:
    """Confidence-weighted multi-view DLT with outlier-view rejection and gap filling.

    Every (frame, joint) is solved at once as a batch of 4x4 normal equations (the smallest
    eigenvector of ``A^T A``, where ``A`` stacks each view's two DLT rows scaled by its
    confidence); only the rejection rounds (at most V - 2) loop in Python.

    Args:
        P: (V, 3, 4) static cameras or (T, V, 3, 4) moving cameras (see
            :func:`projection_matrices`).
        points2d: (T, V, J, 2) pixel coordinates; NaN allowed where not seen.
        conf: (T, V, J) 2D confidences (0 = not detected).
        cfg: settings; defaults to :class:`TriangulationConfig`.

    Returns:
        :class:`Triangulation` (points (T, J, 3), conf (T, J), reproj_err_px / used (T, J, V),
        filled (T, J), long_gaps).

    Raises:
        ValueError: shapes that do not agree, fewer than 2 views, or ``min_views`` < 2.
    """
    cfg = cfg or TriangulationConfig()
    P, xy, w = _check_inputs(P, points2d, conf)
    if cfg.min_views < 2:
        raise ValueError(f"min_views must be at least 2, got {cfg.min_views}")
    T, J, V = w.shape
    seen = w >= cfg.min_conf
    w = np.where(seen, w, 0.0)
    used = seen.copy()

    X = _solve(P[:, None], xy, w)  # (T, J, 3)
    for _ in range(max(V - cfg.min_views, 0)):
        err = np.where(used, _reproj_err(P[:, None], X, xy), -np.inf)
        bad = (used.sum(-1) > cfg.min_views) & (err.max(axis=-1) > cfg.reject_px)
        if not bad.any():
            break
        t_idx, j_idx = np.nonzero(bad)
        P_sub = P[t_idx if P.shape[0] > 1 else np.zeros_like(t_idx)]
        drop, X_new = _drop_worst_view(P_sub, xy[t_idx, j_idx], w[t_idx, j_idx], used[t_idx, j_idx])
        keep = drop >= 0  # a point with no finite leave-one-out solve keeps its views
        t_idx, j_idx = t_idx[keep], j_idx[keep]
        used[t_idx, j_idx, drop[keep]] = False
        X[t_idx, j_idx] = X_new[keep]
        log.debug("rejection round: dropped one view of %d points", t_idx.size)

    n_used = used.sum(-1)
    valid = (n_used >= cfg.min_views) & _in_front(P[:, None], X, used)
    if cfg.drop_unresolved:
        with np.errstate(invalid="ignore"):
            worst = np.where(used, _reproj_err(P[:, None], X, xy), -np.inf).max(axis=-1)
        valid &= ~(worst > cfg.reject_px)
    X = np.where(valid[..., None], X, np.nan)
    # mean used confidence * (views used / V) is simply the used confidences summed over V
    point_conf = np.where(valid, (w * used).sum(-1) / V, 0.0)

    points, filled = fill_gaps(X, valid, cfg.max_gap_frames)
    long_gaps = [g for g in _gap_runs(valid) if not filled[g[1], g[0]]]
    err = np.where(seen, _reproj_err(P[:, None], points, xy), np.nan)
    if long_gaps:  # debug: callers triangulate many times per step; Stage IV reports the gaps once
        log.debug("%d gaps longer than %d frames left unfilled", len(long_gaps), cfg.max_gap_frames)
    return Triangulation(
        points=points, conf=point_conf, reproj_err_px=err, used=used & valid[..., None],
        filled=filled, long_gaps=long_gaps,
    )


def fill_gaps(points: F, valid: NDArray[np.bool_], max_gap: int) -> tuple[F, NDArray[np.bool_]]:
    """Fill short runs of invalid frames by linear interpolation between their neighbours.

    A gap is filled only if it has a valid frame on both sides and is at most ``max_gap`` frames
    long; gaps at the start or end of the sequence are never filled (no extrapolation).
    Vectorised over frames and joints: each frame finds its previous and next valid frame with a
    running max / min over the frame indices.

    Args:
        points: (T, J, D) values (D = 3 for points); rows where ``valid`` is False are ignored.
        valid: (T, J) True where ``points`` holds a measurement.
        max_gap: longest gap filled, frames.

    Returns:
        ``(points, filled)``: a new (T, J, D) array (NaN where invalid and not filled; valid rows
        unchanged) and a (T, J) mask of the filled rows.
    """
    points = np.asarray(points, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if points.ndim != 3 or valid.shape != points.shape[:2]:
        raise ValueError(f"points must be (T, J, D) and valid (T, J); got {points.shape} and {valid.shape}")
    T = valid.shape[0]
    frame = np.arange(T)[:, None]
    prev = np.maximum.accumulate(np.where(valid, frame, -1), axis=0)
    nxt = np.minimum.accumulate(np.where(valid, frame, T)[::-1], axis=0)[::-1]
    gap_len = nxt - prev - 1
    filled = ~valid & (prev >= 0) & (nxt < T) & (gap_len <= max_gap)
    cols = np.arange(valid.shape[1])[None, :]
    a = points[np.clip(prev, 0, T - 1), cols]
    b = points[np.clip(nxt, 0, T - 1), cols]
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = ((frame - prev) / np.maximum(nxt - prev, 1))[..., None]
    out = np.where(valid[..., None], points, np.nan)
    out = np.where(filled[..., None], (1 - alpha) * a + alpha * b, out)
    return out, filled


def triangulate_loop(P: F, points2d: F, conf: F, min_conf: float = 0.3) -> F:
    """Reference: plain unweighted DLT, one ``np.linalg.svd`` per frame and joint.

    What the paper's release does (there with 2 views): for each frame and joint, stack the DLT
    rows of every view whose confidence is at least ``min_conf`` (unweighted) and take the right
    singular vector of the smallest singular value. No rejection, no gap filling.

    Args:
        P: (V, 3, 4) or (T, V, 3, 4) projection matrices.
        points2d: (T, V, J, 2) pixels. conf: (T, V, J).
        min_conf: views below it are left out.

    Returns:
        (T, J, 3) points; NaN where fewer than 2 views are used.
    """
    P, xy, w = _check_inputs(P, points2d, conf)
    T, J, V = w.shape
    out = np.full((T, J, 3), np.nan)
    for t in range(T):
        Pt = P[t if P.shape[0] > 1 else 0]
        for j in range(J):
            rows = []
            for v in range(V):
                if w[t, j, v] >= min_conf:
                    x, y = xy[t, j, v]
                    rows.append(x * Pt[v, 2] - Pt[v, 0])
                    rows.append(y * Pt[v, 2] - Pt[v, 1])
            if len(rows) < 4:
                continue
            _, _, vh = np.linalg.svd(np.asarray(rows))
            out[t, j] = vh[-1, :3] / vh[-1, 3]
    return out


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _check_inputs(P: F, points2d: F, conf: F) -> tuple[F, F, F]:
    """Validate shapes; return P as (1 or T, V, 3, 4), xy (T, J, V, 2), conf (T, J, V).

    Non-finite 2D points get confidence 0 (and coordinates 0, so they add nothing to a solve).
    """
    P = np.asarray(P, dtype=np.float64)
    xy = np.asarray(points2d, dtype=np.float64)
    c = np.asarray(conf, dtype=np.float64)
    if xy.ndim != 4 or xy.shape[-1] != 2:
        raise ValueError(f"points2d must be (T, V, J, 2), got {xy.shape}")
    T, V, J, _ = xy.shape
    if c.shape != (T, V, J):
        raise ValueError(f"conf must be (T, V, J) = {(T, V, J)}, got {c.shape}")
    if V < 2:
        raise ValueError(f"triangulation needs at least 2 views, got {V}")
    if P.shape == (V, 3, 4):
        P = P[None]
    elif P.shape != (T, V, 3, 4):
        raise ValueError(f"P must be (V, 3, 4) or (T, V, 3, 4) with T = {T}, V = {V}; got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError("P holds NaN or infinite values")
    ok = np.all(np.isfinite(xy), axis=-1) & np.isfinite(c)
    xy = np.where(ok[..., None], xy, 0.0).transpose(0, 2, 1, 3)
    c = np.where(ok, c, 0.0).transpose(0, 2, 1)
    return P, xy, c


def _solve(P: F, xy: F, w: F) -> F:
    """Weighted DLT for a batch: P (..., V, 3, 4) broadcasting against xy (..., V, 2), w (..., V).

    Returns (..., 3) points (garbage, not NaN, where fewer than 2 views have weight; callers
    mask those).

    This is the paper's formulation as is (unit-norm homogeneous solution in the given world
    frame), so it equals the per-point SVD of the release. Like any DLT it is not invariant to a
    shift of the world origin under noise (the unit-norm constraint depends on it); moving the
    origin to the cameras' centre was tried and changes results by < 1 mm at 3 px noise, with no
    gain in accuracy. Forming A^T A squares the condition number, which grows with the distance
    from the origin: noise-free points 250 m away still come back within 1e-8 m.
    """
    rows = xy[..., :, None] * P[..., 2:3, :] - P[..., :2, :]  # (..., V, 2, 4)
    rows = rows * w[..., None, None]
    rows = rows.reshape(rows.shape[:-3] + (-1, 4))  # (..., 2V, 4)
    M = np.swapaxes(rows, -1, -2) @ rows
    # Scale each normal matrix to unit trace: eigenvectors are unchanged, and it keeps eigh's
    # absolute tolerances meaningful whatever the pixel and weight magnitudes.
    M = M / np.maximum(np.trace(M, axis1=-2, axis2=-1), 1e-300)[..., None, None]
    _, vecs = np.linalg.eigh(M)
    h = vecs[..., :, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        return h[..., :3] / h[..., 3:4]


def _drop_worst_view(P: F, xy: F, w: F, used: NDArray[np.bool_]) -> tuple[NDArray[np.intp], F]:
    """For N points, the view to drop and the point re-solved without it.

    The worst view is the one whose removal leaves the smallest largest reprojection error over
    the remaining used views (leave-one-out), not simply the view with the largest residual: a
    least-squares fit spreads a gross error over all views, so with three views the corrupted one
    does not always carry the largest residual.

    Args:
        P: (N, V, 3, 4); xy: (N, V, 2); w: (N, V) weights; used: (N, V) views in use.

    Returns:
        ``(view, X)``: (N,) index of the view to drop (-1 where no leave-one-out solve is finite)
        and (N, 3) the point solved without it.
    """
    V = used.shape[-1]
    keep = used[:, None, :] & ~np.eye(V, dtype=bool)  # (N, candidate, V)
    X_loo = _solve(P[:, None], xy[:, None], np.where(keep, w[:, None], 0.0))  # (N, V, 3)
    err = np.where(keep, _reproj_err(P[:, None], X_loo, xy[:, None]), -np.inf).max(axis=-1)
    err = np.where(used & np.isfinite(X_loo).all(-1), err, np.inf)  # only used views are candidates
    view = np.argmin(err, axis=-1)
    X = X_loo[np.arange(len(view)), view]
    return np.where(np.isfinite(err.min(axis=-1)), view, -1), X


def _project(P: F, X: F) -> tuple[F, F]:
    """Pixels (..., V, 2) and depths (..., V) of points X (..., 3) in cameras P (..., V, 3, 4)."""
    h = np.einsum("...vij,...j->...vi", P[..., :3], X) + P[..., 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        return h[..., :2] / h[..., 2:3], h[..., 2]


def _reproj_err(P: F, X: F, xy: F) -> F:
    """(..., V) pixel distance between xy (..., V, 2) and the projection of X (..., 3)."""
    uv, _ = _project(P, X)
    return np.linalg.norm(uv - xy, axis=-1)


def _in_front(P: F, X: F, used: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(...,) True where X lies in front of every used camera (a DLT can return a point behind
    them when the rays nearly diverge; such a point is not a triangulation)."""
    _, depth = _project(P, X)
    sign = np.sign(np.linalg.det(P[..., :3]))  # depth sign convention of a general P
    with np.errstate(invalid="ignore"):
        return np.all(~used | (depth * sign > 0), axis=-1)


def _gap_runs(valid: NDArray[np.bool_]) -> list[tuple[int, int, int]]:
    """Runs of invalid frames per joint as (joint, start, end) with ``end`` exclusive."""
    T, J = valid.shape
    bad = np.zeros((T + 2, J), dtype=np.int8)
    bad[1:-1] = ~valid
    edges = np.diff(bad, axis=0)  # +1 at a run's start, -1 one past its end
    # nonzero over the (J, T+1) transpose lists runs joint by joint in frame order, so starts and
    # ends pair up by position.
    joint, start = np.nonzero(edges.T == 1)
    _, end = np.nonzero(edges.T == -1)
    return [(int(j), int(s), int(e)) for j, s, e in zip(joint, start, end)]
