"""The floor of a scene mesh: the dominant low, near-horizontal plane, and how far it is tilted.

A gravity-aligned (Z-up) scene has a horizontal floor; a capture read with the wrong gravity
(e.g. poses relative to the first camera) gives a floor tilted by the first camera's pitch and
roll. :func:`find_floor` measures that from the mesh alone, so nothing downstream inherits a
tilted world silently.

Method (area-weighted over faces, both windings accepted):

1. faces whose normal lies within ``max_tilt_deg`` of +Z are the horizontal candidates; their
   common direction ``u`` is refined twice by an area-weighted mean over the faces within
   ``band_deg`` of it (tables and the floor share it; slopes drop out);
2. along ``u``, face heights are binned (``bin_m``); the floor is the lowest bin holding at least
   ``min_bin_share`` of the fullest bin's area (low and dominant: a few stray faces below it do
   not count);
3. the faces of that bin (within ``inlier_m`` of its height and ``band_deg`` of ``u``) are fitted
   with an area-weighted plane through their corners, refitted twice with the inliers of the
   previous fit. The tilt is the angle between its upward normal and +Z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class FloorPlane:
    """The floor found in a mesh.

    Attributes:
        normal: (3,) unit normal, pointing up (positive z).
        offset_m: ``d`` with ``normal . x = d`` on the plane (metres).
        tilt_deg: angle between ``normal`` and +Z, degrees.
        area_m2: area of the mesh faces on the plane.
        height_m: the plane's height at the inliers' centroid (z, metres).
    """

    normal: NDArray[np.float64]
    offset_m: float
    tilt_deg: float
    area_m2: float
    height_m: float


def face_geometry(vertices: NDArray, faces: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """(unit normals (F, 3) flipped to z >= 0, areas (F,), centroids (F, 3), corners (F, 3, 3))
    of a triangle mesh."""
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    n, area = _unit_normals(v, f)
    tri = v[f]
    return n, area, tri.mean(axis=1), tri


def _unit_normals(v: NDArray[np.float64], f: NDArray[np.int64]) -> tuple[NDArray, NDArray]:
    """(unit normals (F, 3) flipped to z >= 0, areas (F,)) as :func:`face_geometry` computes them,
    without its (F, 3, 3) corners."""
    a = v[f[:, 0]]
    n = np.cross(v[f[:, 1]] - a, v[f[:, 2]] - a)
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-15
    n = np.where(ok[:, None], n / np.where(ok, length, 1.0)[:, None], 0.0)
    n = np.where(n[:, 2:3] < 0, -n, n)
    return n, 0.5 * length


def find_floor(vertices: NDArray, faces: NDArray, *, max_tilt_deg: float = 30.0, band_deg: float = 10.0,
               bin_m: float = 0.02, min_bin_share: float = 0.25, inlier_m: float = 0.03,
               min_area_m2: float = 0.25) -> FloorPlane | None:
    """The dominant low near-horizontal plane of a mesh, or None when there is none.

    Args:
        vertices: (V, 3) metres, Z up expected (a tilt up to ``max_tilt_deg`` is still found).
        faces: (F, 3) vertex indices.
        max_tilt_deg: faces whose normal is farther than this from +Z are never floor.
        band_deg: faces within this of the common horizontal direction are horizontal.
        bin_m: height bin along that direction, metres.
        min_bin_share: the floor's bin holds at least this share of the fullest bin's area.
        inlier_m: faces within this of the plane are its inliers, metres.
        min_area_m2: a floor smaller than this is no floor (returns None).
    """
    if len(faces) == 0:
        return None
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n, area = _unit_normals(v, f)
    # Only the candidates are used from here on: their corners and centroids alone, not the
    # (F, 3, 3) corners of a scan's millions of walls and ceiling faces too.
    keep = np.flatnonzero((n[:, 2] > np.cos(np.deg2rad(max_tilt_deg))) & (area > 0))
    n, area = n[keep], area[keep]
    if area.sum() < min_area_m2:
        return None
    tri = v[f[keep]]
    cen = tri.mean(axis=1)
    u = _mean_direction(n, area)
    cos_band = np.cos(np.deg2rad(band_deg))
    for _ in range(2):
        near = n @ u > cos_band
        if not near.any():
            return None
        u = _mean_direction(n[near], area[near])
    near = n @ u > cos_band
    h = cen[near] @ u
    lo = h.min()
    bins = np.floor((h - lo) / bin_m).astype(np.int64)
    hist = np.bincount(bins, weights=area[near])
    floor_bin = int(np.nonzero(hist >= min_bin_share * hist.max())[0][0])
    # The bin and its neighbours (a flat floor's faces straddle a bin edge).
    h0 = lo + (floor_bin + 0.5) * bin_m
    inl = np.nonzero(near)[0][np.abs(h - h0) <= max(inlier_m, bin_m)]
    normal, d = u, h0
    for _ in range(3):
        if area[inl].sum() < min_area_m2:
            return None
        # Corners, not centroids: a coarse mesh's floor may be two large triangles.
        normal, d = _plane_fit(tri[inl].reshape(-1, 3), np.repeat(area[inl], 3))
        if normal[2] < 0:
            normal, d = -normal, -d
        dist = np.abs(cen @ normal - d)
        inl = np.nonzero((dist <= inlier_m) & (n @ normal > cos_band))[0]
    if area[inl].sum() < min_area_m2:
        return None
    tilt = float(np.degrees(np.arccos(np.clip(normal[2], -1.0, 1.0))))
    c = np.average(cen[inl], axis=0, weights=area[inl])
    return FloorPlane(normal, float(d), tilt, float(area[inl].sum()), float(c[2]))


def _mean_direction(n: NDArray, w: NDArray) -> NDArray[np.float64]:
    m = (n * w[:, None]).sum(axis=0)
    return m / np.linalg.norm(m)


def _plane_fit(points: NDArray, w: NDArray) -> tuple[NDArray[np.float64], float]:
    """Weighted least-squares plane: (unit normal (3,), d with normal . x = d)."""
    c = np.average(points, axis=0, weights=w)
    X = (points - c) * np.sqrt(w / w.sum())[:, None]
    normal = np.linalg.svd(X, full_matrices=False)[2][-1]
    return normal, float(normal @ c)
