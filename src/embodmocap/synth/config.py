"""Settings of the synthetic studio (kept apart from the studio so the CLI imports it cheaply)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from embodmocap.types import Intrinsics


@dataclass(frozen=True)
class SynthConfig:
    """Settings of one synthetic session."""

    seed: int = 0
    """Random seed; the same seed gives identical files."""
    preset: Literal["indoor", "outdoor"] = "indoor"
    """Scene kind: a furnished room or a fenced yard."""
    seconds: float = 10.0
    """Length of the performance after the sync event, seconds (views record about this long)."""
    scene_seconds: float = 20.0
    """Length of the empty-scene capture, seconds."""
    fps: float = 30.0
    """Frame rate of every capture and of the motion."""
    width: int = 640
    """RGB width in pixels (up to 1920); height follows ``height``."""
    height: int = 480
    """RGB height in pixels (up to 1440)."""
    depth_width: int = 256
    """LiDAR depth width in pixels (the iPhone's is 256)."""
    depth_height: int = 192
    """LiDAR depth height in pixels (the iPhone's is 192)."""
    hfov_deg: float = 67.0
    """Horizontal field of view of the RGB camera, degrees (an iPhone main camera is about 67)."""
    format: Literal["strayscanner", "spectacular"] = "strayscanner"
    """Capture format the phones' files are written in."""
    scene_name: str = "scene0"
    """Name of the scene in the manifest."""
    sequence_name: str = "seq0"
    """Name of the sequence in the manifest."""
    lead_min_s: float = 0.4
    """Shortest time a view records before the sync event, seconds."""
    tail_max_s: float = 0.5
    """Longest time a view stops before the end of the motion, seconds (views end at different times)."""
    perception: Literal["clean", "hard"] = "clean"
    """The 2D detector the perception files imitate: ``clean`` = a good detector on a clear view
    (jitter, low confidence when occluded, rare outliers, short swaps); ``hard`` = every adversity
    of real detectors on (:data:`embodmocap.synth.perception.HARD_KEYPOINT_NOISE`: noise growing
    with occlusion and distance, missed joints, more outliers, left/right limb swaps lasting up to
    a second, whole-body misses, furniture-hidden joints guessed at wrong places) and, unless
    ``keypoint_layout`` says otherwise, OpenPose BODY_25 output."""
    body_prior: Literal["none", "realistic", "poor"] = "realistic"
    """The camera-space body prior written per view: ``none`` (no file: a user without regressor
    weights), ``realistic`` (a VIMO-like regressor: 7 deg per joint, depth 10 % off) or ``poor``
    (15 deg per joint, depth 20 % off)."""
    keypoint_layout: Literal["auto", "COCO17", "BODY_25"] = "auto"
    """Layout of the keypoint JSON: ``COCO17``, ``BODY_25`` (OpenPose's default model, with its own
    hip definition) or ``auto`` (BODY_25 for ``perception = hard``, else COCO17)."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        checks = [
            (self.seconds > 0 and self.scene_seconds > 0, "seconds and scene_seconds must be > 0"),
            (0 < self.fps <= 120, "fps must be in (0, 120]"),
            (16 <= self.width <= 1920 and 16 <= self.height <= 1440, "RGB size must be within 16x16..1920x1440"),
            (self.width % 2 == 0 and self.height % 2 == 0, "RGB width and height must be even (H.264)"),
            (8 <= self.depth_width <= self.width and 8 <= self.depth_height <= self.height, "depth size must be >= 8 and <= the RGB size"),
            (20 < self.hfov_deg < 150, "hfov_deg must be in (20, 150)"),
        ]
        bad = [msg for ok, msg in checks if not ok]
        if bad:
            raise InputError(None, "invalid synth settings: " + "; ".join(bad), "change the options")

    def layout(self) -> str:
        """The keypoint layout the perception files are written in."""
        if self.keypoint_layout != "auto":
            return self.keypoint_layout
        return "BODY_25" if self.perception == "hard" else "COCO17"

    def intrinsics(self) -> Intrinsics:
        fx = (self.width / 2) / np.tan(np.deg2rad(self.hfov_deg) / 2)
        return Intrinsics(fx, fx, (self.width - 1) / 2, (self.height - 1) / 2, self.width, self.height)

    def depth_intrinsics(self) -> Intrinsics:
        return self.intrinsics().scaled(self.depth_width, self.depth_height)
