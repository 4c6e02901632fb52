"""Rays through pixels and ray casting of triangle meshes (Open3D, CPU): the one place for both.

- :func:`camera_ray_dirs`: camera-frame directions through every pixel centre;
- :func:`pixel_rays`: world-space rays (centre, unit direction) of given pixels;
- :func:`raycasting_scene` / :func:`cast_rays`: an Open3D BVH of a mesh and hits of rays on it
  (the studio's renderer, the overlay renderer and :func:`depth_map` all use these);
- :func:`depth_map`: depth of a mesh seen by a pinhole camera.

:func:`depth_map` is used to render the fitted body's silhouette and depth for evaluation (mask IoU, depth error) and
for overlays. Rays go through pixel centres (OpenCV pinhole, pixel (0, 0) centred at (0, 0)) with
camera-frame direction ``K^-1 [u, v, 1]`` (unit z), so the hit distance is the z-depth. Only the
pixels inside the mesh's projected bounding box are cast.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.types import Intrinsics


def camera_ray_dirs(K: Intrinsics) -> NDArray[np.float32]:
    """(3, H*W) float32 camera-frame directions ``K^-1 [u, v, 1]`` through pixel centres, row-major
    (unit z, so a hit distance along them is the z-depth)."""
    u = (np.arange(K.width, dtype=np.float64) - K.cx) / K.fx
    v = (np.arange(K.height, dtype=np.float64) - K.cy) / K.fy
    d = np.empty((3, K.height, K.width), dtype=np.float32)
    d[0] = u[None, :]
    d[1] = v[:, None]
    d[2] = 1.0
    return d.reshape(3, -1)


def pixel_rays(K: NDArray, T_world_cam: NDArray, xy: NDArray) -> tuple[NDArray, NDArray]:
    """World rays of pixels: camera centres (..., 3) and unit directions (..., 3).

    Args:
        K: (..., 3, 3) intrinsic matrices.
        T_world_cam: (..., 4, 4) camera-to-world, OpenCV axes.
        xy: (..., 2) pixel coordinates (pixel centres at integers).
    """
    Kinv = np.linalg.inv(K)
    h = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    d_cam = np.einsum("...ij,...j->...i", Kinv, h)
    d = np.einsum("...ij,...j->...i", T_world_cam[..., :3, :3], d_cam)
    return np.broadcast_to(T_world_cam[..., :3, 3], d.shape), d / np.linalg.norm(d, axis=-1, keepdims=True)


def raycasting_scene(vertices: NDArray, faces: NDArray):
    """An Open3D ``RaycastingScene`` (Embree BVH) of one triangle mesh: vertices (V, 3), faces (F, 3)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor.from_numpy(np.ascontiguousarray(faces, dtype=np.uint32)))
    return scene


def cast_rays(scene, origins: NDArray, dirs: NDArray) -> dict[str, NDArray]:
    """Hits of rays from ``origins`` ((3,) or (n, 3)) along ``dirs`` (n, 3) on a
    :func:`raycasting_scene`: Open3D's result (``t_hit``, ``primitive_ids``, ``primitive_normals``,
    ...) as numpy arrays; ``t_hit`` is in units of the direction's length, ``inf`` for a miss."""
    import open3d as o3d

    rays = np.empty((len(dirs), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    return {k: v.numpy() for k, v in scene.cast_rays(o3d.core.Tensor.from_numpy(rays)).items()}


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
    uu, vv = np.meshgrid(np.arange(u0, u1 + 1, dtype=np.float32), np.arange(v0, v1 + 1, dtype=np.float32))
    dirs = np.stack([(uu.ravel() - K.cx) / K.fx, (vv.ravel() - K.cy) / K.fy, np.ones(uu.size, np.float32)], axis=1)
    t_hit = cast_rays(raycasting_scene(cam, faces), np.zeros(3), dirs)["t_hit"]
    out[v0:v1 + 1, u0:u1 + 1] = t_hit.reshape(uu.shape)
    return out
