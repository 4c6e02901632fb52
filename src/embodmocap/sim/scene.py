"""The scene as collision geometry: a MuJoCo heightfield of the support surfaces, and/or convex
pieces of the scene mesh (:func:`convex_pieces`, coacd for the concave parts, cached by mesh hash).

MuJoCo collides a ``mesh`` geom as its convex hull, so a room mesh given as one geom would be a
solid block. A heightfield is exact for everything a body can stand, sit or lie on, and cheap.

The height map is the shared support map (:func:`embodmocap.geometry.heightmap.support_heightmap`): the
mesh's highest surface per cell without the faces that lie entirely above a cap (``cap_z``: the performer's highest point plus
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

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.heightmap import HeightMap, sample_heightmap, support_heightmap  # noqa: F401 (re-exported)


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


# ------------------------------------------------------------------------------------------------
# Convex pieces


def crop_scene(vertices: NDArray, faces: NDArray, xy_lo: NDArray, xy_hi: NDArray,
               cap_z: float) -> tuple[NDArray, NDArray]:
    """The scene mesh near the motion: faces whose xy bounds overlap the box ``[xy_lo, xy_hi]``
    and that are not entirely above ``cap_z`` (as the heightfield). A closed connected part (a studio box)
    that has any such face is kept whole, so it stays closed; an open scan is cut."""
    import trimesh

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fv = v[f]
    overlap = np.all((fv[..., :2].max(axis=1) >= xy_lo) & (fv[..., :2].min(axis=1) <= xy_hi), axis=-1)
    inside = overlap & (fv[..., 2].min(axis=1) < cap_z)
    labels = trimesh.graph.connected_component_labels(trimesh.graph.face_adjacency(f), node_count=len(f))
    keep = inside.copy()
    for lab in np.unique(labels[inside]):
        part = labels == lab
        if _closed(f[part]):
            keep |= part
    used, f_new = np.unique(f[keep], return_inverse=True)
    return v[used], f_new.reshape(-1, 3)


def _closed(f: NDArray) -> bool:
    """Every edge of the faces is shared by exactly two of them (a closed surface)."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def convex_pieces(vertices: NDArray, faces: NDArray, threshold: float = 0.05, max_pieces: int = 64,
                  resolution: int = 50, convex_tolerance: float = 0.01) -> list[tuple[NDArray, NDArray]]:
    """Convex pieces ``[(vertices (n, 3), faces (m, 3)), ...]`` covering a scene mesh.

    Each connected part that is closed and convex (volume within ``convex_tolerance`` of its hull's:
    the studio's boxes) is its own hull, exactly; every other part (a scan's open surface, an
    L-shaped sofa) goes through coacd (approximate convex decomposition; ``threshold``: its
    concavity bound, ``resolution``: its voxel resolution when it first makes an open mesh
    manifold, ``max_pieces``: its ``max_convex_hull``)."""
    import trimesh

    coacd = None
    out = []
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    for part in mesh.split(only_watertight=False):
        if len(part.faces) < 4:
            continue
        hull = part.convex_hull
        if part.is_watertight and part.volume > 0 and hull.volume - part.volume <= convex_tolerance * hull.volume:
            out.append((np.asarray(hull.vertices), np.asarray(hull.faces)))
            continue
        if coacd is None:
            from embodmocap.errors import require

            coacd = require("coacd", "sim")
            coacd.set_log_level("error")
        res = coacd.run_coacd(coacd.Mesh(np.asarray(part.vertices), np.asarray(part.faces)), threshold=threshold,
                              max_convex_hull=max_pieces, preprocess_resolution=resolution, seed=0)
        out.extend((np.asarray(pv, np.float64), np.asarray(pf, np.int64)) for pv, pf in res)
    return out


def mesh_hash(vertices: NDArray, faces: NDArray, *settings) -> str:
    """Hex digest of a mesh (float64 vertices, int64 faces) and the settings that shape its pieces."""
    import hashlib

    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(faces, np.int64).tobytes())
    h.update(repr(settings).encode())
    return h.hexdigest()[:20]


def cached_convex_pieces(vertices: NDArray, faces: NDArray, cache_dir: Path | None,
                         **kw) -> list[tuple[NDArray, NDArray]]:
    """:func:`convex_pieces`, cached in ``cache_dir/coacd_<hash>.npz`` (hash of the mesh and the
    settings: a changed mesh or setting never reuses a stale file). ``cache_dir`` None: no cache."""
    from embodmocap.io.atomic import write_npz

    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"coacd_{mesh_hash(vertices, faces, sorted(kw.items()))}.npz"
        if path.is_file():
            z = np.load(path)
            vo, fo = z["vertex_offsets"], z["face_offsets"]
            return [(z["vertices"][vo[i]:vo[i + 1]], z["faces"][fo[i]:fo[i + 1]]) for i in range(len(vo) - 1)]
    pieces = convex_pieces(vertices, faces, **kw)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        vo = np.cumsum([0] + [len(v) for v, _ in pieces])
        fo = np.cumsum([0] + [len(f) for _, f in pieces])
        write_npz(path, vertices=np.concatenate([v for v, _ in pieces]) if pieces else np.zeros((0, 3)),
                  faces=np.concatenate([f for _, f in pieces]) if pieces else np.zeros((0, 3), np.int64),
                  vertex_offsets=vo, face_offsets=fo)
    return pieces


def pieces_mjcf(pieces: list[tuple[NDArray, NDArray]], name: str = "scene_piece") -> tuple[str, str]:
    """MJCF ``<mesh>`` assets and static ``<geom>`` lines of convex pieces: (assets, geoms). MuJoCo
    collides each as its convex hull, which it is."""
    assets, geoms = [], []
    for k, (v, f) in enumerate(pieces):
        vs = " ".join(f"{x:.6g}" for x in np.asarray(v).ravel())
        fs = " ".join(str(int(i)) for i in np.asarray(f).ravel())
        assets.append(f'    <mesh name="{name}{k}" vertex="{vs}" face="{fs}"/>')
        geoms.append(f'    <geom name="{name}{k}" type="mesh" mesh="{name}{k}" contype="0" conaffinity="1" '
                     f'material="scene"/>')
    return "\n".join(assets), "\n".join(geoms)
