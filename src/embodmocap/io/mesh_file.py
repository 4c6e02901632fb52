"""Triangle mesh files (PLY) and the plain-array mesh every package passes around.

A mesh is three arrays: ``vertices`` (V, 3) float64 metres (Z-up world), ``faces`` (F, 3) int64
vertex indices, ``colours`` (V, 3) float64 in [0, 1] or (0, 3) when there are none. Open3D does
the PLY work; it is imported only when a file is read or written (the ``scene`` extra).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import atomic_path


def as_mesh(vertices, faces, colours=None) -> tuple[NDArray, NDArray, NDArray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64, colours (V, 3) or (0, 3) float64)``, checked:
    one colour per vertex (or none) and faces that index existing vertices (ValueError)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    c = np.zeros((0, 3)) if colours is None else np.asarray(colours, dtype=np.float64).reshape(-1, 3)
    if len(c) not in (0, len(v)):
        raise ValueError(f"{len(c)} colours for {len(v)} vertices")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("faces index vertices that do not exist")
    return v, f, c


def to_open3d(v: NDArray, f: NDArray, c: NDArray):
    """An ``open3d.geometry.TriangleMesh`` of checked arrays (see :func:`as_mesh`)."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32)))
    if len(c):
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(c, 0.0, 1.0))
    return mesh


def from_open3d(mesh) -> tuple[NDArray, NDArray, NDArray]:
    """``(vertices, faces, colours)`` arrays of an Open3D triangle mesh (colours (0, 3) when absent)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.triangles, dtype=np.int64)
    c = np.asarray(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors() else np.zeros((0, 3))
    return v, f, c


def write_mesh_ply(path: str | Path, vertices, faces, colours=None) -> Path:
    """Write a binary little-endian PLY atomically: vertex x, y, z (float64 as Open3D writes
    doubles), optional red, green, blue (uint8) per vertex, and face vertex_indices (int32)."""
    import open3d as o3d

    path = Path(path)
    v, f, c = as_mesh(vertices, faces, colours)
    with atomic_path(path, suffix=".ply") as tmp:
        ok = o3d.io.write_triangle_mesh(str(tmp), to_open3d(v, f, c), write_ascii=False, compressed=False,
                                        write_vertex_normals=False, write_vertex_colors=len(c) > 0,
                                        write_triangle_uvs=False, print_progress=False)
        if not ok:
            raise OSError(f"{path}: Open3D could not write the mesh")
    return path


def read_mesh_ply(path: str | Path) -> tuple[NDArray, NDArray, NDArray]:
    """Read a triangle mesh PLY as ``(vertices, faces, colours)`` (colours (0, 3) when absent)."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found", "run the scene stage first")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0 and len(mesh.vertices) == 0:
        raise InputError(path, "not a readable triangle mesh (no vertices)", "write it again")
    return from_open3d(mesh)
