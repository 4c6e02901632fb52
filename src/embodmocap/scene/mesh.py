"""Scene mesh clean-up, simplification, statistics and PLY files.

Meshes are plain arrays: ``vertices`` (V, 3) float64 metres (Z-up world), ``faces`` (F, 3) int64
vertex indices, ``colours`` (V, 3) float64 in [0, 1] or (0, 3) when there are none.

Clean-up (:func:`clean_mesh`) follows the paper's release (keep large connected components, drop
unreferenced vertices) but measures "large" relative to the largest component, so small scenes
and coarse voxels work too, and also drops compact floaters (noise blobs in free space).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import atomic_path
from embodmocap.scene.config import SceneConfig

log = logging.getLogger(__name__)


def _as_mesh(vertices, faces, colours) -> tuple[NDArray, NDArray, NDArray]:
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    c = np.zeros((0, 3)) if colours is None else np.asarray(colours, dtype=np.float64).reshape(-1, 3)
    if len(c) not in (0, len(v)):
        raise ValueError(f"{len(c)} colours for {len(v)} vertices")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("faces index vertices that do not exist")
    return v, f, c


def merge_duplicate_vertices(vertices, faces, colours=None) -> tuple[NDArray, NDArray, NDArray]:
    """Merge vertices with identical coordinates (TSDF meshes may repeat a vertex where voxel
    blocks meet, which would split connected components); faces are re-indexed."""
    v, f, c = _as_mesh(vertices, faces, colours)
    uniq, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    return uniq, inverse[f], c[first] if len(c) else c


def remove_unreferenced(vertices, faces, colours=None) -> tuple[NDArray, NDArray, NDArray]:
    """Drop vertices no face uses; faces are re-indexed (order of the kept vertices preserved)."""
    v, f, c = _as_mesh(vertices, faces, colours)
    used = np.zeros(len(v), dtype=bool)
    used[f.reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    return v[used], new_index[f], c[used] if len(c) else c


def face_components(vertices, faces) -> tuple[NDArray[np.int64], int]:
    """Connected component label (F,) of every face (faces sharing a vertex are connected) and
    the number of components."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v, f, _ = _as_mesh(vertices, faces, None)
    if len(f) == 0:
        return np.zeros(0, dtype=np.int64), 0
    # Edges 0-1 and 1-2 of every face connect all three of its vertices.
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(len(v), len(v)))
    n, labels = connected_components(graph, directed=False)
    comp = labels[f[:, 0]]
    # Relabel to 0..k-1 over components that own faces (isolated vertices are not components).
    uniq, comp = np.unique(comp, return_inverse=True)
    return comp.reshape(-1).astype(np.int64), len(uniq)


def clean_mesh(vertices, faces, colours=None, cfg: SceneConfig = SceneConfig()) -> tuple[NDArray, NDArray, NDArray]:
    """Remove small components and floaters, then unreferenced vertices.

    A component (faces connected through shared vertices) is kept when it has at least
    ``max(cfg.min_component_triangles, cfg.min_component_fraction * largest)`` faces and its
    bounding-box diagonal is at least ``cfg.floater_max_extent_m``, or when it spans at least
    ``cfg.structure_min_extent_m`` with at least ``cfg.min_component_triangles`` faces (real
    structure is never dropped for being small next to the floor). Duplicate vertices are merged
    first so that components are not split where voxel blocks meet.

    Returns:
        ``(vertices, faces, colours)`` of the cleaned mesh (new arrays; the inputs are untouched).
    """
    v, f, c = merge_duplicate_vertices(vertices, faces, colours)
    comp, n = face_components(v, f)
    if n == 0:
        return remove_unreferenced(v, f, c)
    size = np.bincount(comp, minlength=n)
    tri_v = v[f]  # (F, 3, 3)
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    np.minimum.at(lo, comp, tri_v.min(axis=1))
    np.maximum.at(hi, comp, tri_v.max(axis=1))
    extent = np.linalg.norm(hi - lo, axis=1)
    min_faces = max(cfg.min_component_triangles, cfg.min_component_fraction * size.max())
    keep_comp = (size >= min_faces) & (extent >= cfg.floater_max_extent_m)
    if cfg.structure_min_extent_m > 0:
        # Size relative to the largest piece says nothing about a ceiling seen from a few frames:
        # anything large enough in space is structure, however few faces it has.
        keep_comp |= (extent >= cfg.structure_min_extent_m) & (size >= cfg.min_component_triangles)
    if not keep_comp.any():  # never return nothing: keep the largest component at least
        keep_comp[np.argmax(size)] = True
    keep = keep_comp[comp]
    log.info("mesh clean-up: kept %d of %d components (%d of %d faces)",
             int(keep_comp.sum()), n, int(keep.sum()), len(f))
    return remove_unreferenced(v, f[keep], c)


def simplify_mesh(vertices, faces, colours=None, voxel_m: float = 0.05) -> tuple[NDArray, NDArray, NDArray]:
    """Simplify by vertex clustering on a ``voxel_m`` grid (Open3D; vertices in a cell are
    averaged), then drop degenerate faces and unreferenced vertices. For viewers and physics."""
    import open3d as o3d

    v, f, c = _as_mesh(vertices, faces, colours)
    if len(f) == 0:
        return v, f, c
    mesh = _to_open3d(v, f, c)
    out = mesh.simplify_vertex_clustering(
        voxel_size=float(voxel_m), contraction=o3d.geometry.SimplificationContraction.Average)
    out.remove_degenerate_triangles()
    out.remove_duplicated_triangles()
    out.remove_unreferenced_vertices()
    return _from_open3d(out)


