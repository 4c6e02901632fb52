"""A MuJoCo state drawn with the package's own ray caster (:mod:`embodmocap.geometry.raycast`):
the fallback of ``sim eval``'s video where MuJoCo's offscreen OpenGL renderer is not available.

The performer's capsules and boxes (posed from ``MjData``) and the scene's support height map (two
triangles per cell, as MuJoCo's heightfield) become one triangle mesh, cast from a camera placed
like MuJoCo's free camera (``lookat``, ``distance``, ``azimuth``, ``elevation`` in degrees), and
shaded by a headlight (Lambert, |cos| of the angle between ray and normal) over flat colours:
performer orange, scene a grey checker of the height-map cells, background sky blue.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.heightmap import HeightMap
from embodmocap.geometry.raycast import camera_ray_dirs, cast_rays, raycasting_scene
from embodmocap.geometry.transforms import look_at_R
from embodmocap.types import Intrinsics

_BODY_RGB = np.array([230, 150, 90], np.float32)
_SKY_RGB = np.array([170, 200, 230], np.uint8)


def heightmap_mesh(hm: HeightMap) -> tuple[NDArray, NDArray]:
    """Vertices (H*W, 3) at the cell centres and faces (2 (H-1)(W-1), 3) of a height map; NaN
    cells are dropped with their faces."""
    h = np.asarray(hm.heights, np.float64)
    H, W = h.shape
    ys, xs = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    v = np.column_stack([hm.origin[0] + (xs.ravel() + 0.5) * hm.cell_m, hm.origin[1] + (ys.ravel() + 0.5) * hm.cell_m,
                         h.ravel()])
    idx = np.arange(H * W).reshape(H, W)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    f = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    f = f[np.all(np.isfinite(v[f, 2]), axis=1)]
    return np.where(np.isfinite(v), v, 0.0), f


def _geom_meshes(mj, model, data) -> tuple[NDArray, NDArray]:
    """The bodies' capsule, box and sphere geoms as one posed triangle mesh (vertices, faces)."""
    import trimesh

    vs, fs, n = [], [], 0
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == 0:
            continue
        t, s = model.geom_type[g], model.geom_size[g]
        if t == mj.mjtGeom.mjGEOM_CAPSULE:
            m = trimesh.creation.capsule(height=2 * s[1], radius=s[0], count=[8, 8])
        elif t == mj.mjtGeom.mjGEOM_BOX:
            m = trimesh.creation.box(extents=2 * s[:3])
        elif t == mj.mjtGeom.mjGEOM_SPHERE:
            m = trimesh.creation.icosphere(subdivisions=1, radius=s[0])
        else:
            continue
        R = data.geom_xmat[g].reshape(3, 3)
        vs.append(np.asarray(m.vertices) @ R.T + data.geom_xpos[g])
        fs.append(np.asarray(m.faces) + n)
        n += len(m.vertices)
    return np.concatenate(vs), np.concatenate(fs)


def free_camera_pose(lookat: NDArray, distance: float, azimuth_deg: float, elevation_deg: float) -> NDArray:
    """(4, 4) ``T_world_cam`` (OpenCV axes) of MuJoCo's free camera."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    fwd = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    centre = np.asarray(lookat, np.float64) - distance * fwd
    T = np.eye(4)
    T[:3, :3] = look_at_R(centre[None], np.asarray(lookat, np.float64)[None])[0]
    T[:3, 3] = centre
    return T


def render_state(mj, model, data, hm: HeightMap, T_world_cam: NDArray, width: int = 320, height: int = 240,
                 fovy_deg: float = 45.0, scene_mesh: tuple[NDArray, NDArray] | None = None) -> NDArray[np.uint8]:
    """(height, width, 3) uint8 picture of the current state (see the module docstring); vertical
    field of view ``fovy_deg`` (MuJoCo's free camera default, 45). ``scene_mesh``:
    :func:`heightmap_mesh` of ``hm``, when the caller keeps it between frames."""
    f = 0.5 * height / np.tan(np.radians(fovy_deg) / 2)
    K = Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
    bv, bf = _geom_meshes(mj, model, data)
    sv, sf = heightmap_mesh(hm) if scene_mesh is None else scene_mesh
    scene = raycasting_scene(np.concatenate([sv, bv]), np.concatenate([sf, bf + len(sv)]))
    d = (T_world_cam[:3, :3] @ camera_ray_dirs(K)).T
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    hit = cast_rays(scene, T_world_cam[:3, 3], d)
    t, prim, nrm = hit["t_hit"], hit["primitive_ids"].astype(np.int64), hit["primitive_normals"]
    ok = np.isfinite(t)
    shade = 0.35 + 0.65 * np.abs(np.sum(nrm * d, axis=1))
    img = np.tile(_SKY_RGB, (len(t), 1)).astype(np.float32)
    body = ok & (prim >= len(sf))
    ground = ok & ~body
    cell = prim[ground] // 2 if len(sf) else prim[ground]
    W = hm.heights.shape[1]
    checker = ((cell % max(W - 1, 1)) // 4 + (cell // max(W - 1, 1)) // 4) % 2  # 0.2 m squares (4 cells)
    img[ground] = (150 + 40 * checker)[:, None] * np.ones(3, np.float32)
    img[body] = _BODY_RGB
    img[ok] *= shade[ok, None]
    return np.clip(img, 0, 255).astype(np.uint8).reshape(height, width, 3)
