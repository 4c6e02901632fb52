"""Settings of the monocular pipeline (``embodmocap mono``): one frozen dataclass per part, every
field documented (tyro turns them into the command's options). No heavy import here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

SceneModelName = Literal["colmap", "precomputed", "vio"]
"""Scene/camera role backends: ``colmap`` runs structure from motion (pycolmap, CPU) on each
chunk's frames (up to scale; runs on any machine); ``precomputed`` reads one npz per chunk in Pi3's
output layout (bring Pi3, VGGT or MASt3R output); ``vio`` uses the phone's own metric poses and LiDAR depth as
point maps (an ablation: what a perfect scene model would give)."""
HumanModelName = Literal["precomputed", "prior"]
"""Human role backends: ``precomputed`` reads a camera-space SMPL npz (VIMO / TRAM / GVHMR output);
``prior`` reads Stage II's ``<view>/body_prior.npz``."""


@dataclass(frozen=True)
class StitchConfig:
    """How chunks are aligned to each other (weighted Umeyama on the overlap)."""

    points_per_frame: int = 1500
    """Point-map pixels sampled per overlapping frame for the alignment (a regular grid, then
    those with confidence); more is slower and barely more accurate."""
    min_conf: float = 0.1
    """Point-map pixels whose confidence (in either chunk) is below this are not used."""
    centre_weight: float = 0.2
    """Share of the total weight given to the overlapping frames' camera centres (the rest to the
    points): they pin the path where the points are few."""
    robust_iterations: int = 4
    """Cauchy re-weighting rounds of the alignment (0 = plain weighted Umeyama)."""
    symmetric_scale: bool = True
    """Take each alignment's scale as the ratio of the overlap's weighted spreads in the two
    chunks (rotation from Umeyama) instead of Umeyama's least-squares scale, which noise in the
    new chunk's points biases low; the bias compounds chunk after chunk (a 60 s studio view with
    Pi3-like noise: the local scale drifted from -1.4 % to +1.2 % of the global one)."""
    min_overlap_frames: int = 2
    """Fewer overlapping frames than this cannot be aligned: a new segment starts."""
    min_points: int = 50
    """Fewer usable overlap points than this cannot be aligned: a new segment starts."""
    max_rel_residual: float = 0.1
    """An alignment whose weighted median point residual exceeds this fraction of the median
    point distance from the cameras is refused: a new segment starts (never a silent jump)."""


@dataclass(frozen=True)
class ColmapSceneConfig:
    """The ``colmap`` scene model: SfM per chunk (:mod:`embodmocap.mono.colmap_scene`)."""

    stride: int = 4
    """Every n-th sequence frame (by frame number, so overlapping chunks share them) goes into SfM;
    the poses of the others are interpolated."""
    image_width: int = 320
    """Frames are downscaled to at most this width for SfM (the intrinsics with them)."""
    max_features: int = 1024
    """SIFT features kept per image."""
    mask_dilate_px: int = 4
    """The person mask is grown by this many pixels (at the SfM image size) before it masks SIFT."""
    seq_neighbours: int = 8
    """Sequential matching: each image is matched with this many following ones."""
    init_min_tri_angle_deg: float = 4.0
    """Smallest triangulation angle of SfM's initial pair (COLMAP's 16 deg default suits photo
    collections, not a 2 s chunk of video)."""
    min_tri_angle_deg: float = 0.5
    """Points whose rays meet at a smaller angle are dropped (COLMAP: 1.5 deg; a chunk of video
    that mostly turns has little parallax, and at 1.5 deg too few points remain to register the
    next image)."""
    init_min_inliers: int = 50
    """Fewest verified matches of SfM's initial pair (COLMAP: 100; 1024 features at 320 px give fewer)."""
    retry_denser: bool = True
    """A chunk SfM failed on is tried again with half the stride (down to every frame) before it
    is declared failed (costs only on such chunks)."""
    min_registered: float = 0.5
    """A chunk where SfM registers fewer than this share of its images has failed: a new segment."""
    min_points: int = 100
    """A chunk with fewer triangulated points has failed: a new segment."""
    map_width: int = 64
    """Width of the sparse point maps (height from the aspect ratio)."""
    num_threads: int = 1
    """Threads of COLMAP's extraction, matching and mapping (-1 = all cores)."""
    seed: int = 0
    """Seed of COLMAP's random generator, so runs repeat."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        if self.stride < 1 or self.image_width < 32 or self.map_width < 4:
            raise InputError(None, f"colmap settings stride {self.stride}, image width {self.image_width}, map width "
                             f"{self.map_width}", "need stride >= 1, image width >= 32, map width >= 4")


@dataclass(frozen=True)
class FeetScaleConfig:
    """The metric scale from the feet on the floor (:mod:`embodmocap.mono.feet`), used where the
    scene model has no points on the person (``colmap``)."""

    max_speed: float = 0.5
    """A foot moving slower than this (m/s, in the provisional metric world) can be in contact. Not
    tighter: a regressor's depth error moves a planted foot along the ray from frame to frame (10 %
    depth error changing over 0.5 s at 3 m is ~0.6 m/s), and a tight bound leaves few frames."""
    max_height: float = 0.08
    """... and no higher than this above the floor plane (metres, provisional scale)."""
    min_down_cos: float = 0.15
    """The foot's pixel ray must point down onto the floor at least this much (cosine between the
    ray and the floor's downward normal): grazing rays give unstable intersections."""
    plane_inlier_rel: float = 0.01
    """Floor plane RANSAC inlier band, as a share of the median camera-to-point distance (the
    stitched points have no metric scale yet)."""
    iterations: int = 3
    """Rounds of (scale -> contact frames -> scale)."""
    min_frames: int = 10
    """Fewer contact frames than this: no metric scale from the feet."""


