"""Triangle mesh files (PLY) and the plain-array mesh every package passes around.

A mesh is three arrays: ``vertices`` (V, 3) float64 metres (Z-up world), ``faces`` (F, 3) int64
vertex indices, ``colours`` (V, 3) float64 in [0, 1] or (0, 3) when there are none. Open3D does
the PLY work; it is imported only when a file is read or written (the ``scene`` extra).
"""

from __future__ import annotations

import io
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


def as_stored(vertices, faces, colours=None) -> tuple[NDArray, NDArray, NDArray]:
    """The arrays :func:`read_mesh_ply` gives back for a mesh :func:`write_mesh_ply` wrote, without
    the file: vertices as float64, faces as int64, colours in [0, 1] rounded to 8 bits (as Open3D
    writes them: nearest step, halves up). Lets a step use a mesh it has just written exactly as
    the next run would read it."""
    v, f, c = as_mesh(vertices, faces, colours)
    if len(c):
        c = np.floor(np.clip(c, 0.0, 1.0) * 255.0 + 0.5) / 255.0
    return v, f, c


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
    return from_open3d(mesh)


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


def obj_text(vertices: NDArray, faces: NDArray) -> str:
    """A Wavefront OBJ (``v x y z`` lines, then 1-based ``f a b c`` lines), coordinates as given."""
    buf = io.StringIO()
    buf.write("# embodmocap scene mesh: Z up, metres\n")
    np.savetxt(buf, np.asarray(vertices, dtype=np.float64), fmt="v %.6f %.6f %.6f")
    np.savetxt(buf, np.asarray(faces, dtype=np.int64) + 1, fmt="f %d %d %d")
    return buf.getvalue()
