"""Height maps of a scene mesh (Z up, metres): the highest surface per grid cell, the support
surfaces under a cap (no ceilings), and bilinear sampling.

Shared by the MimicKit export (``scene_heightmap.npz``), the MuJoCo heightfield of ``embodmocap sim``
and the robot retargeting's ground. Cells: ``heights[i, j]`` covers ``x in [origin_x + j * cell_m,
+cell_m)`` and ``y in [origin_y + i * cell_m, +cell_m)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class HeightMap:
    """Highest scene surface per grid cell, world Z up, metres.

    Attributes:
        heights: (H, W) float32; ``heights[i, j]`` covers ``x in [origin_x + j * cell_m, +cell_m)``
            and ``y in [origin_y + i * cell_m, +cell_m)``; NaN where no surface.
        origin: (2,) world (x, y) of the corner of cell [0, 0], metres.
        cell_m: cell size, metres.
    """

    heights: NDArray[np.float32]
    origin: NDArray[np.float64]
    cell_m: float

    def __post_init__(self) -> None:
        h = np.array(self.heights, dtype=np.float32, copy=True)
        o = np.array(self.origin, dtype=np.float64, copy=True).reshape(2)
        h.setflags(write=False)
        o.setflags(write=False)
        object.__setattr__(self, "heights", h)
        object.__setattr__(self, "origin", o)
        if h.ndim != 2 or not self.cell_m > 0:
            raise ValueError(f"heights must be (H, W) and cell_m > 0; got {h.shape}, {self.cell_m}")


def scene_heightmap(vertices: NDArray, faces: NDArray, *, cell_m: float = 0.05, subsamples: int = 3,
                    margin_m: float = 0.0) -> HeightMap:
    """Height map of a triangle mesh (Z up): the highest surface in each ``cell_m`` cell.

    Rays are cast straight down at ``subsamples x subsamples`` points spread evenly inside every
    cell (never on its border, so a wall standing on a cell border does not raise the cell next
    to it) and the highest hit is kept. Cells with no hit are NaN. The grid covers the mesh's xy
    bounding box grown by ``margin_m``.
    """
    import open3d as o3d

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(v) == 0 or len(f) == 0:
        raise ValueError("the mesh is empty")
    lo = v[:, :2].min(axis=0) - margin_m
    W, H = np.maximum(np.ceil((v[:, :2].max(axis=0) + margin_m - lo) / cell_m).astype(int), 1)
    # Sub-sample centres inside each cell, as fractions of the cell.
    frac = (np.arange(subsamples) + 0.5) / subsamples
    ii, jj, a, b = np.meshgrid(np.arange(H), np.arange(W), frac, frac, indexing="ij")
    x = lo[0] + (jj + b) * cell_m
    y = lo[1] + (ii + a) * cell_m
    top = v[:, 2].max() + 1.0
    rays = np.stack([x, y, np.full_like(x, top), np.zeros_like(x), np.zeros_like(x), -np.ones_like(x)], axis=-1)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    t = scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6).astype(np.float32)))["t_hit"].numpy()
    z = np.where(np.isfinite(t), top - t, -np.inf).reshape(H, W, -1).max(axis=-1)
    heights = np.where(np.isfinite(z), z, np.nan).astype(np.float32)
    return HeightMap(heights=heights, origin=lo, cell_m=float(cell_m))


def support_heightmap(vertices: NDArray, faces: NDArray, cap_z: float, *, cell_m: float = 0.05,
                      xy_lo: NDArray | None = None, xy_hi: NDArray | None = None) -> HeightMap:
    """Height map of the surfaces below ``cap_z`` (Z up, metres); solids rising through the cap
    give the cap; empty cells get the lowest height found.

    Args:
        vertices: (N, 3) scene mesh vertices; faces: (F, 3) triangles.
        cap_z: height above which faces are ignored, metres.
        xy_lo, xy_hi: (2,) optional footprint; only faces touching it are used (the map then covers
            those faces' bounding box).
    """
    import open3d as o3d

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fz = v[f, 2]
    keep = fz.min(axis=1) < cap_z
    if xy_lo is not None and xy_hi is not None:
        fxy = v[f, :2]
        keep &= np.all(fxy.max(axis=1) >= np.asarray(xy_lo), axis=1) & np.all(fxy.min(axis=1) <= np.asarray(xy_hi), axis=1)
    if not keep.any():
        raise ValueError("no scene surface below the cap in the motion's footprint")
    used = np.unique(f[keep])
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    hm = scene_heightmap(v[used], remap[f[keep]], cell_m=cell_m)
    H, W = hm.heights.shape
    # Inside a solid at the cap? Cast straight up from each cell centre against the full mesh.
    ii, jj = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    x = hm.origin[0] + (jj + 0.5) * cell_m
    y = hm.origin[1] + (ii + 0.5) * cell_m
    rays = np.stack([x, y, np.full_like(x, cap_z), np.zeros_like(x), np.zeros_like(x), np.ones_like(x)], axis=-1)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    hit = scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6).astype(np.float32)))
    inside = (np.isfinite(hit["t_hit"].numpy()) & (hit["primitive_normals"].numpy()[:, 2] > 0)).reshape(H, W)
    h = np.minimum(np.array(hm.heights, dtype=np.float64), cap_z)
    h[inside] = cap_z
    h = np.where(np.isnan(h), np.nanmin(h) if np.isfinite(h).any() else 0.0, h)
    return HeightMap(heights=h.astype(np.float32), origin=hm.origin, cell_m=hm.cell_m)


def sample_heightmap(hm: HeightMap, xy: NDArray) -> NDArray[np.float64]:
    """Bilinear height (..., ) at world points ``xy`` (..., 2) between cell centres (clamped at the
    border); MuJoCo's heightfield splits each cell into two triangles instead, which differs only
    across edges."""
    xy = np.asarray(xy, dtype=np.float64)
    h = np.asarray(hm.heights, dtype=np.float64)
    H, W = h.shape
    u = np.clip((xy[..., 0] - hm.origin[0]) / hm.cell_m - 0.5, 0, W - 1)
    w = np.clip((xy[..., 1] - hm.origin[1]) / hm.cell_m - 0.5, 0, H - 1)
    c0, r0 = np.minimum(np.floor(u).astype(int), max(W - 2, 0)), np.minimum(np.floor(w).astype(int), max(H - 2, 0))
    c1, r1 = np.minimum(c0 + 1, W - 1), np.minimum(r0 + 1, H - 1)
    a, b = u - c0, w - r0
    return (h[r0, c0] * (1 - a) * (1 - b) + h[r0, c1] * a * (1 - b) + h[r1, c0] * (1 - a) * b + h[r1, c1] * a * b)


def egocentric_heightmap(heightmap: HeightMap, xy: NDArray, yaw: NDArray, size: int = 11, spacing: float = 0.2,
                         fill: float = np.nan) -> NDArray[np.float32]:
    """Sample a ``size x size`` grid of heights around root positions, turning with the heading.

    Args:
        heightmap: the scene's :class:`HeightMap`.
        xy: (..., 2) root positions, world metres.
        yaw: (...) heading about +Z, radians (0 = facing +X).
        size: grid points per side (the paper: 11).
        spacing: distance between grid points, metres (the paper: 0.2, i.e. 2 m x 2 m).
        fill: value where the grid leaves the map or the cell is empty.

    Returns:
        (..., size, size) heights, world z in metres; ``out[..., i, k]`` is at ``(i - c) *
        spacing`` ahead of the root and ``(k - c) * spacing`` to its left, ``c = (size - 1) / 2``,
        read from the nearest cell.
    """
    xy = np.asarray(xy, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    offs = (np.arange(size) - (size - 1) / 2.0) * spacing
    fwd, left = np.meshgrid(offs, offs, indexing="ij")  # (size, size)
    c, s = np.cos(yaw)[..., None, None], np.sin(yaw)[..., None, None]
    x = xy[..., 0, None, None] + c * fwd - s * left
    y = xy[..., 1, None, None] + s * fwd + c * left
    col = np.floor((x - heightmap.origin[0]) / heightmap.cell_m).astype(np.int64)
    row = np.floor((y - heightmap.origin[1]) / heightmap.cell_m).astype(np.int64)
    H, W = heightmap.heights.shape
    inside = (row >= 0) & (row < H) & (col >= 0) & (col < W)
    out = heightmap.heights[np.clip(row, 0, H - 1), np.clip(col, 0, W - 1)]
    out = np.where(inside, out, np.float32(fill))
    return np.where(np.isnan(out), np.float32(fill), out).astype(np.float32)
