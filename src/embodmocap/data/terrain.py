"""Height maps of a scene and foot contacts: what a motion model learns the ground from.

- :func:`height_grid`: the scene mesh as a regular grid of ground heights (world Z, metres): the
  highest surface in each cell that a person could stand on, i.e. below ``floor + max_height_m``
  (floors, steps, tables and beds, not ceilings or the tops of walls). Triangles are sampled by
  area so that every cell a triangle covers gets points; empty cells take their nearest cell's
  height.
- :func:`sample_heights`: heights at any world x, y (nearest cell, clamped at the grid's edge).
- :func:`height_patch`: a square patch of the grid centred on a point (axis-aligned with the world).
- :func:`foot_contacts`: per-frame contact labels of the ankle and foot joints: near the ground
  under them and slow.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: SMPL joints whose contacts are labelled: left/right ankle, left/right foot (toe base).
CONTACT_JOINTS: tuple[int, ...] = (7, 8, 10, 11)


@dataclass(frozen=True)
class HeightGrid:
    """Ground heights on a regular grid.

    Attributes:
        origin_xy: (2,) world x, y of the centre of cell (0, 0), metres.
        cell_m: cell size, metres.
        heights: (H, W) float32 world z of the ground, metres; row = y index, column = x index.
    """

    origin_xy: NDArray[np.float64]
    cell_m: float
    heights: NDArray[np.float32]


def height_grid(vertices: NDArray, faces: NDArray, cell_m: float = 0.1, max_height_m: float = 1.2,
                max_samples: int = 4_000_000, seed: int = 0) -> HeightGrid:
    """The ground height grid of a triangle mesh (see the module docstring).

    Args:
        vertices: (V, 3) world metres, Z up; faces: (F, 3) vertex indices.
        cell_m: cell size, metres.
        max_height_m: surfaces higher than this above the floor (the 1st percentile of the sampled
            heights) are not ground.
        max_samples: cap on the points sampled on the triangles.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"expected vertices (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    # About 4 samples per cell of a triangle's area, and at least its three corners.
    n = np.minimum(np.ceil(area / (cell_m * cell_m) * 4.0).astype(np.int64), 10_000)
    scale = min(1.0, max_samples / max(1, int(n.sum())))
    n = np.maximum((n * scale).astype(np.int64), 0)
    rng = np.random.default_rng(seed)
    tri = np.repeat(np.arange(len(f)), n)
    r1, r2 = rng.random(len(tri)), rng.random(len(tri))
    s = np.sqrt(r1)
    pts = (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]
    pts = np.concatenate([pts, v], axis=0)
    floor = np.percentile(pts[:, 2], 1.0)
    pts = pts[pts[:, 2] <= floor + max_height_m]
    lo = pts[:, :2].min(axis=0)
    hi = pts[:, :2].max(axis=0)
    shape = np.floor((hi - lo) / cell_m).astype(np.int64) + 1  # (W, H)
    ij = np.floor((pts[:, :2] - lo) / cell_m).astype(np.int64)
    flat = ij[:, 1] * shape[0] + ij[:, 0]
    heights = np.full(int(shape[0] * shape[1]), -np.inf)
    np.maximum.at(heights, flat, pts[:, 2])
    heights = heights.reshape(int(shape[1]), int(shape[0]))
    empty = ~np.isfinite(heights)
    if empty.any():
        from scipy.ndimage import distance_transform_edt

        _, (ri, ci) = distance_transform_edt(empty, return_indices=True)
        heights = heights[ri, ci]
    return HeightGrid(lo + 0.5 * cell_m, float(cell_m), heights.astype(np.float32))


def sample_heights(grid: HeightGrid, xy: NDArray) -> NDArray[np.float32]:
    """Ground heights (...,) at world points ``xy`` (..., 2): nearest cell, clamped at the edges."""
    xy = np.asarray(xy, dtype=np.float64)
    col = np.clip(np.rint((xy[..., 0] - grid.origin_xy[0]) / grid.cell_m).astype(np.int64), 0, grid.heights.shape[1] - 1)
    row = np.clip(np.rint((xy[..., 1] - grid.origin_xy[1]) / grid.cell_m).astype(np.int64), 0, grid.heights.shape[0] - 1)
    return grid.heights[row, col]


def height_patch(grid: HeightGrid, center_xy: NDArray, size: int, cell_m: float | None = None) -> NDArray[np.float32]:
    """(size, size) ground heights on a square around ``center_xy`` (2,), rows along +y and
    columns along +x, ``cell_m`` apart (default: the grid's cell)."""
    step = grid.cell_m if cell_m is None else cell_m
    offs = (np.arange(size) - (size - 1) / 2.0) * step
    gx, gy = np.meshgrid(center_xy[0] + offs, center_xy[1] + offs)
    return sample_heights(grid, np.stack([gx, gy], axis=-1))


def foot_contacts(joints: NDArray, ground_z: NDArray, fps: float, height_m: float = 0.08,
                  speed_m_s: float = 0.4) -> NDArray[np.bool_]:
    """Contact labels of :data:`CONTACT_JOINTS`.

    Args:
        joints: (T, 24, 3) SMPL joints, world metres.
        ground_z: (T, 4) ground height under each contact joint, metres.
        fps: frames per second.
        height_m: a joint at most this far above the ground under it ...
        speed_m_s: ... and moving slower than this (central differences) is in contact.

    Returns:
        (T, 4) bool.
    """
    p = np.asarray(joints, dtype=np.float64)[:, CONTACT_JOINTS]  # (T, 4, 3)
    above = p[..., 2] - np.asarray(ground_z, dtype=np.float64)
    if len(p) > 1:
        vel = np.gradient(p, axis=0) * fps
        speed = np.linalg.norm(vel, axis=-1)
    else:
        speed = np.zeros(above.shape)
    return (above <= height_m) & (speed <= speed_m_s)
