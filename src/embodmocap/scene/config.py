"""Settings of stage I (scene): key frames, depth, TSDF fusion, mesh clean-up and the sparse model.

One flat, frozen dataclass so the whole stage is configured by one object (and one TOML table).
Values that differ between indoor and outdoor scenes come in ``*_indoor`` / ``*_outdoor`` pairs;
read them through the small accessor methods (``cfg.voxel_m(indoor)`` ...) so no caller repeats
the choice. Defaults follow the EmbodMocap paper and its official release (see
``shared/reference/official-release-notes.md`` section 2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from embodmocap.scene.sfm import SfmConfig


@dataclass(frozen=True)
class SceneConfig:
    """Stage I settings (lengths in metres, angles in degrees)."""

    # ------------------------------------------------------------------ key frames
    keyframe_step_m_indoor: float = 0.10
    """Indoor: a new key frame once the camera centre is this far (straight line, metres) from the
    last key frame's centre (the release's SAI ``key_frame_distance``)."""
    keyframe_step_m_outdoor: float = 0.15
    """Outdoor: as ``keyframe_step_m_indoor``."""
    keyframe_step_deg: float = 15.0
    """A new key frame also once the camera has turned this many degrees since the last key frame
    (keeps coverage when the operator pans on the spot)."""
    blur_window: int = 4
    """Key frames are taken in consecutive groups of this many; the blurriest of each full group is
    dropped (the release's ``blur_filter_range``). 0 or 1 = keep all."""
    blur_long_side_px: int = 320
    """Frames are shrunk to this long side (pixels) before the Laplacian sharpness is measured:
    cheap, and insensitive to sensor noise."""
    jump_speed_mps: float = 3.0
    """A pose step faster than this (metres per second) is a tracking jump (handheld walking is
    about 1 m/s)."""
    jump_rate_dps: float = 400.0
    """A pose step turning faster than this (degrees per second) is a tracking jump."""
    jump_ratio: float = 8.0
    """A step is also a jump when it is this many times longer than the median step of its
    neighbours (and longer than ``jump_min_step_m``): catches jumps below the speed limit."""
    jump_min_step_m: float = 0.05
    """Steps shorter than this (metres) are never jumps by the ratio test (noise at rest)."""
    jump_neighbours: int = 15
    """Half-width (steps) of the window whose median step the ratio test compares against."""
    min_keyframes: int = 10
    """Fewer usable key frames than this is an input error (the capture is too short or lost
    tracking)."""

    # ------------------------------------------------------------------ depth
    min_confidence: int = 0
    """LiDAR pixels with confidence below this are dropped (0 low, 1 medium, 2 high). Captures
    without a confidence map keep every pixel. 0 keeps every pixel and lets
    ``confidence_weights`` weigh them instead (low-confidence depth is often the only view of a
    ceiling or a far wall)."""
    confidence_weights: tuple[float, float, float] = (0.25, 0.5, 1.0)
    """Fusion weight of a pixel of confidence 0, 1, 2 (in (0, 1]). The TSDF weighs every
    observation 1, so a weight w is applied as a share: the pixels of that confidence enter w of
    the fused frames (evenly spread, deterministic); over the many frames that see a surface this
    is a weighted average, and a surface seen only at low confidence still gets fused."""
    min_valid_depth_fraction: float = 0.05
    """A scene capture whose sampled frames hold fewer valid depth pixels than this share (after
    ``min_confidence`` and the truncation) is an input error before anything is written."""
    depth_trunc_m_indoor: float = 5.0
    """Indoor: depth beyond this (metres) is dropped. The LiDAR's range (about 5 m): a fixed
    3.5 m cut lost far walls of large rooms and high ceilings; far, noisy pixels come with low
    confidence and are down-weighted (``confidence_weights``) rather than cut."""
    depth_trunc_m_outdoor: float = 5.0
    """Outdoor: as ``depth_trunc_m_indoor``."""
    depth_weight_range_m: float = 0.0
    """Depth (metres) beyond which a pixel's fusion weight (its share of the fused frames, times
    its confidence weight) falls as ``(range / depth)^2``: LiDAR noise grows with range, and a
    scan that looks across the room sees near surfaces from far too. 0 = off."""
    depth_refine: Literal["none", "promptda"] = "none"
    """Learned depth refinement backend: ``"none"`` (confidence-filtered LiDAR depth) or
    ``"promptda"`` (Prompt Depth Anything through transformers; needs ``depth_refine_model``)."""
    depth_refine_model: str = ""
    """Local path or hub id of the refinement model (used when ``depth_refine`` is not "none")."""

    # ------------------------------------------------------------------ TSDF
    voxel_m_indoor: float = 0.01
    """Indoor TSDF voxel size, metres."""
    voxel_m_outdoor: float = 0.02
    """Outdoor TSDF voxel size, metres."""
    sdf_trunc_voxels: float = 5.0
    """TSDF truncation distance in voxels (5 voxels = 5 cm indoors). It must exceed the depth
    noise (LiDAR: ~1 % of the depth) or surfaces get holes; larger values round corners."""
    integrate_every: int = 1
    """Integrate every k-th fusion frame (1 = all); >1 trades completeness for speed."""
    fuse_step_m: float = 0.04
    """Fusion frames (not only the SfM key frames): every trajectory row with a trusted pose (no
    tracking jump) whose camera moved at least this far (metres) or turned ``fuse_step_deg`` since
    the last fused frame. Frames closer than that see the same surface again and add only time."""
    fuse_step_deg: float = 4.0
    """Fusion frames: the rotation step, degrees (see ``fuse_step_m``)."""
    fuse_min_valid_fraction: float = 0.02
    """A frame with fewer valid depth pixels than this share is not fused (a covered sensor, the
    phone facing the sky)."""

    # ------------------------------------------------------------------ mesh clean-up
    min_component_fraction: float = 0.02
    """Connected components with fewer triangles than this fraction of the largest component are
    removed (relative, so small scenes keep their parts; the release uses an absolute 10,000
    vertices)."""
    min_component_triangles: int = 50
    """Components with fewer triangles than this are removed whatever the largest one holds."""
    floater_max_extent_m: float = 0.10
    """Components whose bounding-box diagonal is below this (metres) are floaters and removed,
    however dense (noise blobs in free space). 0 = off."""
    structure_min_extent_m: float = 0.5
    """Components with a bounding-box diagonal of at least this (metres) and at least
    ``min_component_triangles`` faces are real structure and always kept, whatever
    ``min_component_fraction`` says (a ceiling or far wall seen from a few frames, furniture seen
    from one side). 0 = off."""

    # ------------------------------------------------------------------ gravity check
    floor_tilt_warn_deg: float = 2.0
    """The fused mesh's floor (its dominant low near-horizontal plane) tilted more than this from
    horizontal, degrees, gives a warning (and ``floor_tilt_deg`` in the stage manifest): the
    capture's gravity is wrong (e.g. poses read relative to the first camera) and everything
    downstream (contacts, simulation) would inherit the tilt. 0 = no check."""

    # ------------------------------------------------------------------ simplified mesh
    simplify_voxel_m: float = 0.05
    """Vertex-clustering cell size (metres) of the simplified mesh for viewers and physics; 0 = do
    not write a simplified mesh."""

    # ------------------------------------------------------------------ sparse model (SfM)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    """Sparse-model settings (key frames used, SIFT, pair selection from the poses, triangulation)."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        checks = [
            (self.keyframe_step_m_indoor > 0 and self.keyframe_step_m_outdoor > 0, "keyframe steps must be > 0"),
            (self.keyframe_step_deg > 0, "keyframe_step_deg must be > 0"),
            (self.blur_window >= 0, "blur_window must be >= 0"),
            (self.blur_long_side_px >= 16, "blur_long_side_px must be >= 16"),
            (self.jump_speed_mps > 0 and self.jump_rate_dps > 0 and self.jump_ratio > 1, "jump thresholds must be > 0 (ratio > 1)"),
            (self.jump_neighbours >= 1, "jump_neighbours must be >= 1"),
            (self.min_keyframes >= 2, "min_keyframes must be >= 2"),
            (self.floor_tilt_warn_deg >= 0, "floor_tilt_warn_deg must be >= 0"),
            (self.min_confidence in (0, 1, 2), "min_confidence must be 0, 1 or 2"),
            (len(self.confidence_weights) == 3 and all(0 < w <= 1 for w in self.confidence_weights),
             "confidence_weights must be three values in (0, 1]"),
            (0 <= self.min_valid_depth_fraction < 1 and 0 <= self.fuse_min_valid_fraction < 1,
             "valid depth fractions must be in [0, 1)"),
            (self.fuse_step_m >= 0 and self.fuse_step_deg >= 0, "fuse steps must be >= 0"),
            (self.structure_min_extent_m >= 0, "structure_min_extent_m must be >= 0"),
            (self.depth_trunc_m_indoor > 0 and self.depth_trunc_m_outdoor > 0, "depth truncation must be > 0"),
            (self.depth_weight_range_m >= 0, "depth_weight_range_m must be >= 0 (0 = off)"),
            (self.depth_refine in ("none", "promptda"), "depth_refine must be 'none' or 'promptda'"),
            (self.voxel_m_indoor > 0 and self.voxel_m_outdoor > 0, "voxel sizes must be > 0"),
            (self.sdf_trunc_voxels >= 1, "sdf_trunc_voxels must be >= 1"),
            (self.integrate_every >= 1, "integrate_every must be >= 1"),
            (0 <= self.min_component_fraction <= 1, "min_component_fraction must be in [0, 1]"),
            (self.min_component_triangles >= 0 and self.floater_max_extent_m >= 0, "clean-up sizes must be >= 0"),
            (self.simplify_voxel_m >= 0, "simplify_voxel_m must be >= 0"),
        ]
        bad = [msg for ok, msg in checks if not ok]
        if bad:
            raise InputError(None, "invalid scene settings: " + "; ".join(bad), "fix the [scene] options")

    # Accessors for the indoor/outdoor pairs -----------------------------------------------------

    def keyframe_step_m(self, indoor: bool) -> float:
        """Key-frame translation step for this kind of scene, metres."""
        return self.keyframe_step_m_indoor if indoor else self.keyframe_step_m_outdoor

    def depth_trunc_m(self, indoor: bool) -> float:
        """Depth truncation for this kind of scene, metres."""
        return self.depth_trunc_m_indoor if indoor else self.depth_trunc_m_outdoor

    def voxel_m(self, indoor: bool) -> float:
        """TSDF voxel size for this kind of scene, metres."""
        return self.voxel_m_indoor if indoor else self.voxel_m_outdoor

    def sdf_trunc_m(self, indoor: bool) -> float:
        """TSDF truncation distance for this kind of scene, metres."""
        return self.sdf_trunc_voxels * self.voxel_m(indoor)
