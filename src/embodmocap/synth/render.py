"""A CPU ray-casting renderer for the synthetic studio: RGB, depth, person mask, laser dot.

Speed comes from never casting more rays than needed (budget ~40 ms for a 640x480 RGB frame plus
a 256x192 depth frame on 2 cores):

- the room shell (floor, four walls, ceiling; floor and fence outdoors) is an axis-aligned box seen
  from inside, intersected analytically (a slab exit test, ~2 ms for 300k rays);
- the props (furniture, pictures, fence posts) are one Open3D ``RaycastingScene`` (Embree) built
  once; each frame casts it only for the pixels inside the props' projected bounding boxes (boxes
  clipped at the near plane, so the bounds are exact);
- the moving body goes in its own small ``RaycastingScene`` built per frame (a few thousand
  triangles: cheap), cast only inside its projected bounding box;
- hits are composited by the nearest distance. A camera outside the shell falls back to casting
  one BVH of the whole static mesh (same answers, slower).

Rays go through pixel centres (OpenCV pinhole, pixel (0, 0) centred at (0, 0)) with camera-frame
direction ``K^-1 [u, v, 1]``: unit z, so every hit distance *is* the z-depth.

Shading: albedo from the solid texture (:mod:`embodmocap.synth.texture`) times Lambertian light from
one fixed direction plus ambient (per face, precomputed), a mild per-frame exposure change and
small Gaussian sensor noise (drawn from a seeded generator). The body gets a clothing colour with
a per-triangle pattern attached to its surface. No shadows, no inter-reflections.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.raycast import camera_ray_dirs, cast_rays, raycasting_scene  # noqa: F401 (camera_ray_dirs: old import path)
from embodmocap.synth.scene import BuiltScene
from embodmocap.synth.texture import LATTICE_ROTATION, albedo_lattice, relight
from embodmocap.types import Intrinsics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RenderConfig:
    """Look of the rendered images."""

    light_dir: tuple[float, float, float] = (0.35, 0.55, 1.0)
    """Direction *towards* the main light (scene frame; normalised): sun or ceiling lamps."""
    ambient: float = 0.45
    """Light reaching every surface regardless of its orientation (0..1)."""
    diffuse: float = 0.6
    """Strength of the Lambertian term ``max(0, n . l)``."""
    noise_sigma: float = 1.5 / 255
    """Standard deviation of the additive Gaussian sensor noise, in [0, 1] intensity units."""
    exposure_jitter: float = 0.015
    """Standard deviation of the per-frame multiplicative exposure change (0 = none)."""
    body_rgb: tuple[float, float, float] = (0.20, 0.28, 0.55)
    """Clothing colour of the body (when the caller gives no per-face colours)."""
    body_pattern: float = 0.35
    """Brightness swing of the body's per-triangle pattern (0 = plain)."""
    laser_radius_m: float = 0.012
    """Radius of the laser dot on the wall, metres."""
    laser_min_radius_px: float = 2.5
    """The dot's radius is enlarged with distance so that it is at least this many pixels."""
    laser_rgb: tuple[float, float, float] = (1.1, 0.06, 0.04)
    """Colour of the dot's core (red above 1 saturates at 255 even after noise)."""
    laser_glow: float = 2.2
    """The red glow fades out at this multiple of the dot's radius."""
    sky_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.80, 0.86, 0.92), (0.45, 0.62, 0.85))
    """Sky colour at the horizon and at the zenith (outdoor scenes; rays that hit nothing)."""
    seed: int = 0
    """Seed of the renderer's own generator (noise and exposure) when ``render`` is given none."""


@dataclass(frozen=True)
class RenderOut:
    """One rendered frame.

    Attributes:
        rgb: (H, W, 3) uint8 RGB.
        depth_m: (H, W) float32 z-depth in metres (OpenCV camera z), 0 where nothing is hit.
        person_mask: (H, W) bool, pixels whose nearest surface is the body.
        depth_lr_m: (h, w) float32 z-depth at the depth camera's resolution, or None.
        person_mask_lr: (h, w) bool person mask at the depth resolution, or None.
    """

    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    person_mask: NDArray[np.bool_]
    depth_lr_m: NDArray[np.float32] | None
    person_mask_lr: NDArray[np.bool_] | None


