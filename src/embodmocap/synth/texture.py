"""A procedural solid (3D) texture: the colour of a surface point depends only on where it is.

Because the colour is a function of the 3D point, every view of a surface sees the same pattern,
so feature matching (SIFT) across views and across captures is geometrically consistent, and no
UV mapping is needed.

The pattern is built from hashed integer lattices ("blocky" value noise): the lattice is turned by
one fixed, generic rotation so that its cell walls are never parallel to the scene's axis-aligned
faces. A plane therefore slices the cubic cells into polygons of 3-6 sides with sharp edges and
corners at random angles: plenty of distinctive SIFT keypoints at 640 x 480 from 1-5 m, and no
flicker from faces lying on a lattice plane. Per material:

- a **cell** layer: per-cell mix between a base and an alternative colour, optionally with dark
  grout lines on the cell borders (tiles, planks);
- two **blob** octaves: per-cell brightness changes at the blob size and at ~0.37 of it.

Cost: ~70 float32 element operations per point, no temporaries larger than (N, 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Material:
    """Texture parameters of one material (plain tuples so the material is hashable).

    Attributes:
        name: e.g. ``"wall"``, ``"floor"``, ``"wood"``.
        base_rgb: (3,) colour in [0, 1] of half of the cells.
        alt_rgb: (3,) the other end of the per-cell colour mix.
        cell_m: (3,) cell size along the texture lattice's three axes, metres (anisotropic = planks).
        blob_m: size of the brightness blobs, metres (a second octave at 0.37 of it).
        contrast: brightness swing of the blobs, 0 (flat) .. ~0.7.
        grout_m: width of dark lines on the cell borders, metres (0 = none).
        grout_rgb: (3,) colour of those lines.
        seed: integer mixed into the lattice hash, so materials differ (lower 32 bits used).
        period: 0 for a non-repeating pattern; k > 0 makes the cell and blob layers repeat every k
            cells along each lattice axis (wallpaper, tiles: the repetitive walls that confuse
            feature matching, since many places then look alike).
    """

    name: str
    base_rgb: tuple[float, float, float]
    alt_rgb: tuple[float, float, float]
    cell_m: tuple[float, float, float]
    blob_m: float
    contrast: float
    grout_m: float
    grout_rgb: tuple[float, float, float]
    seed: int
    period: int = 0


# A fixed generic rotation (no cell wall parallel to any axis-aligned face).
def _generic_rotation() -> NDArray[np.float32]:
    a, b, c = 0.61, 0.83, 0.37  # radians about z, y, x
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(c), -np.sin(c)], [0, np.sin(c), np.cos(c)]])
    return (Rz @ Ry @ Rx).astype(np.float32)


#: (3, 3) rotation from the texture lattice frame to the scene frame.
LATTICE_ROTATION = _generic_rotation()

_LEVELS = 16  # per-cell colour mix is quantised to this many steps (+1 palette row for grout)


@lru_cache(maxsize=16)
def _tables(materials: tuple[Material, ...]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Per-material scalars (6, M) [1/cell x, y, z, 1/blob, contrast, grout] and the palette
    (M * (_LEVELS + 1), 3): row ``m * (_LEVELS + 1) + l`` is material m's colour at mix level l,
    the last row of each block its grout colour."""
    scalars = np.array(
        [[1 / m.cell_m[0], 1 / m.cell_m[1], 1 / m.cell_m[2], 1 / m.blob_m, m.contrast, m.grout_m] for m in materials],
        dtype=np.float32,
    ).T.copy()
    t = np.linspace(0.0, 1.0, _LEVELS)[:, None]
    palette = np.concatenate(
        [np.concatenate([np.asarray(m.base_rgb) + (np.subtract(m.alt_rgb, m.base_rgb)) * t, [m.grout_rgb]]) for m in materials]
    )
    return scalars, palette.astype(np.float32)


@lru_cache(maxsize=16)
def _seeds(materials: tuple[Material, ...]) -> NDArray[np.uint32]:
    return (np.array([m.seed for m in materials], dtype=np.uint64) & 0xFFFFFFFF).astype(np.uint32)


@lru_cache(maxsize=16)
def _periods(materials: tuple[Material, ...]) -> NDArray[np.float32]:
    return np.array([max(int(m.period), 0) for m in materials], dtype=np.float32)


def _wrap(c: NDArray[np.float32], period: NDArray[np.float32]) -> NDArray[np.float32]:
    """Lattice coordinates folded into ``[0, period)`` where ``period > 0`` (left alone elsewhere),
    so the hash of ``floor(c)`` repeats every ``period`` cells."""
    p = np.where(period > 0, period, np.float32(1.0))
    return np.where(period > 0, c - p * np.floor(c / p), c)