@dataclass(frozen=True)
class ScaleConfig:
    """How the metric scale comes from the body (median of body depth / point-map depth)."""

    erode_px: int = 0
    """Point-map pixels this close to the body's rendered silhouette edge are left out. 0 by
    default: ``max_edge_rel`` already drops pixels on depth edges (where a model's point mixes
    person and background), and at a low map resolution an erosion leaves a body drawn too far
    (small) no pixel, so such frames stopped voting and biased the scale low (3.40 -> 2.97 % on a
    20 s studio view whose prior alone is 2.7 % off)."""
    min_conf: float = 0.3
    """Point-map pixels below this confidence are not sampled."""
    max_edge_rel: float = 0.05
    """A pixel whose 3x3 point-map depths spread more than this fraction of its depth is on a depth
    edge (person against background, an object in front) and is left out."""
    min_frame_samples: int = 10
    """A frame whose person mask covers fewer point-map pixels than this does not vote."""
    min_samples: int = 50
    """Fewer (pixel, frame) samples in a segment than this: no metric scale from the body's depth
    (the feet are tried next with ``cue = auto`` and used alone with ``combined``; without either the segment stays in the model's
    units, its frames flagged invalid)."""
    cue: Literal["auto", "body", "feet", "combined"] = "combined"
    """Metric cue: ``body`` (body depth / point-map depth inside the person mask, the paper's: needs
    points on the person, as Pi3-like dense maps have), ``feet`` (the body's feet in contact
    against the scene's floor plane: works with sparse SfM), ``auto`` = ``body`` where it has
    ``min_samples``, else ``feet``; ``combined`` (the default) = both where each has enough
    samples, averaged (in log scale) with weights ``1 / se_rel^2`` from each cue's own block
    standard error: the only cue within 2 % on all eleven studio views measured with the
    realistic prior and the keypoint depth refinement (six used to develop it, five held out;
    body 2.07 % on the 60 s one, feet 2.27 % on a held-out one; BENCHMARKS.md, session 6)."""
    block_s: float = 2.0
    """Block length (seconds) of the scale's standard error ``se_rel``: the per-frame votes are
    grouped into blocks this long, longer than the regressor's error correlation (its depth error
    drifts over ~0.5 s), and the blocks' medians spread gives the error of their median."""
    feet: FeetScaleConfig = field(default_factory=FeetScaleConfig)
    """Settings of the feet cue."""
    height_m: float | None = None
    """The performer's real height (rest-pose stature, metres), if the user knows it: the
    sequence's one shape is moved along the shape direction that changes stature (the smallest
    change) until its height matches, before the depth refinement. The body's size is what no
    image shows (a regressor that thinks the person 3 % smaller places them 3 % nearer), so this
    is the one input that corrects the metric scale's remaining error. None = the model's shape."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        if self.height_m is not None and not 0.5 <= self.height_m <= 2.5:
            raise InputError(None, f"--scale.height-m {self.height_m}: not a person's height in metres",
                             "give the performer's height in metres, e.g. --scale.height-m 1.78")


@dataclass(frozen=True)
class DepthRefineConfig:
    """The camera-space body's translation refined against Stage II's 2D keypoints
    (:mod:`embodmocap.mono.refine`)."""

    min_conf: float = 0.3
    """Keypoints below this confidence are not used."""
    min_keypoints: int = 6
    """A frame with fewer usable keypoints keeps an interpolated correction (not solved)."""
    iterations: int = 10
    """Gauss-Newton / Cauchy re-weighting rounds per frame."""
    cauchy_rel: float = 0.05
    """Cauchy scale of the reprojection error, as a share of the person's size in the image: a
    joint whose pose the regressor got wrong, or a detector outlier, weighs little beyond it."""
    max_factor: float = 1.5
    """A frame whose solved depth is more than this factor away from the model's (either way) is
    not trusted (interpolated from its neighbours)."""
    median_frames: int = 5
    """Median filter (frames) over the solved corrections before the smoothing (outlier frames)."""
    smooth_s: float = 0.1
    """Gaussian smoothing (sigma, seconds) of the corrections over time: the solve's noise is
    frame to frame, a regressor's depth error drifts over ~0.5 s."""


