"""Z-up for a stitched, metric segment: from the phone's VIO when it has poses, else from the
dominant plane of the scene points (the floor).

- VIO: the rotation ``R = mean_i R^vio_i (R^st_i)^T`` (chordal mean over tracked frames) takes the
  stitched frame onto the VIO world's axes (Z up: the VIO world is gravity-aligned), so gravity
  and heading follow the phone; the translation puts the first tracked camera where the VIO has it.
- Plane: ``up0`` = the cameras' mean up direction (-y of OpenCV cameras, phones held upright);
  RANSAC planes whose normal is within 35 deg of ``up0`` and that lie below the mean camera
  centre; the one with most inliers (``inlier_m``) is refitted (least squares) and its normal
  (pointing to the cameras) turned onto +Z; the plane becomes z = 0 and the first camera x = y = 0.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.similarity import mean_rotation, rotation_between


def vio_alignment(R_stitch: NDArray, T_vio: NDArray) -> NDArray[np.float64]:
    """(4, 4) rigid transform taking metric stitched poses onto the VIO world's axes.

    Args:
        R_stitch: (n, 3, 3) camera rotations in the (metric) stitched frame.
        T_vio: (n, 4, 4) the VIO poses of the same frames.
    """
    R = mean_rotation(np.asarray(T_vio)[:, :3, :3] @ np.swapaxes(R_stitch, -1, -2))
    out = np.eye(4)
    out[:3, :3] = R
    return out


def floor_plane(points: NDArray, R_cams: NDArray, centres: NDArray, inlier_m: float = 0.03, iters: int = 300,
                seed: int = 0, min_below: float = 0.3) -> tuple[NDArray, float, float] | None:
    """The dominant plane below the cameras: (unit normal towards the cameras (3,), offset ``d``
    with ``n . x + d = 0``, inlier fraction), or None when no such plane holds 5 % of the points.

    Args:
        points: (N, 3) metric points; ``R_cams`` (n, 3, 3) and ``centres`` (n, 3) the cameras.
        min_below: the plane lies at least this far below the mean camera centre.
    """
    P = np.asarray(points, dtype=np.float64)
    if len(P) < 3:
        return None
    up0 = -np.asarray(R_cams)[:, :, 1].sum(0)
    up0 /= np.linalg.norm(up0)
    cbar = np.asarray(centres).mean(0)
    rng = np.random.default_rng(seed)
    best, best_n = None, 0
    tri = rng.integers(0, len(P), size=(iters, 3))
    for a, b, c in tri:
        n = np.cross(P[b] - P[a], P[c] - P[a])
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        if n @ up0 < 0:
            n = -n
        if n @ up0 < np.cos(np.deg2rad(35)):
            continue
        d = -n @ P[a]
        if n @ cbar + d < min_below:  # the floor is below the cameras
            continue
        k = int((np.abs(P @ n + d) < inlier_m).sum())
        if k > best_n:
            best, best_n = (n, d), k
    if best is None or best_n < 0.05 * len(P):
        return None
    n, d = best
    inl = P[np.abs(P @ n + d) < inlier_m]
    mu = inl.mean(0)
    n = np.linalg.svd(inl - mu, full_matrices=False)[2][-1]  # not full: U would be (N, N)
    if n @ up0 < 0:
        n = -n
    return n, float(-n @ mu), best_n / len(P)


def plane_alignment(normal: NDArray, d: float, first_centre: NDArray) -> NDArray[np.float64]:
    """(4, 4) rigid transform turning the plane's normal onto +Z, the plane to z = 0 and the first
    camera to x = y = 0."""
    R = rotation_between(normal, np.array([0.0, 0.0, 1.0]))
    out = np.eye(4)
    out[:3, :3] = R
    c = R @ first_centre
    out[:3, 3] = [-c[0], -c[1], d]  # a point x on the plane: n.x = -d -> z = -d + d = 0
    return out


def world_alignment(T_metric: NDArray, points: NDArray, T_vio: NDArray | None) -> tuple[NDArray[np.float64], str]:
    """(4, 4) rigid transform taking one metric segment into the Z-up world, and where up came from.

    Args:
        T_metric: (n, 4, 4) the segment's metric stitched poses.
        points: (N, 3) its metric stitched scene points (for the plane).
        T_vio: (n, 4, 4) the VIO poses of the same frames, NaN rows for untracked frames; None =
            use the floor plane.

    Returns:
        The transform and ``"vio"``, ``"plane"`` or ``"cameras"`` (no plane found: the cameras'
        mean up direction; the caller warns).
    """
    if T_vio is not None and np.isfinite(T_vio[:, 0, 0]).any():
        tr = np.flatnonzero(np.isfinite(T_vio[:, 0, 0]))
        A = vio_alignment(T_metric[tr, :3, :3], T_vio[tr])
        A[:3, 3] = T_vio[tr[0], :3, 3] - A[:3, :3] @ T_metric[tr[0], :3, 3]
        return A, "vio"
    pl = floor_plane(points, T_metric[:, :3, :3], T_metric[:, :3, 3])
    if pl is not None:
        return plane_alignment(pl[0], pl[1], T_metric[0, :3, 3]), "plane"
    A = np.eye(4)
    A[:3, :3] = rotation_between(-T_metric[:, :3, 1].sum(0), np.array([0.0, 0.0, 1.0]))
    A[:3, 3] = -A[:3, :3] @ T_metric[0, :3, 3]
    return A, "cameras"