def mesh_stats(vertices, faces) -> dict:
    """``{"vertices": V, "faces": F, "area_m2": total area, "bounds": [[xmin, ymin, zmin], [xmax, ymax, zmax]]}``."""
    v, f, _ = _as_mesh(vertices, faces, None)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    bounds = [v.min(0).tolist(), v.max(0).tolist()] if len(v) else [[0.0] * 3, [0.0] * 3]
    return {"vertices": int(len(v)), "faces": int(len(f)), "area_m2": float(area), "bounds": bounds}


# ------------------------------------------------------------------------------------------------
# PLY files


def _to_open3d(v: NDArray, f: NDArray, c: NDArray):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32)))
    if len(c):
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(c, 0.0, 1.0))
    return mesh


def _from_open3d(mesh) -> tuple[NDArray, NDArray, NDArray]:
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.triangles, dtype=np.int64)
    c = np.asarray(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors() else np.zeros((0, 3))
    return v, f, c


def write_mesh_ply(path: str | Path, vertices, faces, colours=None) -> Path:
    """Write a binary little-endian PLY atomically: vertex x, y, z (float64 as Open3D writes
    doubles), optional red, green, blue (uint8) per vertex, and face vertex_indices (int32)."""
    import open3d as o3d

    path = Path(path)
    v, f, c = _as_mesh(vertices, faces, colours)
    with atomic_path(path, suffix=".ply") as tmp:
        ok = o3d.io.write_triangle_mesh(str(tmp), _to_open3d(v, f, c), write_ascii=False, compressed=False,
                                        write_vertex_normals=False, write_vertex_colors=len(c) > 0,
                                        write_triangle_uvs=False, print_progress=False)
        if not ok:
            raise OSError(f"{path}: Open3D could not write the mesh")
    return path


def read_mesh_ply(path: str | Path) -> tuple[NDArray, NDArray, NDArray]:
    """Read a triangle mesh PLY as ``(vertices, faces, colours)`` (colours (0, 3) when absent)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found", "run the scene stage first")
    fast = _read_own_ply(path)
    if fast is not None:
        return fast
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0 and len(mesh.vertices) == 0:
        raise InputError(path, "not a readable triangle mesh (no vertices)", "write it again")
    return _from_open3d(mesh)


# The exact binary layout :func:`write_mesh_ply` produces (through Open3D): read with NumPy alone,
# which skips Open3D's import (~5 s, it pulls in its ML packages) for Stage III and the
# benchmarks; any other PLY goes through Open3D.
_OWN_VERTEX = (("x", "double"), ("y", "double"), ("z", "double"))
_OWN_COLOUR = (("red", "uchar"), ("green", "uchar"), ("blue", "uchar"))


def _read_own_ply(path: Path) -> tuple[NDArray, NDArray, NDArray] | None:
    """``(vertices, faces, colours)`` of a PLY in :func:`write_mesh_ply`'s layout, or None for any
    other layout (ASCII, other property types or order, more elements)."""
    with open(path, "rb") as fh:
        head = fh.read(4096)
        end = head.find(b"end_header\n")
        if not head.startswith(b"ply\n") or end < 0:
            return None
        lines = [ln.split() for ln in head[:end].decode("ascii", "replace").splitlines()[1:]]
        lines = [ln for ln in lines if ln and ln[0] != "comment"]
        if not lines or lines[0] != ["format", "binary_little_endian", "1.0"]:
            return None
        elems: list[tuple[str, int, list[tuple[str, ...]]]] = []
        for ln in lines[1:]:
            if ln[0] == "element" and len(ln) == 3:
                elems.append((ln[1], int(ln[2]), []))
            elif ln[0] == "property" and elems:
                elems[-1][2].append(tuple(ln[1:]))
            else:
                return None
        if [e[0] for e in elems] != ["vertex", "face"]:
            return None
        (_, nv, vprops), (_, nf, fprops) = elems
        props = [(p[1], p[0]) for p in vprops if len(p) == 2]
        has_colour = tuple(props) == _OWN_VERTEX + _OWN_COLOUR
        if len(props) != len(vprops) or not (has_colour or tuple(props) == _OWN_VERTEX):
            return None
        if fprops != [("list", "uchar", "uint", "vertex_indices")] and fprops != [("list", "uchar", "int", "vertex_indices")]:
            return None
        vdt = np.dtype([("xyz", "<f8", 3)] + ([("rgb", "u1", 3)] if has_colour else []))
        fdt = np.dtype([("n", "u1"), ("idx", "<u4" if fprops[0][2] == "uint" else "<i4", 3)])
        fh.seek(end + len(b"end_header\n"))
        data = fh.read()
    if len(data) != nv * vdt.itemsize + nf * fdt.itemsize:
        return None
    vert = np.frombuffer(data, vdt, count=nv)
    face = np.frombuffer(data, fdt, count=nf, offset=nv * vdt.itemsize)
    if nf and not np.all(face["n"] == 3):
        return None
    v = vert["xyz"].astype(np.float64)
    f = face["idx"].astype(np.int64)
    c = vert["rgb"].astype(np.float64) / 255.0 if has_colour else np.zeros((0, 3))
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        return None
    if nv == 0:
        raise InputError(path, "not a readable triangle mesh (no vertices)", "write it again")
    return v, f, c
