"""The realistic laser dot: what a phone records of a real pointer on a real wall.

A pointer at 2-6 m makes a spot of 1-2 cm. The phone's auto-exposure is set for the room, so the
spot is far brighter than the wall: its centre saturates every channel (white core, a few pixels),
and lens and sensor bloom spread red light a few pixels further (red halo). This module draws, per
seed, every part of that look from the ranges of :class:`~embodmocap.synth.config.LaserConfig`:

- the wall's colour and texture (:func:`wall_material`: reddish, magenta, beige, grey, strongly
  textured, or the scene's own), applied to every wall of the room (or the fence);
- the physical spot size (one per session; each view sees it at its own distance);
- the spot's brightness (``gain``) and the sensor's green/blue response to it (``whiteness``):
  together they decide whether the core is white or red;
- the lens blur (a Gaussian PSF) and the bloom (the red halo, an image-space Gaussian);
- the shutter time: the whole frame is blurred along the image motion of the dot (the phone
  moving while the shutter is open);
- a brief occlusion: for a few frames something (the performer's arm) passes in front of the dot.

The renderer calls :func:`paint_dot` on its linear image and then the per-frame effects of
:func:`frame_effects` (occluder, motion blur), all before exposure, noise and quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from embodmocap.synth.config import LaserConfig
from embodmocap.synth.scene import BuiltScene
from embodmocap.synth.texture import Material
from embodmocap.types import Intrinsics

# name: base, alt, cell size (m), blob size (m), blob contrast, grout width (m), grout colour
_WALLS: dict[str, tuple] = {
    "reddish": ((0.70, 0.30, 0.25), (0.60, 0.23, 0.19), 0.20, 0.05, 0.35, 0.0, (0.0, 0.0, 0.0)),
    "magenta": ((0.72, 0.28, 0.58), (0.58, 0.20, 0.47), 0.06, 0.02, 0.50, 0.0, (0.0, 0.0, 0.0)),
    "beige": ((0.86, 0.77, 0.61), (0.78, 0.70, 0.55), 0.25, 0.06, 0.30, 0.0, (0.0, 0.0, 0.0)),
    "grey": ((0.55, 0.55, 0.56), (0.45, 0.46, 0.48), 0.20, 0.04, 0.35, 0.0, (0.0, 0.0, 0.0)),
    # Small high-contrast cells with reddish-brown speckles and dark grout: a busy, partly red wall.
    "textured": ((0.82, 0.78, 0.70), (0.62, 0.30, 0.26), 0.035, 0.012, 0.65, 0.003, (0.15, 0.10, 0.10)),
}

#: Clothing colours of the performer in realistic / none sessions; the first is the red one.
_RED_CLOTHES = (0.78, 0.08, 0.10)
_MAX_BLUR_PX = 60.0  # longest motion-blur streak drawn, pixels
_OCCLUDER_RGB = ((0.78, 0.08, 0.10), (0.85, 0.62, 0.50), (0.15, 0.18, 0.35), (0.30, 0.30, 0.30))


@dataclass(frozen=True)
class DotLook:
    """How one view sees the dot (drawn per seed by :func:`draw_looks`).

    Attributes:
        core_radius_m: radius of the over-exposed spot on the wall, metres.
        core_px: its diameter in pixels at the sync event (for reports).
        halo_px: diameter of the red halo, pixels.
        gain: the spot's brightness relative to a white wall.
        whiteness: green/blue response relative to red.
        psf_sigma_px: lens blur, pixels.
        shutter: exposure time as a fraction of the frame interval (motion blur).
        occluded: raw frames of the view in which an occluder hides the dot.
        occluder_rgb: the occluder's colour (linear, 0..1).
        occluder_px: the occluder's width, pixels.
    """

    core_radius_m: float
    core_px: float
    halo_px: float
    gain: float
    whiteness: float
    psf_sigma_px: float
    shutter: float
    occluded: tuple[int, ...] = ()
    occluder_rgb: tuple[float, float, float] = (0.3, 0.3, 0.3)
    occluder_px: float = 30.0


def wall_material(base: Material, look: str, rng: np.random.Generator) -> Material:
    """The wall material ``base`` repainted with the preset ``look`` (colours jittered a little)."""
    if look == "scene":
        return base
    if look not in _WALLS:
        raise ValueError(f"unknown wall look {look!r}; one of {['scene', *_WALLS]}")
    b, a, cell, blob, contrast, grout, grout_rgb = _WALLS[look]

    def jit(rgb):
        return tuple(np.clip(np.asarray(rgb) + rng.uniform(-0.04, 0.04, 3), 0.02, 0.98).round(4).tolist())

    return replace(base, base_rgb=jit(b), alt_rgb=jit(a), cell_m=(cell, cell, cell), blob_m=blob,
                   contrast=contrast, grout_m=grout, grout_rgb=grout_rgb)


def with_wall_look(built: BuiltScene, look: str, rng: np.random.Generator) -> BuiltScene:
    """The same scene with its ``"wall"`` material (room walls or fence) repainted as ``look``."""
    i = built.material_id("wall")
    mats = list(built.materials)
    mats[i] = wall_material(mats[i], look, rng)
    return replace(built, materials=tuple(mats))


def clothes_rgb(cfg: LaserConfig, rng: np.random.Generator) -> tuple[float, float, float] | None:
    """Red clothes with probability ``cfg.red_clothes_prob`` in realistic / none sessions, else None
    (the renderer's default colour)."""
    u = rng.random()  # drawn in every mode, so the draws after it do not depend on the mode
    if cfg.mode != "easy" and u < cfg.red_clothes_prob:
        return _RED_CLOTHES
    return None


def draw_looks(cfg: LaserConfig, rng: np.random.Generator, distance_m: dict[str, float], fx: float,
               lead_frames: dict[str, int]) -> dict[str, DotLook]:
    """Per view, the dot's look, for a realistic session.

    Args:
        cfg: the ranges.
        rng: the session's generator for the laser.
        distance_m: per view, camera-to-dot z-distance at the event, metres.
        fx: focal length, pixels.
        lead_frames: per view, frames recorded before the event (the dot is on in 0..lead-1).
    """
    views = list(distance_m)
    # One physical spot: the first view sees it at the drawn size, the others at their distance
    # (kept within the range: the exposure decides how much of the spot over-exposes).
    target = rng.uniform(*cfg.core_px)
    diameter_m = target * distance_m[views[0]] / fx
    looks = {}
    for v in views:
        z = distance_m[v]
        core = float(np.clip(diameter_m * fx / z, *cfg.core_px))
        halo = float(max(rng.uniform(*cfg.halo_px), core + 2.0))
        occluded: tuple[int, ...] = ()
        n_occ = int(rng.integers(cfg.occlusion_frames[0], cfg.occlusion_frames[1] + 1))
        lead = lead_frames[v]
        # Hidden somewhere in the middle of the "on" stretch: seen before and after, so the true
        # switch-off stays observable (an occlusion over the switch-off would hide the event).
        if rng.random() < cfg.occlusion_prob and n_occ > 0 and lead - 4 - n_occ > 3:
            s = int(rng.integers(3, lead - 4 - n_occ + 1))
            occluded = tuple(range(s, s + n_occ))
        looks[v] = DotLook(
            core_radius_m=core / 2 * z / fx, core_px=round(core, 3), halo_px=round(halo, 3),
            gain=float(rng.uniform(*cfg.gain)), whiteness=float(rng.uniform(*cfg.whiteness)),
            psf_sigma_px=float(rng.uniform(*cfg.psf_sigma_px)), shutter=float(rng.uniform(*cfg.shutter)),
            occluded=occluded, occluder_rgb=_OCCLUDER_RGB[int(rng.integers(len(_OCCLUDER_RGB)))],
            occluder_px=float(rng.uniform(20, 45)),
        )
    return looks


def hand_wobble(T_scene_cam: NDArray, fps: float, cfg: LaserConfig, rng: np.random.Generator) -> NDArray:
    """Cameras (T, 4, 4) with a smooth hand wobble of the aim added (positions untouched).

    The wobble is a sum of three sinusoids per axis (pan and tilt about the camera's own axes),
    the main one at a frequency drawn from ``cfg.shake_hz``, with an amplitude drawn from
    ``cfg.shake_deg``: the image moves by up to ~10 px per frame, as a hand-held phone does.
    """
    from scipy.spatial.transform import Rotation

    T = np.array(T_scene_cam, dtype=np.float64, copy=True)
    t = np.arange(len(T)) / fps
    amp = np.deg2rad(rng.uniform(*cfg.shake_deg))
    f0 = rng.uniform(*cfg.shake_hz)
    angles = np.zeros((len(T), 3))
    for axis in (0, 1):  # tilt about camera x, pan about camera y
        for k, (mult, w) in enumerate(((1.0, 0.7), (2.3, 0.2), (4.1, 0.1))):
            angles[:, axis] += amp * w * np.sin(2 * np.pi * f0 * mult * rng.uniform(0.8, 1.2) * t + rng.uniform(0, 2 * np.pi))
    T[:, :3, :3] = T[:, :3, :3] @ Rotation.from_rotvec(angles).as_matrix()
    return T


def project(K: Intrinsics, T_world_cam: NDArray, p: NDArray) -> tuple[float, float, float]:
    """(u, v, z) of world point ``p`` (3,) in camera ``T_world_cam`` (4, 4)."""
    pc = (np.asarray(p, float) - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    z = float(pc[2])
    if z <= 1e-6:
        return float("nan"), float("nan"), z
    return float(pc[0] / z * K.fx + K.cx), float(pc[1] / z * K.fy + K.cy), z


def paint_dot(rgb: NDArray[np.float32], t: NDArray, body_hit: NDArray, dirs: NDArray, K: Intrinsics,
              T: NDArray, dot: NDArray, look: DotLook) -> None:
    """Add the spot's light to a linear (H*W, 3) image in place.

    Args:
        rgb: (H*W, 3) float32 linear colour (1 = white wall).
        t: (H*W,) hit z-distance (inf: none); body_hit: (H*W,) the body is the nearest surface.
        dirs: (3, H*W) world ray directions with unit camera z.
        K, T: the camera; dot: (3,) the spot's centre on the wall.
    """
    import cv2

    u, v, z = project(K, T, dot)
    if not z > 0.05 or not np.isfinite(u):
        return
    foot = z / K.fx  # metres per pixel at the dot
    r_halo = look.halo_px / 2
    half = int(np.ceil(2.2 * r_halo + 3 * look.psf_sigma_px + 3))
    u0, u1 = int(max(0, np.floor(u) - half)), int(min(K.width, np.floor(u) + half + 2))
    v0, v1 = int(max(0, np.floor(v) - half)), int(min(K.height, np.floor(v) + half + 2))
    if u0 >= u1 or v0 >= v1:
        return
    h, w = v1 - v0, u1 - u0
    idx = (np.arange(v0, v1)[:, None] * K.width + np.arange(u0, u1)[None, :]).reshape(-1)
    visible = np.isfinite(t[idx]) & ~body_hit[idx]
    tt = np.where(visible, t[idx], 0.0).astype(np.float64)
    p = T[:3, 3] + tt[:, None] * dirs[:, idx].T.astype(np.float64)
    dist = np.linalg.norm(p - dot, axis=1)
    # Anti-aliased coverage of the spot: a pixel's footprint is ~foot metres across.
    cov = np.where(visible, np.clip((look.core_radius_m - dist) / foot + 0.5, 0.0, 1.0), 0.0).reshape(h, w)
    area = np.pi * (look.core_radius_m / foot) ** 2
    seen = float(np.clip(cov.sum() / max(area, 1e-6), 0.0, 1.0))
    if seen <= 0:
        return  # the spot is hidden: no light reaches the lens, no bloom either
    core = cv2.GaussianBlur(cov.astype(np.float32), (0, 0), look.psf_sigma_px)
    yy, xx = np.mgrid[v0:v1, u0:u1]
    sigma_h = r_halo / 1.95  # the halo's added red falls to ~0.12 of its peak at r_halo
    halo = (0.85 * seen) * np.exp(-0.5 * ((xx - u) ** 2 + (yy - v) ** 2) / sigma_h**2).astype(np.float32)
    add = np.empty((h, w, 3), np.float32)
    add[..., 0] = look.gain * core + halo
    add[..., 1] = look.gain * look.whiteness * core + 0.06 * halo
    add[..., 2] = look.gain * look.whiteness * core + 0.05 * halo
    img = rgb.reshape(K.height, K.width, 3)
    img[v0:v1, u0:u1] += add


def frame_effects(look: DotLook, K: Intrinsics, T_prev: NDArray, T: NDArray, T_next: NDArray, dot: NDArray,
                  frame: int) -> Callable[[NDArray[np.float32]], None]:
    """Per-frame effects on the linear (H, W, 3) image after the dot is drawn: the occluder (if
    ``frame`` is in ``look.occluded``) and the motion blur of the whole frame (the image motion of
    the dot over the shutter time, from the neighbouring camera poses)."""
    u, v, z = project(K, T, dot)
    up, vp, zp = project(K, T_prev, dot)
    un, vn, zn = project(K, T_next, dot)
    motion = np.array([un - up, vn - vp]) / 2 * look.shutter  # pixels moved while the shutter is open
    if min(z, zp, zn) < 0.1 or not np.all(np.isfinite(motion)) or np.hypot(*motion) > _MAX_BLUR_PX:
        # The dot is behind or beside the camera (it has turned back to the performer): the image
        # motion at the image centre, for a point as far as the dot.
        p = T[:3, 3] + T[:3, 2] * max(float(np.linalg.norm(np.asarray(dot) - T[:3, 3])), 0.5)
        a, b = np.array(project(K, T_prev, p)[:2]), np.array(project(K, T_next, p)[:2])
        motion = (b - a) / 2 * look.shutter
        if not np.all(np.isfinite(motion)):
            motion = np.zeros(2)
        motion *= min(1.0, _MAX_BLUR_PX / max(float(np.hypot(*motion)), 1e-9))

    def apply(img: NDArray[np.float32]) -> None:
        import cv2

        H, W = img.shape[:2]
        if frame in look.occluded and np.isfinite(u):
            # An arm crossing the dot: a bar from above the dot down to the image bottom, moving
            # sideways across it during the occlusion, shaded so it is not flat.
            k = look.occluded.index(frame)
            n = len(look.occluded)
            cx = u + look.occluder_px * 0.3 * ((k + 0.5) / n - 0.5)
            x0, x1 = int(max(0, cx - look.occluder_px / 2)), int(min(W, cx + look.occluder_px / 2 + 1))
            y0 = int(max(0, v - 1.5 * look.occluder_px))
            if x0 < x1 and y0 < H:
                xs = np.linspace(-1, 1, x1 - x0, dtype=np.float32)
                shade = (0.55 + 0.45 * np.sqrt(np.clip(1 - xs**2, 0, 1)))[None, :, None]
                img[y0:H, x0:x1] = np.asarray(look.occluder_rgb, np.float32) * shade
        length = float(np.hypot(*motion))
        if length >= 1.0:
            n = int(np.ceil(length)) | 1
            kern = np.zeros((n, n), np.float32)
            c = n // 2
            for s in np.linspace(-0.5, 0.5, 4 * n):
                kern[int(round(c + s * motion[1])), int(round(c + s * motion[0]))] += 1
            kern /= kern.sum()
            img[:] = cv2.filter2D(img, -1, kern, borderType=cv2.BORDER_REFLECT)

    return apply
