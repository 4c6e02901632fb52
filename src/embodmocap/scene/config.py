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


@dataclass(frozen=True)
class SfmConfig:
    """Sparse model (Stage I) settings. Defaults keep a 60 s, 30 fps, 640x480 scene capture
    (~150 key frames) well under 90 s on 2 CPU cores."""

    max_images: int = 150
    """At most this many key frames go into SfM; more are thinned evenly (in the given order)."""
    max_features: int = 2048
    """SIFT features kept per image (the strongest). Matching cost grows with its square."""
    first_octave: int = 0
    """SIFT's first octave: 0 = the image as is; -1 upsamples it 2x first (about 1.6x the points at
    640x480 but about 4x slower extraction)."""
    image_format: Literal["jpg", "png"] = "jpg"
    """Format of the key frames written to ``out_dir/images``: JPEG (small, fast) or PNG (lossless)."""
    jpeg_quality: int = 95
    """JPEG quality 1..100 when ``image_format`` is ``"jpg"``."""
    pairing: Literal["poses", "exhaustive"] = "poses"
    """How image pairs are chosen: ``"poses"`` = from the known poses (see the fields below);
    ``"exhaustive"`` = every pair (only sensible for a few dozen images)."""
    num_neighbours: int = 10
    """``pairing="poses"``: each key frame is paired with at most this many others, those whose view
    overlaps it most."""
    max_view_angle_deg: float = 60.0
    """``pairing="poses"``: two key frames whose optical axes differ by more than this never pair."""
    overlap_depths_m: tuple[float, ...] = (1.0, 2.0, 3.0)
    """``pairing="poses"``: depths (metres) of the probe points cast from each key frame through a
    3x3 grid of pixels; the share of them another key frame sees is the pair's overlap. No depth maps
    are needed."""
    min_overlap: float = 0.15
    """``pairing="poses"``: pairs whose overlap (0..1) is below this are not matched."""
    match_max_ratio: float = 0.8
    """Lowe's ratio test threshold of the SIFT matcher (lower = stricter)."""
    ransac_max_error_px: float = 4.0
    """Geometric verification: largest epipolar error (pixels) of an inlier match."""
    min_num_inliers: int = 15
    """Geometric verification: a pair with fewer inlier matches is dropped."""
    max_reproj_error_px: float = 4.0
    """Triangulation: observations reprojecting farther than this (pixels) are dropped from their
    track, and points left with fewer than two observations are removed."""
    min_tri_angle_deg: float = 1.5
    """Triangulation: points whose rays meet at a smaller angle (degrees) are removed (poorly
    conditioned depth)."""
    two_view_tracks: bool = True
    """Also triangulate features matched in only two key frames (COLMAP skips them by default). With
    the poses known they are reliable enough, and they keep sparsely overlapping key frames (fast
    turns) in the model."""
    min_track_length: int = 2
    """Points seen in fewer key frames than this are removed after triangulation (>= 2)."""
    num_threads: int = 1
    """Threads for triangulation (-1 = all cores). With more than one thread COLMAP's results
    depend on thread timing (point ids: the model differs byte for byte from run to run, its point
    count by a few); 1 makes runs bitwise repeatable (BENCHMARKS.md, issue 20)."""
    feature_threads: int = 2
    """Threads for SIFT extraction and matching (-1 = all cores). The database is the same for any
    number: the images are registered in their order before extraction (COLMAP would number them
    as its threads finish) and the file is rewritten in key order after matching."""
    seed: int = 0
    """Seed of COLMAP's random generator (RANSAC), so that runs repeat exactly."""
    refine_poses: bool = True
    """Correct the capture's VIO drift in the key frames before the final triangulation: a bundle
    adjustment with the VIO's relative motion between consecutive key frames as a prior and the
    first key frame fixed (:mod:`embodmocap.scene.adjust`), used only when the evidence below
    holds; the points are then triangulated again with the corrected poses held fixed, and Stage I
    fuses its mesh with the same correction (interpolated between key frames). Needs the key
    frames' times (``times_s``) and at least 4 key frames."""
    drift_m_per_10s: float = 0.01
    """``refine_poses``: spread of the VIO's translation drift after 10 s, metres (a random walk:
    it grows as the square root of time). Phones' VIO drifts about 1 cm over 10 s indoors."""
    drift_deg_per_10s: float = 0.1
    """``refine_poses``: spread of the VIO's yaw drift after 10 s, degrees."""
    tilt_ratio: float = 0.25
    """``refine_poses``: drift of roll and pitch relative to yaw (gravity keeps the tilt)."""
    anchor_m: float = 0.0005
    """``refine_poses``: how far the first key frame may move, metres: it sets the world (the VIO
    world is defined at the capture's start, where it has not drifted yet)."""
    anchor_deg: float = 0.005
    """``refine_poses``: how far the first key frame may turn, degrees."""
    reproj_sigma_px: float = 1.0
    """``refine_poses``: spread of a SIFT keypoint's position, pixels (weight of the images against
    the VIO prior); residuals beyond twice it count linearly (Huber)."""
    adjust_max_iterations: int = 50
    """``refine_poses``: at most this many evaluations of the least-squares solver."""
    min_adjust_gain: float = 0.01
    """``refine_poses``: the correction is used only when it lowers the RMS reprojection error of
    the model by at least this fraction (else the images do not ask for one)."""
    max_prior_step: float = 4.0
    """``refine_poses``: ... and when no step of the correction between consecutive key frames is
    larger than this many times the drift the VIO reaches in their time apart (a Gaussian random
    walk almost never steps 4 sigma): a larger one is a tracking glitch or wrong matches, not
    drift, and the adjustment smears it over its neighbours."""
    max_pose_change_m: float = 0.05
    """``refine_poses``: ... and when no key frame moves further than this, metres."""


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
    voxel_m_indoor: float = 0.02
    """Indoor TSDF voxel size, metres. 2 cm like outdoors, not the release's 1 cm: the LiDAR's
    256x192 depth samples the surface about 1 cm apart at 2 m and coarser beyond, so 1 cm voxels
    mostly fit its noise (on the studio's 15 s scan: 6x the faces, mean distance to the true
    surface 1.73 cm vs 0.56 cm, the same completeness), and the mesh's cost (fusion, extraction,
    clean-up, floor, simplification) falls with the voxel count (Stage I's CPU about halves)."""
    voxel_m_outdoor: float = 0.02
    """Outdoor TSDF voxel size, metres."""
    sdf_trunc_voxels: float = 5.0
    """TSDF truncation distance in voxels (5 voxels = 10 cm, the release's ``sdf_trunc`` 0.1). It
    must exceed the depth noise (LiDAR: ~1 % of the depth) or surfaces get holes; larger values
    round corners."""
    integrate_every: int = 1
    """Integrate every k-th fusion frame (1 = all); >1 trades completeness for speed."""
    fusion_threads: int = 1
    """OpenMP threads of Open3D's TSDF integration (0 = one per core). The mesh is the same for
    any number; 1 (default) lets the frame reader have the second core and keeps a busy machine's
    cores from spinning in OpenMP's waits (10-20x the CPU time at a load of 20 on 2 cores)."""
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
            (self.fusion_threads >= 0, "fusion_threads must be >= 0"),
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
