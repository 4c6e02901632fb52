"""Settings of the overlay renderer (:class:`RenderConfig`, ``embodmocap render``) and the web viewer
(:class:`ViewerConfig`, ``embodmocap view``); also importable from their modules."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class RenderConfig:
    """How the overlay videos look."""

    alpha: float = 0.6
    """Opacity of the body over the frame (0 = invisible, 1 = opaque)."""
    body_rgb: tuple[int, int, int] = (110, 170, 255)
    """Base colour of the body, 0..255 RGB."""
    ambient: float = 0.35
    """Light reaching every body surface whatever its orientation (0..1)."""
    diffuse: float = 0.75
    """Strength of the Lambertian term; the light comes from the camera, slightly from above."""
    occlude_with_scene: bool = True
    """Hide body parts behind the scene mesh (needs the scene's mesh file; skipped without it)."""
    scene_mesh: Literal["simplified", "full"] = "simplified"
    """Which Stage I mesh occludes the body: ``mesh_simplified.ply`` or ``mesh_raw.ply``."""
    occlusion_margin_m: float = 0.03
    """The scene hides a body pixel only when it is nearer by more than this (metres): feet on the
    floor and a seated body stay visible despite the mesh's noise."""
    max_side: int = 1280
    """Frames larger than this (longest side, pixels) are scaled down before drawing; 0 = never."""
    side_by_side: bool = True
    """Also write ``side_by_side.mp4`` with both views at a common height."""
    crf: int = 20
    """H.264 quality (lower = better, larger files)."""
    chunk_frames: int = 64
    """Frames posed at once (memory: chunk x 6890 x 3 float32)."""
    progress: bool = True
    """Show a tqdm progress bar."""


@dataclass(frozen=True)
class ViewerConfig:
    """Settings of the web viewer."""

    host: str = "127.0.0.1"
    """Interface to listen on; ``0.0.0.0`` makes the viewer reachable from other machines."""
    port: int = 8080
    """TCP port of the page (http://host:port)."""
    mesh: Literal["simplified", "full", "none"] = "simplified"
    """Scene mesh to show: ``mesh_simplified.ply``, ``mesh_raw.ply`` or none."""
    max_image_side: int = 320
    """Longest side, pixels, of the frame shown inside each frustum (0 = no images)."""
    frustum_scale: float = 0.25
    """Size of the camera frusta, metres."""
    jpeg_quality: int = 80
    """JPEG quality of the frustum images sent to the browser (1..100)."""
    point_size: float = 0.04
    """Diameter of the keypoint markers, metres."""
    body_rgb: tuple[int, int, int] = (110, 170, 255)
    """Body colour, 0..255 RGB."""
    body_opacity: float = 1.0
    """Body opacity (0..1)."""
    chunk_frames: int = 64
    """Frames posed at once (memory: 2 chunks x V x 3 float32)."""
    playback_fps: float | None = None
    """Playback speed at 1x, frames per second; None = the motion's own frame rate."""
    start_playing: bool = False
    """Start the timeline playing as soon as the server is up."""
    robot: str = "auto"
    """Retargeted robot to show (``embodmocap robot retarget``): a robot name, ``auto`` (the first
    one found, if any) or ``none``."""
    robot_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where the robot is drawn relative to its motion, metres (e.g. ``1 0 0`` puts it beside the
    body instead of in its place)."""
