"""Scene mesh clean-up, simplification and statistics (PLY files: :mod:`embodmocap.io.mesh_file`).

Meshes are plain arrays: ``vertices`` (V, 3) float64 metres (Z-up world), ``faces`` (F, 3) int64
vertex indices, ``colours`` (V, 3) float64 in [0, 1] or (0, 3) when there are none.

Clean-up (:func:`clean_mesh`) follows the paper's release (keep large connected components, drop
unreferenced vertices) but measures "large" relative to the largest component, so small scenes
and coarse voxels work too, and also drops compact floaters (noise blobs in free space).
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from embodmocap.io.mesh_file import as_mesh as _as_mesh, from_open3d as _from_open3d, to_open3d as _to_open3d
from embodmocap.io.mesh_file import read_mesh_ply, write_mesh_ply  # noqa: F401 (moved to io; old import path kept)
from embodmocap.scene.config import SceneConfig

log = logging.getLogger(__name__)


def merge_duplicate_vertices(vertices, faces, colours=None) -> tuple[NDArray, NDArray, NDArray]:
    """Merge vertices with identical coordinates (TSDF meshes may repeat a vertex where voxel
    blocks meet, which would split connected components); faces are re-indexed."""
    v, f, c = _as_mesh(vertices, faces, colours)
    if len(v) == 0:
        return v, f, c
    # As np.unique(v, axis=0, return_index=True, return_inverse=True) (rows sorted by x, then y,
    # then z; each kept at its first occurrence), but a stable lexsort of the three columns is
    # several times faster than unique's sort of whole rows on a few million vertices.
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    vs = v[order]
    new = np.empty(len(v), dtype=bool)
    new[0] = True
    new[1:] = np.any(vs[1:] != vs[:-1], axis=1)
    inverse = np.empty(len(v), dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    first = order[new]
    return vs[new], inverse[f], c[first] if len(c) else c


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
    # Relabel to 0..k-1 over components that own faces (isolated vertices are not components), in
    # the order of the old labels (as np.unique's inverse, without its sort of F labels).
    owns = np.zeros(n, dtype=bool)
    owns[comp] = True
    new_label = np.cumsum(owns) - 1
    return new_label[comp].astype(np.int64), int(owns.sum())


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
    lo, hi = _component_bounds(v, f, comp, n)
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


def _component_bounds(v: NDArray, f: NDArray, comp: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """Bounding boxes ``(lo (n, 3), hi (n, 3))`` of the ``n`` face components ``comp`` (F,).

    Every vertex a face uses belongs to that face's component, so a component's box is the box of
    its vertices: one stable sort of the V vertex labels and a segmented min / max, instead of
    ``np.minimum.at`` over the F x 3 corners (about 10x the time on a 5 M-face scan).
    """
    label = np.full(len(v), n, dtype=np.int64)  # n: used by no face (sorts last, never read)
    for k in range(3):
        label[f[:, k]] = comp
    order = np.argsort(label, kind="stable")
    start = np.searchsorted(label[order], np.arange(n + 1))  # every component has >= 3 vertices
    vs = v[order[: start[-1]]]  # without the unused vertices: the last segment ends with its component
    start = start[:-1]
    return np.minimum.reduceat(vs, start, axis=0), np.maximum.reduceat(vs, start, axis=0)


def _unique_rows(rows: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
    """``np.unique(rows, axis=0, return_inverse=True, return_counts=True)`` for (N, 3) integer rows
    >= 0: the same arrays (rows in lexicographic order), through one int64 key per row when the
    rows' box fits one (much faster than unique's sort of whole rows), else unique itself."""
    if len(rows) == 0 or rows.min() < 0:
        uniq, inverse, count = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
        return uniq, inverse.reshape(-1), count
    dims = rows.max(axis=0).astype(np.int64) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        uniq, inverse, count = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
        return uniq, inverse.reshape(-1), count
    key = (rows[:, 0] * dims[1] + rows[:, 1]) * dims[2] + rows[:, 2]  # increasing in (x, y, z) order
    ukey, inverse, count = np.unique(key, return_inverse=True, return_counts=True)
    uniq = np.stack([ukey // (dims[1] * dims[2]), (ukey // dims[2]) % dims[1], ukey % dims[2]], axis=1)
    return uniq.astype(rows.dtype), inverse.reshape(-1), count


def _sum_at(index: NDArray, values: NDArray, n: int) -> NDArray[np.float64]:
    """``out = zeros((n,) + values.shape[1:]); np.add.at(out, index, values)``, bit for bit (both add
    in index order), through ``np.bincount`` per column (several times faster)."""
    if values.ndim == 1:
        return np.bincount(index, weights=values, minlength=n)
    return np.stack([np.bincount(index, weights=values[:, k], minlength=n) for k in range(values.shape[1])], axis=1)


def simplify_mesh(vertices, faces, colours=None, voxel_m: float = 0.05) -> tuple[NDArray, NDArray, NDArray]:
    """Simplify by vertex clustering on a ``voxel_m`` grid (the vertices of a cell are averaged into
    one), keeping every face oriented like the surface it replaces. For viewers and physics.

    A face of the input whose three vertices fall in three different cells becomes a face of the
    output; the faces that land on the same three cells are merged into one. Its winding is chosen
    by a vote: the area-weighted normals of the input faces it replaces plus those of all input
    faces touching its three cells, projected on its normal, must sum to a positive number. Why a
    vote and not the input winding: averaging moves vertices, so a small face can come out turned
    over; where two sheets a few mm apart collapse into the same cells (a TSDF floor with a thin
    pocket under it) their faces land on the same cells with opposite windings, and keeping
    either at random (Open3D's clustering + duplicate removal kept both) left 4-7 % of a scanned
    floor's area facing down, which a consumer testing the side of a point by its closest face
    (``sim check``) reads as solid above the floor. The faces touching the cells, not only the few
    that span three of them, outvote the single turned-over faces of the TSDF's own noise (~1 %
    of a scanned floor).

    Returns:
        ``(vertices (V', 3), faces (F', 3), colours (V', 3) or (0, 3))``, new arrays.
    """
    v, f, c = _as_mesh(vertices, faces, colours)
    if len(f) == 0:
        return v, f, c
    voxel = float(voxel_m)
    cell = np.floor((v - v.min(axis=0)) / voxel).astype(np.int64)  # (V, 3)
    _, cluster, count = _unique_rows(cell)
    nv = len(count)
    cv = _sum_at(cluster, v, nv)
    cv /= count[:, None]
    if len(c):
        cc = _sum_at(cluster, c, nv)
        cc /= count[:, None]
    else:
        cc = c
    cf = cluster[f]  # (F, 3)
    ok = (cf[:, 0] != cf[:, 1]) & (cf[:, 1] != cf[:, 2]) & (cf[:, 0] != cf[:, 2])
    if not ok.any():
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    cf = cf[ok]
    tri = v[f[ok]]
    n_in = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F', 3), |.| = 2 x area
    out, which, _ = _unique_rows(np.sort(cf, axis=1))
    n_out = np.cross(cv[out[:, 1]] - cv[out[:, 0]], cv[out[:, 2]] - cv[out[:, 0]])  # (G, 3)
    nonzero = np.linalg.norm(n_out, axis=1) > 1e-12 * voxel * voxel
    vote = _sum_at(which, np.einsum("fc,fc->f", n_in, n_out[which]), len(out))
    n_all = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # every input face, 2 x area
    # A face counts a third in each cell it touches (corner 0 of every face, then corner 1, then 2).
    n_cell = _sum_at(cluster[f.T.reshape(-1)], np.tile(n_all / 3.0, (3, 1)), nv)
    vote += np.einsum("gc,gc->g", n_cell[out].sum(axis=1), n_out)
    flip = vote < 0
    out[flip] = out[flip][:, [0, 2, 1]]
    out = out[nonzero]  # collapsed to a line or a point by the averaging: degenerate
    return remove_unreferenced(cv, out, cc)


def mesh_stats(vertices, faces) -> dict:
    """``{"vertices": V, "faces": F, "area_m2": total area, "bounds": [[xmin, ymin, zmin], [xmax, ymax, zmax]]}``."""
    v, f, _ = _as_mesh(vertices, faces, None)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    bounds = [v.min(0).tolist(), v.max(0).tolist()] if len(v) else [[0.0] * 3, [0.0] * 3]
    return {"vertices": int(len(v)), "faces": int(len(f)), "area_m2": float(area), "bounds": bounds}
