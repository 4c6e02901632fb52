"""Overlay videos (``embodmocap render``): the fitted body drawn over each view's RGB frames.

For every sequence frame and view, the world SMPL body is seen through the view's final camera
(``cameras_final.npz``) and drawn, semi-transparent and Lambert-shaded, over the raw capture frame
the camera belongs to (``raw_frames``). Output, in ``SESSION/sequences/<seq>/render/``:

- ``<view>_overlay.mp4`` per view, at the capture's resolution (or scaled down to ``max_side``);
- ``side_by_side.mp4``: both views next to each other at a common height.

The body is drawn with the CPU ray caster the synthetic studio uses (Open3D ``RaycastingScene``):
rays through the pixel centres (:func:`embodmocap.geometry.raycast.camera_ray_dirs`) are cast only
inside the body's projected bounding box, so a frame costs a few milliseconds. With
``occlude_with_scene`` the scene mesh is cast for the same pixels and hides the body parts behind
furniture, as in the real image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.layout import SessionLayout
from embodmocap.geometry.raycast import camera_ray_dirs, cast_rays, raycasting_scene
from embodmocap.types import Intrinsics
from embodmocap.viz.config import RenderConfig
from embodmocap.viz import SequenceData, BodyFrames, load_sequence

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BodyPixels:
    """Where the body is in one image.

    Attributes:
        mask: (H, W) bool, pixels whose nearest (visible) surface is the body.
        shade: (H, W) float32 Lambert factor of the body at those pixels (0 elsewhere).
    """

    mask: NDArray[np.bool_]
    shade: NDArray[np.float32]


def _body_box(K: Intrinsics, T_world_cam: NDArray, vertices: NDArray) -> tuple[int, int, int, int] | None:
    """Half-open pixel box ``(u0, u1, v0, v1)`` holding the body's projection, or None if not seen.

    Vertices behind the camera (z <= 1 cm) make the box the whole image: their projection is
    unbounded, and the ray cast itself decides what is seen.
    """
    pc = (np.asarray(vertices, dtype=np.float64) - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    z = pc[:, 2]
    if (z <= 1e-2).all():
        return None
    if (z <= 1e-2).any():
        return 0, K.width, 0, K.height
    u = pc[:, 0] / z * K.fx + K.cx
    v = pc[:, 1] / z * K.fy + K.cy
    u0, u1 = np.clip([np.floor(u.min()) - 1, np.ceil(u.max()) + 2], 0, K.width).astype(int)
    v0, v1 = np.clip([np.floor(v.min()) - 1, np.ceil(v.max()) + 2], 0, K.height).astype(int)
    if u0 >= u1 or v0 >= v1:
        return None
    return int(u0), int(u1), int(v0), int(v1)


def body_pixels(K: Intrinsics, T_world_cam: NDArray, vertices: NDArray, faces: NDArray,
                occluder=None, cfg: RenderConfig = RenderConfig()) -> BodyPixels:
    """Ray-cast a body mesh from one pinhole camera.

    Args:
        K: the camera (OpenCV pinhole, pixel centres at integer coordinates).
        T_world_cam: (4, 4) camera-to-world, OpenCV axes.
        vertices: (V, 3) body vertices in the world, metres.
        faces: (F, 3) triangles.
        occluder: an Open3D ``RaycastingScene`` of the scene, or None (the body is never hidden).
        cfg: shading and occlusion settings.

    Returns:
        The body's visible pixels and their shading.
    """
    H, W = K.height, K.width
    mask = np.zeros((H, W), dtype=bool)
    shade = np.zeros((H, W), dtype=np.float32)
    T = np.asarray(T_world_cam, dtype=np.float64)
    box = _body_box(K, T, vertices)
    if box is None:
        return BodyPixels(mask, shade)
    u0, u1, v0, v1 = box
    dirs_cam = camera_ray_dirs(K).reshape(3, H, W)[:, v0:v1, u0:u1].reshape(3, -1)
    dirs = (T[:3, :3].astype(np.float32) @ dirs_cam).T  # (n, 3) world; unit camera z, so t = depth
    hit = cast_rays(raycasting_scene(vertices, faces), T[:3, 3], dirs)
    seen = np.isfinite(hit["t_hit"])
    if occluder is not None and seen.any():
        t_scene = cast_rays(occluder, T[:3, 3], dirs)["t_hit"]
        seen &= ~(t_scene < hit["t_hit"] - cfg.occlusion_margin_m)
    # Light from the camera, tilted a little towards the world's up, so the shading reads as
    # shape whatever the viewing direction; normals are flipped to face the camera (the mesh's
    # winding does not matter).
    n = hit["primitive_normals"][seen]
    d = dirs[seen] / np.linalg.norm(dirs[seen], axis=1, keepdims=True)
    n = np.where((np.sum(n * d, axis=1) > 0)[:, None], -n, n)
    light = -d + np.float32(0.5) * np.array([0.0, 0.0, 1.0], dtype=np.float32)
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    lam = np.clip(np.sum(n * light, axis=1), 0.0, None)
    box_mask = np.zeros((v1 - v0) * (u1 - u0), dtype=bool)
    box_mask[seen] = True
    box_shade = np.zeros(len(box_mask), dtype=np.float32)
    box_shade[seen] = cfg.ambient + cfg.diffuse * lam
    mask[v0:v1, u0:u1] = box_mask.reshape(v1 - v0, u1 - u0)
    shade[v0:v1, u0:u1] = box_shade.reshape(v1 - v0, u1 - u0)
    return BodyPixels(mask, shade)


def overlay(rgb: NDArray[np.uint8], body: BodyPixels, cfg: RenderConfig = RenderConfig()) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 frame with the shaded body blended in at ``cfg.alpha``."""
    out = rgb.copy()
    m = body.mask
    colour = np.clip(np.asarray(cfg.body_rgb, dtype=np.float32)[None] * body.shade[m][:, None], 0, 255)
    out[m] = np.clip((1 - cfg.alpha) * rgb[m] + cfg.alpha * colour + 0.5, 0, 255).astype(np.uint8)
    return out


