"""Depth maps of a triangle mesh seen by a pinhole camera (Open3D ray casting, CPU).

Used to render the fitted body's silhouette and depth for evaluation (mask IoU, depth error) and
for overlays. Rays go through pixel centres (OpenCV pinhole, pixel (0, 0) centred at (0, 0)) with
camera-frame direction ``K^-1 [u, v, 1]`` (unit z), so the hit distance is the z-depth. Only the
pixels inside the mesh's projected bounding box are cast.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.types import Intrinsics


def depth_map(vertices: NDArray, faces: NDArray, K: Intrinsics, T_world_cam: NDArray,
              near: float = 0.05) -> NDArray[np.float32]:
    """(H, W) float32 z-depth of the nearest surface, ``inf`` where no triangle is hit.

    Args:
        vertices: (V, 3) world positions, metres.
        faces: (F, 3) vertex indices.
        K: the camera (pixel size from ``K.width`` / ``K.height``).
        T_world_cam: (4, 4) camera-to-world, OpenCV axes.
        near: vertices closer than this (or behind the camera) do not count for the bounding box;
            a mesh wholly behind gives an all-``inf`` map.
    """
    import open3d as o3d

    H, W = K.height, K.width
    out = np.full((H, W), np.inf, dtype=np.float32)
    T = np.asarray(T_world_cam, dtype=np.float64)
    R, c = T[:3, :3], T[:3, 3]
    cam = (np.asarray(vertices, dtype=np.float64) - c) @ R  # (V, 3) camera frame
    front = cam[:, 2] > near
    if not front.any():
        return out
    u = K.fx * cam[front, 0] / cam[front, 2] + K.cx
    v = K.fy * cam[front, 1] / cam[front, 2] + K.cy
    if front.all():
        u0, u1 = int(np.floor(u.min())), int(np.ceil(u.max()))
        v0, v1 = int(np.floor(v.min())), int(np.ceil(v.max()))
    else:  # part of the mesh behind the camera: its projection is unbounded, cast everything
        u0, u1, v0, v1 = 0, W - 1, 0, H - 1
    u0, u1, v0, v1 = max(u0, 0), min(u1, W - 1), max(v0, 0), min(v1, H - 1)
    if u0 > u1 or v0 > v1:
        return out
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor.from_numpy(np.ascontiguousarray(cam, dtype=np.float32)),
                        o3d.core.Tensor.from_numpy(np.ascontiguousarray(faces, dtype=np.uint32)))
    uu, vv = np.meshgrid(np.arange(u0, u1 + 1, dtype=np.float32), np.arange(v0, v1 + 1, dtype=np.float32))
    rays = np.zeros((uu.size, 6), dtype=np.float32)
    rays[:, 3] = (uu.ravel() - K.cx) / K.fx
    rays[:, 4] = (vv.ravel() - K.cy) / K.fy
    rays[:, 5] = 1.0
    t_hit = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
    out[v0:v1 + 1, u0:u1 + 1] = t_hit.reshape(uu.shape)
    return out
