"""The scene as collision geometry: a MuJoCo heightfield of the support surfaces (coacd convex
pieces are not built: see docs/sim.md, Limits).

MuJoCo collides a ``mesh`` geom as its convex hull, so a room mesh given as one geom would be a
solid block. A heightfield is exact for everything a body can stand, sit or lie on, and cheap.

The height map is the package's own (:func:`embodmocap.export.mimickit.scene_heightmap`) of the
mesh without the faces that lie entirely above a cap (``cap_z``: the performer's highest point plus
a margin), so ceilings and lamps do not hide the floor. A cell whose centre at the cap is inside a
solid (the first surface straight up from there faces up, i.e. it is the inside of a box's top,
as in a wall) is raised to the cap, so walls stay walls.

MuJoCo's heightfield samples sit on a regular grid: with ``nrow x ncol`` samples and half sizes
``(rx, ry)``, samples lie ``2 rx / (ncol - 1)`` and ``2 ry / (nrow - 1)`` apart around the geom's
position, the ``elevation`` attribute listing rows from +y to -y (checked against ``mj_ray`` in the
tests), and MuJoCo interpolates between samples (two triangles per cell). Here the samples are
the centres of the height-map cells.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.export.mimickit import HeightMap, scene_heightmap


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


def heightfield_mjcf(hm: HeightMap, name: str = "scene", base_m: float = 0.5) -> tuple[str, str]:
    """MJCF ``<hfield>`` asset and ``<geom>`` for a height map: (asset line, geom line).

    ``base_m`` is the thickness of the solid below the lowest sample (a body pushed below the lowest
    surface still meets the field).
    """
    h = np.asarray(hm.heights, dtype=np.float64)
    H, W = h.shape
    if H < 2 or W < 2:  # MuJoCo needs at least 2 x 2 samples
        h = np.pad(h, ((0, max(0, 2 - H)), (0, max(0, 2 - W))), mode="edge")
        H, W = h.shape
    zmin, zmax = float(h.min()), float(h.max())
    span = max(zmax - zmin, 1e-3)
    rx, ry = (W - 1) * hm.cell_m / 2, (H - 1) * hm.cell_m / 2
    cx, cy = hm.origin[0] + hm.cell_m / 2 + rx, hm.origin[1] + hm.cell_m / 2 + ry
    # The elevation attribute lists rows from +y down to -y (as an image is stored): flip ours.
    elev = " ".join(f"{x:.5f}" for x in ((h[::-1] - zmin) / span).ravel())
    asset = (f'    <hfield name="{name}" nrow="{H}" ncol="{W}" size="{rx:.6g} {ry:.6g} {span:.6g} {base_m:.6g}" '
             f'elevation="{elev}"/>')
    geom = (f'    <geom name="{name}" type="hfield" hfield="{name}" pos="{cx:.6g} {cy:.6g} {zmin:.6g}" '
            f'contype="0" conaffinity="1" material="scene"/>')
    return asset, geom


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