def _even_size(K: Intrinsics, max_side: int) -> tuple[int, int]:
    """Output (width, height): scaled so the longest side is at most ``max_side``, both even."""
    s = min(1.0, max_side / max(K.width, K.height)) if max_side > 0 else 1.0
    return max(2, int(round(K.width * s)) // 2 * 2), max(2, int(round(K.height * s)) // 2 * 2)


def _open_frames(session: Path, seq: str, view: str):
    """The view's raw capture frames (``FrameSource``), as the manifest names the capture."""
    from embodmocap.io.captures import open_capture
    from embodmocap.io.manifest import load_manifest

    lay = SessionLayout(session)
    entry = load_manifest(lay.manifest).sequences[seq].views.get(view)
    path = entry.capture if entry is not None else lay.view_capture(seq, view)
    return open_capture(path)


def _occluder(session: Path, data: SequenceData, cfg: RenderConfig):
    if not cfg.occlude_with_scene:
        return None
    from embodmocap.io.mesh_file import read_mesh_ply

    scene = SessionLayout(session).scene(data.scene)
    path = scene.mesh_simplified if cfg.scene_mesh == "simplified" else scene.mesh_raw
    if not path.is_file():
        log.warning("%s not found: the body is drawn without scene occlusion", path)
        return None
    v, f, _ = read_mesh_ply(path)
    return raycasting_scene(v, f)


def _resized(rgb: NDArray[np.uint8], size: tuple[int, int]) -> NDArray[np.uint8]:
    import cv2

    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def render_sequence(session: str | Path, seq: str, cfg: RenderConfig = RenderConfig()) -> list[Path]:
    """Write the overlay MP4s of a sequence; returns their paths (views first, then side by side).

    Raises:
        InputError: Stage IV outputs are missing or malformed (run the motion stage first), or a
            camera names a raw frame the capture does not have.
    """
    from embodmocap.progress import progress

    from embodmocap.body.model import load_body_model
    from embodmocap.io.video import VideoWriter

    session = Path(session)
    data = load_sequence(session, seq)
    out_dir = SessionLayout(session).sequence(seq).renders_dir
    body = BodyFrames(load_body_model(data.body_model), data.params, chunk=cfg.chunk_frames)
    faces = body.faces
    occluder = _occluder(session, data, cfg)

    views, sizes, sources = list(data.views), {}, {}
    for v in views:
        cams = data.views[v]
        capture = _open_frames(session, seq, v)
        raw = cams.raw_frames[data.frames]
        if len(raw) and (raw.min() < 0 or raw.max() >= capture.num_frames):
            raise InputError(SessionLayout(session).sequence(seq).view(v).cameras_final,
                             f"raw frames {int(raw.min())}..{int(raw.max())} outside the capture's "
                             f"0..{capture.num_frames - 1}", f"run `embodmocap motion SESSION --seq {seq}` again")
        sizes[v] = _even_size(cams.intrinsics, cfg.max_side)
        sources[v] = capture.frames
    fps = data.params.fps
    paths = [out_dir / f"{v}_overlay.mp4" for v in views]
    writers = [VideoWriter(p, fps, *sizes[v], crf=cfg.crf) for p, v in zip(paths, views)]
    # Side by side at the smaller of the two heights; widths follow each view's aspect.
    H = min(h for _, h in sizes.values())
    sbs_sizes = {v: (max(2, int(round(w * H / h)) // 2 * 2), H) for v, (w, h) in sizes.items()}
    if cfg.side_by_side:
        paths.append(out_dir / "side_by_side.mp4")
        writers.append(VideoWriter(paths[-1], fps, sum(w for w, _ in sbs_sizes.values()), H, crf=cfg.crf))
    try:
        for i, t in enumerate(progress(data.frames, f"render {seq}", unit="frame", disable=not cfg.progress)):
            verts = body.vertices(i)
            tiles = []
            for v, writer in zip(views, writers):
                cams = data.views[v]
                K = cams.intrinsics.scaled(*sizes[v])
                rgb = _resized(sources[v].rgb(int(cams.raw_frames[t])), sizes[v])
                img = overlay(rgb, body_pixels(K, cams.T_world_cam[t], verts, faces, occluder, cfg), cfg)
                writer.write(img)
                tiles.append(_resized(img, sbs_sizes[v]))
            if cfg.side_by_side:
                writers[-1].write(np.concatenate(tiles, axis=1))
    except BaseException:
        for w in writers:
            w.abort()
        raise
    for w in writers:
        w.close()
    log.info("wrote %s", ", ".join(str(p) for p in paths))
    return paths
