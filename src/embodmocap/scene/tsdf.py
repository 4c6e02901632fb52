"""TSDF fusion of posed depth maps into a coloured triangle mesh.

Two implementations of the same projective TSDF (Curless & Levoy style, weight 1 per observation,
running average, signed distance measured along the camera ray and truncated at ``sdf_trunc``):

- :func:`fuse_open3d`: Open3D's ``ScalableTSDFVolume`` (hashed voxel blocks, C++): the product's
  path. Needs open3d 0.19 (0.20 extracts empty meshes).
- :class:`NumpyTSDF`: a plain, vectorised NumPy version on a dense grid over given bounds, kept
  readable as the reference the tests and ``benchmarks/bench_tsdf.py`` compare against. Its
  surface comes out by marching tetrahedra (no lookup tables beyond a 16-entry one built here).

Conventions: world Z up, metres; cameras OpenCV (x right, y down, z forward); ``T_world_cam``
is camera-to-world, so Open3D's ``extrinsic`` (world-to-camera) is its inverse. Open3D's pinhole
model puts pixel (u, v) at ``u = fx x/z + cx`` like OpenCV, so intrinsics pass through unchanged.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Iterable

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.transforms import invert_T
from embodmocap.types import Intrinsics

log = logging.getLogger(__name__)

#: One fusion input: (rgb (h, w, 3) uint8, depth_m (h, w) float32 0 = invalid, intrinsics (h, w),
#: T_world_cam (4, 4)).
FusionFrame = tuple[NDArray[np.uint8], NDArray[np.float32], Intrinsics, NDArray]

#: A triangle mesh: vertices (V, 3) float64 metres, faces (F, 3) int64, colours (V, 3) float64 in
#: [0, 1] (may be (0, 3) when the mesh carries none).
MeshArrays = tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]


def fuse_open3d(frames: Iterable[FusionFrame], voxel_m: float, sdf_trunc_m: float, depth_trunc_m: float,
                threads: int = 1) -> MeshArrays:
    """Fuse posed RGB-D frames with Open3D's ``ScalableTSDFVolume`` and extract a coloured mesh.

    Args:
        frames: iterable of (rgb, depth_m, intrinsics, T_world_cam); rgb and depth share the size
            of ``intrinsics``. Consumed once, so a generator reading from disk keeps memory flat.
        voxel_m: voxel edge length, metres.
        sdf_trunc_m: truncation distance of the signed distance, metres.
        depth_trunc_m: depth beyond this is ignored, metres.
        threads: OpenMP threads of Open3D's integration (0 = Open3D's default, one per core). The
            mesh is the same for any number (each voxel is updated by one thread); 1 keeps a loaded
            machine from spinning (:mod:`embodmocap.parallel`) while ``frames`` is read on another.

    Returns:
        ``(vertices (V, 3), faces (F, 3), colours (V, 3) in [0, 1])`` in the poses' world frame;
        empty arrays if nothing was observed.
    """
    from embodmocap.io.open3d_core import open3d as o3d
    from embodmocap.parallel import library_threads

    with library_threads(threads, ("openmp",)) if threads > 0 else contextlib.nullcontext():
        return _fuse_open3d(o3d, frames, voxel_m, sdf_trunc_m, depth_trunc_m)


def _fuse_open3d(o3d, frames: Iterable[FusionFrame], voxel_m: float, sdf_trunc_m: float,
                 depth_trunc_m: float) -> MeshArrays:

    volume = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=float(voxel_m), sdf_trunc=float(sdf_trunc_m),
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8,
    )
    n = 0
    for rgb, depth, K, T_world_cam in frames:
        if rgb.shape[:2] != depth.shape or depth.shape != (K.height, K.width):
            raise ValueError(f"rgb {rgb.shape[:2]}, depth {depth.shape} and intrinsics {K.width}x{K.height} disagree")
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(rgb, dtype=np.uint8)),
            o3d.geometry.Image(np.ascontiguousarray(depth, dtype=np.float32)),
            depth_scale=1.0, depth_trunc=float(depth_trunc_m), convert_rgb_to_intensity=False,
        )
        cam = o3d.camera.PinholeCameraIntrinsic(K.width, K.height, K.fx, K.fy, K.cx, K.cy)
        volume.integrate(rgbd, cam, invert_T(np.asarray(T_world_cam, dtype=np.float64)))
        n += 1
    mesh = volume.extract_triangle_mesh()
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.triangles, dtype=np.int64)
    c = np.asarray(mesh.vertex_colors, dtype=np.float64)
    log.debug("open3d TSDF: %d frames -> %d vertices, %d faces", n, len(v), len(f))
    return v, f, c if len(c) == len(v) else np.zeros((0, 3))


# ------------------------------------------------------------------------------------------------
# NumPy reference


# Cube corners: bit 0 -> x, bit 1 -> y, bit 2 -> z.
_CUBE = np.array([[(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], dtype=np.int64)
# Six tetrahedra around the cube's main diagonal 0-7; they tile the cube and neighbouring cubes
# cut shared faces the same way, so the surface has no cracks.
_TETS = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])


def _tet_table() -> list[list[tuple[tuple[int, int], ...]]]:
    """For each of the 16 inside/outside patterns of a tetrahedron (bit i = corner i inside),
    the triangles of its surface piece as triples of tet edges (a, b) crossed by the surface."""
    table = []
    for mask in range(16):
        inside = [i for i in range(4) if mask >> i & 1]
        outside = [i for i in range(4) if not mask >> i & 1]
        if len(inside) in (0, 4):
            table.append([])
        elif len(inside) in (1, 3):
            lone, rest = (inside[0], outside) if len(inside) == 1 else (outside[0], inside)
            table.append([tuple((lone, r) for r in rest)])
        else:  # two in, two out: a quad cut into two triangles
            (a, b), (c, d) = inside, outside
            table.append([((a, c), (a, d), (b, d)), ((a, c), (b, d), (b, c))])
    return table


_TET_TABLE = _tet_table()


class NumpyTSDF:
    """A dense-grid projective TSDF in plain NumPy (the reference for :func:`fuse_open3d`).

    Voxel ``(i, j, k)`` has its centre at ``lo + (i + 0.5, j + 0.5, k + 0.5) * voxel_m``. Stored
    values: ``tsdf`` (X, Y, Z) float32 in [-1, 1] (signed distance / truncation, positive in front
    of the surface), ``weight`` (X, Y, Z) float32 (number of observations), ``colour`` (X, Y, Z, 3)
    float32 in [0, 1] (running average).

    Args:
        lo, hi: (3,) corners of the box to reconstruct, metres (world frame).
        voxel_m: voxel edge, metres.
        sdf_trunc_m: truncation distance, metres.
        depth_trunc_m: depth beyond this is ignored, metres.
    """

    def __init__(self, lo, hi, voxel_m: float, sdf_trunc_m: float, depth_trunc_m: float = np.inf) -> None:
        self.lo = np.asarray(lo, dtype=np.float64)
        self.voxel_m = float(voxel_m)
        self.sdf_trunc_m = float(sdf_trunc_m)
        self.depth_trunc_m = float(depth_trunc_m)
        self.shape = tuple(int(s) for s in np.maximum(np.ceil((np.asarray(hi, dtype=np.float64) - self.lo) / voxel_m), 1))
        self.tsdf = np.ones(self.shape, dtype=np.float32)
        self.weight = np.zeros(self.shape, dtype=np.float32)
        self.colour = np.zeros(self.shape + (3,), dtype=np.float32)
        # Voxel centres along each axis; full (N, 3) grids are built one x-slab at a time.
        self._axes = [self.lo[a] + (np.arange(self.shape[a]) + 0.5) * voxel_m for a in range(3)]

    def integrate(self, depth_m: NDArray, K: Intrinsics, T_world_cam: NDArray, rgb: NDArray | None = None) -> None:
        """Fuse one depth map (h, w) float32 metres (0 = invalid) seen from ``T_world_cam`` (4, 4).

        Each voxel centre is projected to its nearest pixel; where that pixel has depth ``d`` and
        the voxel's camera depth is ``z``, the signed distance along the ray is ``(d - z) *
        |K^-1 [u, v, 1]|``. Voxels more than ``sdf_trunc`` behind the surface are left alone
        (occluded); the rest get ``min(1, sdf / trunc)`` averaged in with weight 1.
        """
        depth = np.asarray(depth_m, dtype=np.float32)
        T_cam_world = invert_T(np.asarray(T_world_cam, dtype=np.float64))
        R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
        h, w = depth.shape
        ys, zs = np.meshgrid(self._axes[1], self._axes[2], indexing="ij")  # (Y, Z)
        yz = np.stack([ys.ravel(), zs.ravel()], axis=1)
        # Camera coordinates of a slab: p_cam = R[:, 0] x + (R[:, 1:] @ yz) + t; the yz part is
        # shared by every slab.
        base = yz @ R[:, 1:].T + t  # (Y*Z, 3)
        for i, x in enumerate(self._axes[0]):  # one x-slab at a time keeps temporaries small
            p = base + x * R[:, 0]
            z = p[:, 2]
            in_front = z > 1e-6
            zs_safe = np.where(in_front, z, 1.0)
            u = np.rint(p[:, 0] / zs_safe * K.fx + K.cx).astype(np.int64)
            v = np.rint(p[:, 1] / zs_safe * K.fy + K.cy).astype(np.int64)
            ok = in_front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            idx = np.flatnonzero(ok)
            if idx.size == 0:
                continue
            d = depth[v[idx], u[idx]]
            good = (d > 0) & (d <= self.depth_trunc_m)
            idx, d = idx[good], d[good]
            ray = np.sqrt(1.0 + ((u[idx] - K.cx) / K.fx) ** 2 + ((v[idx] - K.cy) / K.fy) ** 2)
            sdf = (d - z[idx]) * ray
            seen = sdf >= -self.sdf_trunc_m
            idx, sdf = idx[seen], sdf[seen]
            if idx.size == 0:
                continue
            val = np.minimum(1.0, sdf / self.sdf_trunc_m).astype(np.float32)
            tsdf, wgt = self.tsdf[i].reshape(-1), self.weight[i].reshape(-1)
            wi = wgt[idx]
            tsdf[idx] = (tsdf[idx] * wi + val) / (wi + 1.0)
            if rgb is not None:
                col = self.colour[i].reshape(-1, 3)
                c = np.asarray(rgb[v[idx], u[idx]], dtype=np.float32) / 255.0
                col[idx] = (col[idx] * wi[:, None] + c) / (wi[:, None] + 1.0)
            wgt[idx] = wi + 1.0

    def surface_points(self) -> NDArray[np.float64]:
        """(N, 3) zero crossings of the TSDF between observed neighbouring voxels (linear
        interpolation along x, y and z): a point sampling of the surface, no mesh needed."""
        pts = []
        for a in range(3):
            s0 = [slice(None)] * 3
            s1 = [slice(None)] * 3
            s0[a], s1[a] = slice(0, -1), slice(1, None)
            t0, t1 = self.tsdf[tuple(s0)], self.tsdf[tuple(s1)]
            ok = (self.weight[tuple(s0)] > 0) & (self.weight[tuple(s1)] > 0) & ((t0 > 0) != (t1 > 0))
            ok &= (np.abs(t0) < 1) & (np.abs(t1) < 1)  # both inside the band: a real surface
            ijk = np.argwhere(ok)
            frac = t0[ok] / (t0[ok] - t1[ok])
            p = self.lo + (ijk + 0.5) * self.voxel_m
            p[:, a] += frac * self.voxel_m
            pts.append(p)
        return np.concatenate(pts, axis=0)

    def extract_mesh(self) -> MeshArrays:
        """Marching tetrahedra over the cubes whose 8 corners are observed and inside the band.

        Returns ``(vertices (V, 3), faces (F, 3), colours (V, 3))``; vertices on a shared grid
        edge are merged. Faces are not consistently oriented (metrics do not need it).
        """
        X, Y, Z = self.shape
        if min(X, Y, Z) < 2:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
        flat_t = self.tsdf.reshape(-1)
        flat_c = self.colour.reshape(-1, 3)
        obs = (self.weight > 0) & (np.abs(self.tsdf) < 1)
        neg = self.tsdf < 0
        # A cube (i, j, k) spans grid points (i..i+1, j..j+1, k..k+1). Find the cubes with all 8
        # corners observed and a sign change using shifted boolean views (cheap), then gather
        # corner values only for those.
        all_obs = np.ones((X - 1, Y - 1, Z - 1), dtype=bool)
        any_neg = np.zeros_like(all_obs)
        all_neg = np.ones_like(all_obs)
        for dx, dy, dz in _CUBE:
            sl = (slice(dx, X - 1 + dx), slice(dy, Y - 1 + dy), slice(dz, Z - 1 + dz))
            all_obs &= obs[sl]
            any_neg |= neg[sl]
            all_neg &= neg[sl]
        origin = np.ravel_multi_index(np.nonzero(all_obs & any_neg & ~all_neg), self.shape)
        corners = origin[:, None] + np.ravel_multi_index(_CUBE.T, self.shape)[None, :]  # (C, 8) flat ids
        inside = flat_t[corners] < 0

        tri_edges = []  # (n, 3, 2) grid-point id pairs
        for tet in _TETS:
            tc = corners[:, tet]  # (C, 4)
            mask = (inside[:, tet] * (1 << np.arange(4))).sum(axis=1)
            for m in range(1, 15):
                sel = mask == m
                if not sel.any():
                    continue
                for tri in _TET_TABLE[m]:
                    e = np.array(tri)  # (3, 2) tet-corner pairs
                    tri_edges.append(tc[sel][:, e])  # (n, 3, 2)
        if not tri_edges:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
        edges = np.concatenate(tri_edges, axis=0).reshape(-1, 2)
        edges.sort(axis=1)
        n_pts = X * Y * Z
        uniq, inverse = np.unique(edges[:, 0] * n_pts + edges[:, 1], return_inverse=True)
        a, b = uniq // n_pts, uniq % n_pts
        ta, tb = flat_t[a], flat_t[b]
        frac = (ta / (ta - tb))[:, None]
        pa = self.lo + (np.stack(np.unravel_index(a, self.shape), 1) + 0.5) * self.voxel_m
        pb = self.lo + (np.stack(np.unravel_index(b, self.shape), 1) + 0.5) * self.voxel_m
        verts = pa + frac * (pb - pa)
        cols = flat_c[a] + frac * (flat_c[b] - flat_c[a])
        faces = inverse.reshape(-1, 3).astype(np.int64)
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
        return verts, faces, cols.astype(np.float64)

    def integrate_frames(self, frames: Iterable[FusionFrame]) -> int:
        """Integrate every (rgb, depth, K, T_world_cam) of ``frames``; returns how many."""
        n = 0
        for rgb, depth, K, T in frames:
            self.integrate(depth, K, T, rgb)
            n += 1
        return n