@dataclass(frozen=True)
class MonoConfig:
    """The monocular pipeline: one view's video -> cameras, scene points and SMPL in a metric world."""

    scene_model: SceneModelName = "colmap"
    """Scene/camera model: ``colmap`` (SfM per chunk on the video, CPU, up to scale; the default:
    runs on any machine), ``precomputed`` (npz per chunk, Pi3 layout, in
    ``perception/<seq>/<view>/mono_scene/``) or ``vio`` (the phone's poses and depth; ablation)."""
    human_model: HumanModelName = "prior"
    """Camera-space body: ``prior`` (Stage II's body prior) or ``precomputed``
    (``perception/<seq>/<view>/mono_human.npz``)."""
    human_depth: Literal["keypoints", "model"] = "keypoints"
    """Where the body's per-frame translation (its depth above all) comes from: ``keypoints``
    (one shape for the sequence, each frame's translation refined so the body's joints reproject
    onto Stage II's 2D keypoints, ``<view>/keypoints2d.npz``; without that file the model's depth
    is used, with a warning) or ``model`` (the human model's own translation, as it is). The
    refined body feeds the metric scale and ``smpl_world.npz``."""
    depth_refine: DepthRefineConfig = field(default_factory=DepthRefineConfig)
    """Settings of ``--human-depth keypoints``."""
    chunk: int = 64
    """Frames per chunk given to the scene model."""
    overlap: int = 16
    """Frames shared by consecutive chunks (what the alignment uses); < chunk."""
    gravity: Literal["auto", "vio", "plane"] = "auto"
    """Where Z-up comes from: ``vio`` (the phone's gravity-aligned poses), ``plane`` (the scene
    points' dominant plane near the cameras' mean down direction), ``auto`` = ``vio`` when Stage II
    has tracked VIO poses, else ``plane``."""
    ply_points: int = 200_000
    """At most this many coloured points in ``points.ply``."""
    ply_frame_stride: int = 8
    """Every n-th frame contributes points (and decodes its RGB frame) to ``points.ply``."""
    stitch: StitchConfig = field(default_factory=StitchConfig)
    """Chunk alignment settings."""
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    """Metric scale settings."""
    colmap: ColmapSceneConfig = field(default_factory=ColmapSceneConfig)
    """``--scene-model colmap`` settings."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        if self.chunk < 2 or not 0 <= self.overlap < self.chunk:
            raise InputError(None, f"--chunk {self.chunk} --overlap {self.overlap}: need chunk >= 2 and 0 <= overlap < chunk",
                             "pick e.g. --chunk 64 --overlap 16")