def _hash01(x: NDArray[np.float32], y: NDArray[np.float32], z: NDArray[np.float32], seed: NDArray[np.uint32]) -> NDArray[np.float32]:
    """A [0, 1) float per point from its integer cell ``floor(x, y, z)`` (each (N,)) and seed (N,)."""
    h = np.floor(x).astype(np.int32).view(np.uint32) * np.uint32(0x8DA6B343)
    h ^= np.floor(y).astype(np.int32).view(np.uint32) * np.uint32(0xD8163841)
    h ^= np.floor(z).astype(np.int32).view(np.uint32) * np.uint32(0xCB1AB31F)
    h ^= seed
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def albedo(points: NDArray, material_ids: NDArray, materials: tuple[Material, ...]) -> NDArray[np.float32]:
    """Surface colour of points.

    Args:
        points: (N, 3) surface points in the scene frame, metres (any float dtype).
        material_ids: (N,) integer index into ``materials`` of each point.
        materials: the palette (hashable; its tables are cached).

    Returns:
        (N, 3) float32 RGB albedo in [0, 1].
    """
    q = LATTICE_ROTATION.T @ np.asarray(points, dtype=np.float32).T
    return albedo_lattice(q, material_ids, materials)


_CHUNK = 16384  # points per pass: keeps every temporary in the CPU cache (2-3x faster than one pass)


def albedo_lattice(q: NDArray[np.float32], material_ids: NDArray, materials: tuple[Material, ...]) -> NDArray[np.float32]:
    """:func:`albedo` of points already in the lattice frame, ``q = LATTICE_ROTATION.T @ p``, given
    as (3, N) float32 rows (the renderer computes them directly from its rays, saving a pass)."""
    q = np.asarray(q, dtype=np.float32)
    mid = np.asarray(material_ids, dtype=np.intp)
    out = np.empty((q.shape[1], 3), dtype=np.float32)
    for s in range(0, q.shape[1], _CHUNK):
        out[s:s + _CHUNK] = _albedo_chunk(q[:, s:s + _CHUNK], mid[s:s + _CHUNK], tuple(materials))
    return out


def _albedo_chunk(q: NDArray[np.float32], mid: NDArray[np.intp], materials: tuple[Material, ...]) -> NDArray[np.float32]:
    scalars, palette = _tables(materials)
    mat_seed = _seeds(materials)[mid]
    # Structure of arrays: each coordinate and parameter a contiguous (N,) row (fast elementwise).
    qx, qy, qz = q
    inv_x, inv_y, inv_z, inv_blob, contrast, grout_m = (row[mid] for row in scalars)

    period = _periods(materials)[mid]
    repeat = bool(period.any())

    # Cell layer: per-cell colour mix level, grout on the cell borders.
    cx, cy, cz = qx * inv_x, qy * inv_y, qz * inv_z
    hx, hy, hz = (_wrap(c, period) for c in (cx, cy, cz)) if repeat else (cx, cy, cz)
    level = (_hash01(hx, hy, hz, mat_seed) * _LEVELS).astype(np.intp)
    border = None
    for c, inv in ((cx, inv_x), (cy, inv_y), (cz, inv_z)):
        f = c - np.floor(c)
        d = np.minimum(f, 1.0 - f) / inv  # metres to the nearest cell wall along this axis
        border = d if border is None else np.minimum(border, d)
    level[border < grout_m] = _LEVELS
    rgb = np.take(palette, mid * (_LEVELS + 1) + level, axis=0)

    # Two blob octaves: brightness only, so the colour layer stays readable.
    bx, by, bz = qx * inv_blob, qy * inv_blob, qz * inv_blob
    if repeat:  # blobs repeat with the cells: one period of cells holds cell/blob of them
        bp = period * np.maximum(np.round(inv_blob / np.minimum(inv_x, np.minimum(inv_y, inv_z))), 1)
        bx, by, bz = (_wrap(b, bp) for b in (bx, by, bz))
    k = _hash01(bx, by, bz, mat_seed ^ np.uint32(0x5BD1E995)) - 0.5
    s = np.float32(2.71)
    # (Folded blob coordinates make this octave repeat with the same period.)
    k += 0.6 * (_hash01(bx * s, by * s, bz * s, mat_seed ^ np.uint32(0x1B873593)) - 0.5)
    rgb *= (1.0 + contrast * k)[:, None]
    np.clip(rgb, 0.0, 1.0, out=rgb)
    return rgb


def relight(rgb: NDArray, gain: float, white_balance) -> NDArray:
    """The same image under other light: an exposure ``gain`` and a per-channel ``white_balance``
    (3,) multiplier, applied to linear light (sRGB decoded, scaled, re-encoded) and clipped like a
    sensor that saturates. (..., 3) uint8 in [0, 255] -> uint8, or float in [0, 1] -> float32."""
    is_int = np.asarray(rgb).dtype == np.uint8
    x = np.asarray(rgb, dtype=np.float32) / np.float32(255.0 if is_int else 1.0)
    x = np.clip(x, 0.0, 1.0)
    lin = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    lin = lin * (np.float32(gain) * np.asarray(white_balance, dtype=np.float32))
    np.clip(lin, 0.0, 1.0, out=lin)
    out = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055).astype(np.float32)
    return np.round(out * 255.0).astype(np.uint8) if is_int else out