def _cast(scene, origin: NDArray, dirs: NDArray[np.float32]) -> dict:
    """Cast rays from one origin along (3, n) directions; returns Open3D's result as numpy."""
    return cast_rays(scene, origin, dirs.T)


_CHUNK = 16384  # pixels per pass of the per-pixel numpy work: temporaries stay in the CPU cache


def _chunks(n: int):
    return (slice(s, s + _CHUNK) for s in range(0, n, _CHUNK))


# Box edges as corner-index pairs (corners numbered as in scene.box_mesh: bit 0 x, bit 1 y, bit 2 z).
_EDGES = np.array([(a, a | b) for a in range(8) for b in (1, 2, 4) if not a & b])
_SHELL_PARTS = frozenset({"floor", "wall_-x", "wall_+x", "wall_-y", "wall_+y", "ceiling"})


def projected_boxes(corners_cam: NDArray, K: Intrinsics, near: float = 1e-3) -> NDArray[np.int64]:
    """Pixel bounding boxes of boxes seen by a pinhole camera, clipped at the near plane.

    Args:
        corners_cam: (B, 8, 3) box corners in the camera frame (OpenCV axes).
        K: the camera.
        near: the near plane (metres); the part of a box behind it is cut away first, so a box
            reaching behind the camera still gets a tight, correct bound.

    Returns:
        (B, 4) ``[u0, u1, v0, v1]`` half-open pixel ranges clipped to the image (empty: u0 >= u1).
    """
    a, b = corners_cam[:, _EDGES[:, 0]], corners_cam[:, _EDGES[:, 1]]  # (B, 12, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (near - a[..., 2]) / (b[..., 2] - a[..., 2])
    crossing = (s > 0) & (s < 1)
    cut = a + np.where(crossing, s, 0.0)[..., None] * (b - a)
    pts = np.concatenate([corners_cam, cut], axis=1)  # (B, 20, 3)
    ok = np.concatenate([corners_cam[..., 2] >= near, crossing], axis=1)
    z = np.where(ok, np.maximum(pts[..., 2], near), 1.0)
    u = pts[..., 0] / z * K.fx + K.cx
    v = pts[..., 1] / z * K.fy + K.cy
    big = 1e9
    out = np.stack([
        np.floor(np.where(ok, u, big).min(1)) - 1, np.ceil(np.where(ok, u, -big).max(1)) + 2,
        np.floor(np.where(ok, v, big).min(1)) - 1, np.ceil(np.where(ok, v, -big).max(1)) + 2,
    ], axis=1)
    out[:, :2] = np.clip(out[:, :2], 0, K.width)
    out[:, 2:] = np.clip(out[:, 2:], 0, K.height)
    return out.astype(np.int64)


@dataclass
class _Hits:
    """Per-pixel result of one ray grid (static scene and body composited)."""

    t: NDArray[np.float32]  # (N,) z-depth of the nearest hit, inf where none
    material: NDArray[np.int64] | None  # (N,) static material id (-1: none / body)
    shade: NDArray[np.float32] | None  # (N,) Lambertian factor of the static surface hit
    body_hit: NDArray[np.bool_]  # (N,) nearest hit is the body
    body_prim: NDArray[np.int64] | None  # (n_body,) body triangle of the body pixels (flatnonzero order)
    body_normal: NDArray[np.float32] | None  # (n_body, 3) their geometric normals
    dirs: NDArray[np.float32]  # (3, N) world-frame ray directions (unit camera z)


