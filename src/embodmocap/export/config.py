"""Settings of the exports (:class:`ExportConfig`, ``embodmocap export``); also importable from
:mod:`embodmocap.export.run`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal


@dataclass(frozen=True)
class ExportConfig:
    """Options of the exports (defaults suit most users)."""

    amass_hands: bool = False
    """AMASS: write the (T, 156) SMPL+H pose layout with zero hands instead of SMPL's (T, 72)."""
    bvh_units: Literal["cm", "m"] = "cm"
    """BVH: length unit of offsets and root positions (most BVH tools expect centimetres)."""
    mimickit_loop: Literal["clamp", "wrap"] = "clamp"
    """MimicKit: what the motion does past its end (clamp = hold the last frame, wrap = loop)."""
    heightmap_cell_m: float = 0.05
    """MimicKit and MJCF: height-map cell size, metres (the paper samples a 0.05 m map)."""
    scene_collision: Literal["heightfield", "coacd", "both"] = "heightfield"
    """MJCF: the scene as a support heightfield, as convex pieces of the mesh (coacd, cached in
    sequences/SEQ/sim/ by mesh hash; keeps overhangs such as a table's underside open), or both."""
    robot: str = "g1"
    """Robot (``--to robot``): a built-in robot name (g1)."""
    robot_config: Path | None = None
    """Robot (``--to robot``): a robot config TOML (docs/robot.md) instead of a built-in robot."""
    training_jpeg_quality: int = 95
    """Training (``--to training``): JPEG quality of the RGB frames (1-100; 95 keeps the images
    close to the video's own quality at about 90 KB a 640x480 frame)."""
    training_rgb_width: int = 0
    """Training (``--to training``): width of the stored RGB frames and masks in pixels, the aspect
    kept (0 = the capture's own size; e.g. 640 for 1920x1440 iPhone video). K, keypoints and boxes
    follow; depth keeps its own size."""
