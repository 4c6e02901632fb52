"""The laser sync event: where the dot shines and how the operators film it.

In a real session someone shines a laser pointer on a wall that both phones see, then switches it
off; the frame where the dot disappears syncs the two videos. The studio reproduces that: it picks
a wall point both operators can see without much turning and that nothing hides, and turns each
camera toward it from the start of the recording until shortly after the event, blending back to
following the performer afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.transforms import look_at_R
from embodmocap.synth.scene import BuiltScene


@dataclass(frozen=True)
class SyncEventConfig:
    """How the operators film the laser dot."""

    dot_height_m: tuple[float, float] = (1.0, 1.8)
    """Range of heights of candidate dot positions on the walls, metres."""
    spacing_m: float = 0.25
    """Spacing of candidate dot positions along each wall, metres."""
    max_distance_m: float = 6.5
    """Largest camera-to-dot distance considered, metres (a phone still resolves the dot)."""
    max_incidence_deg: float = 65.0
    """Largest angle between the view ray and the wall normal (grazing dots are hard to see)."""
    hold_s: float = 0.5
    """Time the cameras keep aiming at the wall after the dot goes off, seconds."""
    blend_s: float = 1.0
    """Time over which the cameras turn back to the performer, seconds."""


def _wall_candidates(scene: BuiltScene, cfg: SyncEventConfig) -> tuple[NDArray, NDArray]:
    """Points (N, 3) on the four inner walls (or fence) and their inward normals (N, 3)."""
    lo, hi = np.asarray(scene.spec.floor_min_xy, float), np.asarray(scene.spec.floor_max_xy, float)
    zs = np.arange(cfg.dot_height_m[0], cfg.dot_height_m[1] + 1e-9, cfg.spacing_m)
    pts, nrm = [], []
    for axis in (0, 1):
        other = 1 - axis
        along = np.arange(lo[other] + 0.4, hi[other] - 0.4 + 1e-9, cfg.spacing_m)
        for side, normal_sign in ((lo[axis], 1.0), (hi[axis], -1.0)):
            a, z = np.meshgrid(along, zs, indexing="ij")
            p = np.zeros(a.shape + (3,))
            p[..., axis] = side
            p[..., other] = a
            p[..., 2] = z
            n = np.zeros(3)
            n[axis] = normal_sign
            pts.append(p.reshape(-1, 3))
            nrm.append(np.broadcast_to(n, (p.size // 3, 3)))
    return np.concatenate(pts), np.concatenate(nrm)


def choose_dot(
    scene: BuiltScene,
    T_scene_cam: list[NDArray],
    body: tuple[NDArray, NDArray],
    cfg: SyncEventConfig = SyncEventConfig(),
) -> tuple[NDArray, NDArray]:
    """Pick the laser dot: the wall point every camera sees unoccluded with the least turning.

    Args:
        scene: the built scene.
        T_scene_cam: per view, the (4, 4) camera pose at the sync event.
        body: the performer's (vertices (V,3), faces (F,3)) at the event (it may hide the wall).

    Returns:
        ``(point (3,), inward normal (3,))``.
    """
    import open3d as o3d

    pts, nrm = _wall_candidates(scene, cfg)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(scene.vertices.astype(np.float32)), o3d.core.Tensor(scene.faces.astype(np.uint32)))
    rc.add_triangles(o3d.core.Tensor(body[0].astype(np.float32)), o3d.core.Tensor(np.asarray(body[1]).astype(np.uint32)))
    # A candidate sits on the wall plane; pictures and shelves may stand in front of it. Pull it
    # 2 mm off the wall so the occlusion test below sees only what really stands between.
    cost = np.zeros(len(pts))
    ok = np.ones(len(pts), bool)
    for T in T_scene_cam:
        c = T[:3, 3]
        d = pts - c
        dist = np.linalg.norm(d, axis=1)
        u = d / dist[:, None]
        cos_inc = -(u * nrm).sum(1)
        ok &= (dist < cfg.max_distance_m) & (cos_inc > np.cos(np.deg2rad(cfg.max_incidence_deg)))
        rays = np.concatenate([np.broadcast_to(c, pts.shape), u], axis=1).astype(np.float32)
        t_hit = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        ok &= t_hit > dist - 0.01  # nothing nearer than the wall itself along the ray
        forward = T[:3, 2]
        cost = np.maximum(cost, np.arccos(np.clip(u @ forward, -1, 1)))
    if not ok.any():
        raise RuntimeError("no wall point is visible from both operators at the sync event")
    best = int(np.argmin(np.where(ok, cost, np.inf)))
    return pts[best], nrm[best]


def with_dot(scene: BuiltScene, dot: NDArray, normal: NDArray) -> BuiltScene:
    """The same scene with the laser dot moved to ``dot``."""
    return replace(scene, spec=replace(scene.spec, laser_dot=np.asarray(dot, float), laser_normal=np.asarray(normal, float)))


def aim_at_dot(T_scene_cam: NDArray, dot: NDArray, event_frame: int, fps: float, cfg: SyncEventConfig = SyncEventConfig()) -> NDArray:
    """Turn cameras (T, 4, 4) toward ``dot`` up to shortly after ``event_frame``, then blend back.

    The hand shake of the original trajectory is kept: only the aim changes. Positions are untouched.
    """
    T = np.array(T_scene_cam, dtype=np.float64, copy=True)
    n = len(T)
    f = np.arange(n)
    hold_end = event_frame + cfg.hold_s * fps
    s = np.clip((f - hold_end) / max(cfg.blend_s * fps, 1.0), 0.0, 1.0)
    w = 1.0 - (3 * s**2 - 2 * s**3)  # 1 while aiming at the dot, smoothstep down to 0
    sel = w > 0
    if not sel.any():
        return T
    c = T[sel, :3, 3]
    R = T[sel, :3, :3]
    fwd = R[:, :, 2]
    R_aim = look_at_R(c, c + fwd)
    R_shake = np.swapaxes(R_aim, 1, 2) @ R  # what the hand adds on top of the aim
    to_dot = dot[None] - c
    to_dot /= np.linalg.norm(to_dot, axis=1, keepdims=True)
    d = w[sel, None] * to_dot + (1 - w[sel, None]) * fwd
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    T[sel, :3, :3] = look_at_R(c, c + d) @ R_shake
    return T