class Renderer:
    """Renders a :class:`BuiltScene` (+ an optional body mesh) from pinhole cameras."""

    def __init__(self, scene: BuiltScene, config: RenderConfig = RenderConfig()) -> None:
        self.scene = scene
        self.config = config
        spec = scene.spec
        self._rng = np.random.default_rng(config.seed)
        self._ray_cache: dict[Intrinsics, NDArray[np.float32]] = {}
        self._noise_cache: dict[tuple[int, int], NDArray[np.float32]] = {}
        self._pattern_cache: dict[int, NDArray[np.float32]] = {}
        self._light = (np.asarray(config.light_dir, dtype=np.float64) / np.linalg.norm(config.light_dir)).astype(np.float32)

        # Per static face: material and Lambertian shading (faces are flat).
        v = scene.vertices[scene.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        self._face_shade = self._lambert(n)
        self._face_material = scene.face_material.astype(np.int64)

        # The shell: box [lo, hi] x [0, H] seen from inside. Exit plane index = 2 * axis + (d > 0).
        self._lo = np.array([*spec.floor_min_xy, 0.0])
        self._hi = np.array([*spec.floor_max_xy, spec.wall_height])
        wall, floor = scene.material_id("wall"), scene.material_id("floor")
        top = scene.material_id("ceiling") if spec.preset == "indoor" else -1  # outdoors: open sky
        self._plane_material = np.array([wall, wall, wall, wall, floor, top], dtype=np.int64)
        inward = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
        self._plane_shade = self._lambert(inward)

        # Props: every box that is not part of the shell, in one BVH; plus a whole-scene BVH for
        # cameras outside the shell.
        box_part = np.asarray(scene.face_part)[::12]
        is_prop = np.array([scene.part_names[p] not in _SHELL_PARTS for p in box_part], dtype=bool)
        self._prop_boxes = np.flatnonzero(is_prop)
        self._prop_corners = scene.vertices.reshape(-1, 8, 3)[self._prop_boxes]  # (B, 8, 3)
        self._prop_faces = (self._prop_boxes[:, None] * 12 + np.arange(12)).reshape(-1)
        self._props = raycasting_scene(scene.vertices, scene.faces[self._prop_faces]) if is_prop.any() else None
        self._whole = raycasting_scene(scene.vertices, scene.faces)

    def _lambert(self, normals: NDArray) -> NDArray[np.float32]:
        cfg = self.config
        return (cfg.ambient + cfg.diffuse * np.clip(normals @ self._light, 0.0, None)).astype(np.float32)

    # --------------------------------------------------------------------------------------------

    def render(
        self,
        intrinsics: Intrinsics,
        T_world_cam: NDArray,
        body: tuple[NDArray, NDArray] | tuple[NDArray, NDArray, NDArray] | None = None,
        laser_on: bool = False,
        depth_intrinsics: Intrinsics | None = None,
        rng: np.random.Generator | None = None,
        lighting: tuple[float, NDArray] | None = None,
        laser_look=None,
        post=None,
    ) -> RenderOut:
        """Render one frame.

        Args:
            intrinsics: the RGB camera.
            T_world_cam: (4, 4) camera-to-scene pose, OpenCV camera axes.
            body: ``(vertices (V, 3), faces (F, 3))`` of the performer in the scene frame, optionally
                with ``face_rgb (F, 3)`` in [0, 1] as a third item; None = empty scene.
            laser_on: draw the laser dot at ``scene.spec.laser_dot`` where it is visible.
            depth_intrinsics: also cast a grid at this (depth sensor) resolution.
            rng: generator for noise and exposure; None = the renderer's own (seeded) one, so a
                fixed sequence of calls gives identical images.
            lighting: ``(gain, white_balance (3,))`` of other light on the scene
                (:func:`embodmocap.synth.texture.relight`); the laser dot, far brighter than any
                lamp, is drawn after it and still saturates.
            laser_look: a :class:`embodmocap.synth.laser.DotLook`: draw the realistic dot instead of
                the easy one (only when ``laser_on``).
            post: called with the linear (H, W, 3) float32 image after the dot, before exposure and
                noise (occluders, motion blur: :func:`embodmocap.synth.laser.frame_effects`).
        """
        rng = self._rng if rng is None else rng
        T = np.asarray(T_world_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_world_cam must be a finite (4, 4) pose, got shape {T.shape}")
        body_scene = raycasting_scene(body[0], body[1]) if body is not None else None
        hits = self._hits(intrinsics, T, body_scene, body, shading=True)
        H, W = intrinsics.height, intrinsics.width
        rgb = self._shade(hits, T, body)
        if lighting is not None:
            rgb = relight(rgb, *lighting)
        if laser_on and laser_look is not None:
            from embodmocap.synth.laser import paint_dot

            paint_dot(rgb, hits.t, hits.body_hit, hits.dirs, intrinsics, T, self.scene.spec.laser_dot, laser_look)
        elif laser_on:
            self._draw_laser(rgb, hits, intrinsics, T)
        if post is not None:
            post(rgb.reshape(H, W, 3))
        rgb = self._finish(rgb.reshape(H, W, 3), rng)
        depth = np.where(np.isfinite(hits.t), hits.t, 0.0).astype(np.float32).reshape(H, W)
        mask = hits.body_hit.reshape(H, W)
        depth_lr = mask_lr = None
        if depth_intrinsics is not None:
            lr = self._hits(depth_intrinsics, T, body_scene, body, shading=False)
            hw = (depth_intrinsics.height, depth_intrinsics.width)
            depth_lr = np.where(np.isfinite(lr.t), lr.t, 0.0).astype(np.float32).reshape(hw)
            mask_lr = lr.body_hit.reshape(hw)
        return RenderOut(rgb, depth, mask, depth_lr, mask_lr)

    # --------------------------------------------------------------------------------------------

    def _dirs(self, K: Intrinsics) -> NDArray[np.float32]:
        d = self._ray_cache.get(K)
        if d is None:
            d = self._ray_cache[K] = camera_ray_dirs(K)
        return d

    def _inside_shell(self, c: NDArray) -> bool:
        return bool(np.all(c > self._lo + 1e-3) and np.all(c < self._hi - 1e-3))

    def _hits(self, K: Intrinsics, T: NDArray, body_scene, body, shading: bool) -> _Hits:
        c = T[:3, 3]
        dirs = T[:3, :3].astype(np.float32) @ self._dirs(K)  # (3, N) world directions
        N = dirs.shape[1]
        if self._inside_shell(c):
            t, mat, shade = self._shell(c, dirs, shading)
            if self._props is not None:
                sel = self._prop_pixels(K, T)
                if sel.size:
                    self._merge(t, mat, shade, sel, _cast(self._props, c, dirs[:, sel]), self._prop_faces, shading)
        else:
            t = np.full(N, np.inf, dtype=np.float32)
            mat = np.full(N, -1, dtype=np.int64) if shading else None
            shade = np.zeros(N, dtype=np.float32) if shading else None
            self._merge(t, mat, shade, np.arange(N), _cast(self._whole, c, dirs), None, shading)

        body_hit = np.zeros(N, dtype=bool)
        body_prim = body_normal = None
        if body_scene is not None:
            sel = self._body_pixels(K, T, body[0])
            if sel.size:
                bh = _cast(body_scene, c, dirs[:, sel])
                nearer = bh["t_hit"] < t[sel]
                idx = sel[nearer]  # increasing, like np.flatnonzero(body_hit)
                body_hit[idx] = True
                t[idx] = bh["t_hit"][nearer]
                if shading:
                    body_prim = bh["primitive_ids"][nearer].astype(np.int64)
                    body_normal = bh["primitive_normals"][nearer]
        return _Hits(t, mat, shade, body_hit, body_prim, body_normal, dirs)

    def _shell(self, c: NDArray, dirs: NDArray[np.float32], shading: bool):
        """Exit distance (N,) of rays from inside the shell box, with material and shade per ray."""
        N = dirs.shape[1]
        t = np.empty(N, dtype=np.float32)
        plane = np.empty(N, dtype=np.int64)
        lo = (self._lo - c).astype(np.float32)
        hi = (self._hi - c).astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            for s in _chunks(N):  # cache-sized passes
                tc = pc = None
                for axis in range(3):
                    d = dirs[axis, s]
                    pos = d > 0
                    # From inside the box every exit distance is positive; abs() turns the -inf of
                    # d == 0 into +inf (never the exit).
                    ta = np.abs(np.where(pos, hi[axis], lo[axis]) / d)
                    if tc is None:
                        tc, pc = ta, pos.astype(np.int64)
                    else:
                        closer = ta < tc
                        tc = np.where(closer, ta, tc)
                        pc = np.where(closer, 2 * axis + pos, pc)
                t[s], plane[s] = tc, pc
        mat = shade = None
        if self._plane_material[5] < 0:  # open top: rays leaving upwards see the sky
            t[plane == 5] = np.inf
        if shading:
            mat = self._plane_material[plane]
            shade = self._plane_shade[plane]
        return t, mat, shade

    def _merge(self, t, mat, shade, sel, hit: dict, face_map, shading: bool) -> None:
        """Write a BVH cast over pixels ``sel`` into the per-pixel arrays where it is nearer."""
        nearer = hit["t_hit"] < t[sel]
        idx = sel[nearer]
        t[idx] = hit["t_hit"][nearer]
        if shading:
            prim = hit["primitive_ids"][nearer].astype(np.int64)
            face = face_map[prim] if face_map is not None else prim
            mat[idx] = self._face_material[face]
            shade[idx] = self._face_shade[face]

    def _prop_pixels(self, K: Intrinsics, T: NDArray) -> NDArray[np.int64]:
        """Flat indices of the pixels inside any prop box's projected bounds (increasing)."""
        corners = (self._prop_corners - T[:3, 3]) @ T[:3, :3]  # (B, 8, 3) camera frame
        boxes = projected_boxes(corners, K)
        mask = np.zeros((K.height, K.width), dtype=bool)
        for u0, u1, v0, v1 in boxes[(boxes[:, 0] < boxes[:, 1]) & (boxes[:, 2] < boxes[:, 3])]:
            mask[v0:v1, u0:u1] = True
        return np.flatnonzero(mask)

    @staticmethod
    def _body_pixels(K: Intrinsics, T: NDArray, verts: NDArray) -> NDArray[np.int64]:
        """Flat indices of the pixels inside the body's projected bounding box (increasing)."""
        pc = (np.asarray(verts, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]
        lo, hi = pc.min(0), pc.max(0)
        if lo[2] > 1e-3:  # all in front: the vertices' own projections give the tightest bounds
            u = pc[:, 0] / pc[:, 2] * K.fx + K.cx
            v = pc[:, 1] / pc[:, 2] * K.fy + K.cy
            u0, u1 = np.clip([np.floor(u.min()) - 1, np.ceil(u.max()) + 2], 0, K.width).astype(int)
            v0, v1 = np.clip([np.floor(v.min()) - 1, np.ceil(v.max()) + 2], 0, K.height).astype(int)
        else:  # partly behind the camera: bound its camera-frame box, clipped at the near plane
            corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(1, 8, 3)
            corners = corners[:, [0, 4, 2, 6, 1, 5, 3, 7]]  # bit 0 x, bit 1 y, bit 2 z
            u0, u1, v0, v1 = projected_boxes(corners, K)[0]
        if u0 >= u1 or v0 >= v1:
            return np.zeros(0, dtype=np.int64)
        return (np.arange(v0, v1)[:, None] * K.width + np.arange(u0, u1)[None, :]).reshape(-1)

    # --------------------------------------------------------------------------------------------

    def _shade(self, hits: _Hits, T: NDArray, body) -> NDArray[np.float32]:
        """(N, 3) float32 linear colour of every pixel."""
        cfg = self.config
        c = T[:3, 3]
        # Hit points in the texture's lattice frame, straight from the rays: q = R^T c + t R^T d,
        # in cache-sized passes.
        Rl = LATTICE_ROTATION.T
        cl = (Rl @ c.astype(np.float32))[:, None]
        N = len(hits.t)
        rgb = np.empty((N, 3), dtype=np.float32)
        mats = self.scene.materials
        for s in _chunks(N):
            t = hits.t[s]
            t = np.where(np.isfinite(t), t, np.float32(0.0))
            q = (Rl @ hits.dirs[:, s]) * t
            q += cl
            col = albedo_lattice(q, np.maximum(hits.material[s], 0), mats)
            col *= hits.shade[s, None]
            rgb[s] = col
        sky = np.flatnonzero(~np.isfinite(hits.t))
        if sky.size:
            d = hits.dirs[:, sky]
            up = np.clip(d[2] / np.linalg.norm(d, axis=0), 0.0, 1.0)[:, None]
            lo, hi = np.asarray(cfg.sky_rgb, dtype=np.float32)
            rgb[sky] = lo + (hi - lo) * np.sqrt(up)
        if hits.body_prim is not None and hits.body_prim.size:
            rgb[np.flatnonzero(hits.body_hit)] = self._body_colour(hits, body)
        return rgb

    def _body_colour(self, hits: _Hits, body) -> NDArray[np.float32]:
        cfg = self.config
        prim = hits.body_prim
        n_faces = len(body[1])
        if len(body) > 2 and body[2] is not None:
            base = np.asarray(body[2], dtype=np.float32)[prim]
        else:
            base = np.broadcast_to(np.asarray(cfg.body_rgb, dtype=np.float32), (len(prim), 3))
        pattern = self._pattern_cache.get(n_faces)
        if pattern is None:
            # A fixed per-triangle brightness pattern: attached to the surface, so it moves with it.
            g = np.random.default_rng(n_faces)
            pattern = (1.0 + cfg.body_pattern * (g.random(n_faces) - 0.5)).astype(np.float32)
            self._pattern_cache[n_faces] = pattern
        n = hits.body_normal
        d = hits.dirs[:, np.flatnonzero(hits.body_hit)].T
        # Face the normal towards the camera (the mesh may be wound either way).
        facing = np.where(np.sum(n * d, axis=1) > 0, -1.0, 1.0).astype(np.float32)
        lam = np.clip((n @ self._light) * facing, 0.0, None)
        shade = (cfg.ambient + cfg.diffuse * lam) * pattern[prim]
        return base * shade[:, None]

    def _draw_laser(self, rgb: NDArray[np.float32], hits: _Hits, K: Intrinsics, T: NDArray) -> None:
        """Paint the laser dot in place where the wall around ``spec.laser_dot`` is visible."""
        cfg = self.config
        dot = np.asarray(self.scene.spec.laser_dot, dtype=np.float64)
        pc = (dot - T[:3, 3]) @ T[:3, :3]
        if pc[2] <= 0.05:
            return
        r_m = max(cfg.laser_radius_m, cfg.laser_min_radius_px * pc[2] / K.fx)
        r_glow = cfg.laser_glow * r_m
        u = pc[0] / pc[2] * K.fx + K.cx
        v = pc[1] / pc[2] * K.fy + K.cy
        # Pixels whose rays could land within the glow (generous: the wall may be seen obliquely).
        win = 4 * r_glow * K.fx / pc[2] + 3
        u0, u1 = int(max(0, np.floor(u - win))), int(min(K.width, np.ceil(u + win) + 1))
        v0, v1 = int(max(0, np.floor(v - win))), int(min(K.height, np.ceil(v + win) + 1))
        if u0 >= u1 or v0 >= v1:
            return
        idx = (np.arange(v0, v1)[:, None] * K.width + np.arange(u0, u1)[None, :]).reshape(-1)
        idx = idx[np.isfinite(hits.t[idx]) & ~hits.body_hit[idx]]
        p = T[:3, 3] + hits.t[idx, None].astype(np.float64) * hits.dirs[:, idx].T
        dist = np.linalg.norm(p - dot, axis=1)
        core = dist <= r_m
        glow = (dist > r_m) & (dist < r_glow)
        red = np.asarray(cfg.laser_rgb, dtype=np.float32)
        rgb[idx[core]] = red
        a = (0.7 * (1.0 - (dist[glow] - r_m) / (r_glow - r_m))).astype(np.float32)[:, None]
        rgb[idx[glow]] = rgb[idx[glow]] * (1 - a) + np.minimum(red, 1.0) * a

    def _finish(self, rgb: NDArray[np.float32], rng: np.random.Generator) -> NDArray[np.uint8]:
        """Exposure, sensor noise, quantisation: (H, W, 3) float -> uint8."""
        cfg = self.config
        H, W = rgb.shape[:2]
        out = rgb * np.float32(255.0 * (1.0 + cfg.exposure_jitter * rng.standard_normal()))
        if cfg.noise_sigma > 0:
            # A bank of Gaussian noise drawn once per size; each frame takes a randomly shifted
            # window with a random sign: statistically like fresh noise at a fraction of the cost.
            bank = self._noise_cache.get((H, W))
            if bank is None:
                g = np.random.default_rng(cfg.seed + 1)
                bank = (g.standard_normal((H + 32, W + 32, 3)) * cfg.noise_sigma * 255).astype(np.float32)
                self._noise_cache[(H, W)] = bank
            dy, dx = rng.integers(0, 33, 2)
            if rng.random() < 0.5:
                out += bank[dy:dy + H, dx:dx + W]
            else:
                out -= bank[dy:dy + H, dx:dx + W]
        np.clip(out, 0.0, 255.0, out=out)
        out += 0.5
        return out.astype(np.uint8)
