"""Stage III settings: :class:`CalibrateConfig` (the ``[calibrate]`` table and ``embodmocap calibrate``'s
options; also importable from :mod:`embodmocap.calibrate.stage`) and the joint refinement's
:class:`RefineConfig` (also importable from :mod:`embodmocap.calibrate.refine`).

This module imports no solver code (no torch), so the command line can build its options from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from embodmocap.calibrate.offset import RobustOffsetConfig
from embodmocap.sequence.geosync import GeoSyncConfig


Solver = Literal["adam", "lm", "both"]


@dataclass(frozen=True)
class RegisterConfig:
    """Settings of view-frame registration. Defaults register 2 x 200 frames at 640x480 in about a
    minute on 2 CPU cores."""

    num_frames: int = 24
    """Frames sampled per view by :func:`select_frames`: spread over time and over viewpoints
    (the VIO path and turn), the steadiest frame of each stretch (least blur). A 6 s view has
    about 175 frames, a 60 s one 1,800. The offset has 4 parameters and the per-view error is
    dominated by a bias common to the view's frames, not by their number (the VIO chain ties the
    frames between): beyond ~24 well spread frames more only cost time (SIFT and matching are most
    of Stage III's time; 80 until issue 30, 40 until session 14: camera centres on the 10 hard
    studio seeds median 0.92 / p95 1.61 cm with 24 against 0.93 / 1.58 with 40)."""
    workers: int = 0
    """Threads registering frames in parallel (0 = one per CPU core). OpenCV and pycolmap release
    the GIL; each frame's result does not depend on the thread count or order."""
    coarse_frames: int = 16
    """Frames registered first by retrieval (24 until issue 30); their VIO-consistent poses give a coarse offset from
    which the other frames get their candidate key frames by pose (:func:`pose_candidates`)."""
    max_features: int = 2048
    """SIFT features kept per query frame (the strongest)."""
    contrast_threshold: float = 0.03
    """OpenCV SIFT contrast threshold (lower = more, weaker features; OpenCV's default is 0.04)."""
    mask_dilation_px: int = 10
    """The person mask is grown by this many pixels before features are excluded, so that no
    descriptor window reaches into the performer."""
    num_candidates: int = 8
    """Scene key frames each query frame is matched against."""
    candidates: Literal["auto", "retrieval", "pose"] = "auto"
    """How candidate key frames are chosen: ``"retrieval"`` = most similar bag of visual words;
    ``"pose"`` = key frames whose view overlaps the query's predicted view (needs predicted poses);
    ``"auto"`` = pose where a prediction is given, retrieval elsewhere."""
    vocabulary_size: int = 256
    """Visual words of the retrieval vocabulary (k-means over the key frames' descriptors)."""
    vocabulary_samples: int = 20000
    """At most this many key frame descriptors (random) train the vocabulary."""
    max_view_angle_deg: float = 75.0
    """``"pose"`` candidates: key frames whose optical axis differs from the predicted one by more
    than this are never candidates."""
    pose_probe_depths_m: tuple[float, ...] = (1.5, 3.0, 5.0)
    """``"pose"`` candidates: depths (metres) of the probe points cast from the predicted camera
    (:func:`pose_overlap`); room scale by default."""
    ratio: float = 0.8
    """Lowe's ratio test: a match is kept when its distance is below ``ratio`` x the second best."""
    ransac_max_error_px: float = 6.0
    """Absolute pose RANSAC: largest reprojection error (pixels) of an inlier."""
    min_inliers: int = 20
    """A frame with fewer pose inliers counts as not registered."""
    min_inlier_ratio: float = 0.1
    """RANSAC's lowest accepted inlier share of the matches (COLMAP's option)."""
    seed: int = 0
    """Seed of the vocabulary's k-means and of RANSAC, so that runs repeat exactly."""


@dataclass(frozen=True)
class RefineConfig:
    """Settings of the joint refinement."""

    w_track: float = 2.0
    """Weight of the cross-view track term (the release weights it 2x the per-view terms)."""
    w_chamfer: float = 1.0
    """Weight of each view's Chamfer (view -> scene) term."""
    w_reproj: float = 1.0
    """Weight of each view's reprojection term."""
    track_phase: bool = True
    """Let the track term fit the views' sub-frame phase: view b's points are compared with view a's
    moved by the performer's motion over a fitted fraction of a frame (one parameter; the motion
    from the same keypoint about 5 frames before and after). Two phones film a fraction of a frame
    apart; without it the term reads the performer's motion over that fraction as an offset of
    view b and pulls the cameras by it. Not with ``presync`` (its pairs are already on one clock).
    On issue 29's 10 hard random-phase seeds it meets the camera-centre targets (median / p95 /
    worst 1.06 / 1.75 / 1.76 -> 0.93 / 1.58 / 1.66 cm; outdoor_5's view 2 1.76 -> 0.80) with WA /
    PA / RTE unchanged; with Stage IV's arm depth points (``depth_points.arm_other_max_conf``) the
    W c100 median / worst are 28.3 / 38.2 mm (without them, 32.5 / 42.9: Stage IV's first frames
    swung with the cameras; history 2026-12-06-s13-cams.md and -coord.md)."""
    track_kernel: str = "huber"
    """Robust kernel of the track term: "l2", "huber" or "geman_mcclure"."""
    track_scale_m: float = 0.05
    """Robust scale of the track term, metres (keypoint noise plus joint-vs-surface mismatch)."""
    chamfer_max_distance_m: float = 0.5
    """Background points farther than this from every scene sample are left out of the Chamfer
    term (objects the mesh lacks, mesh holes); the initial offset must be better than this."""
    chamfer_kernel: str = "huber"
    """Robust kernel of the Chamfer term."""
    chamfer_scale_m: float = 0.03
    """Robust scale of the Chamfer term, metres (LiDAR noise plus mesh error)."""
    reproj_kernel: str = "huber"
    """Robust kernel of the reprojection term."""
    reproj_scale_px: float = 3.0
    """Robust scale of the reprojection term, pixels."""
    solver: Solver = "lm"
    """Which solver(s) to run: "adam", "lm" or "both" (keeps the lower final loss). LM by default:
    on the benchmark seeds it ends within 0.01 % of Adam's loss (or below it) in 10-20 iterations,
    where Adam takes 200 and costs about as much again."""
    adam_lr: float = 1e-2
    """Adam's initial learning rate (the release's value)."""
    adam_lr_final: float = 1e-4
    """Learning rate reached at the last iteration by cosine decay (= adam_lr: constant)."""
    adam_iterations: int = 200
    """Adam iterations (the release's value)."""
    adam_clip_norm: float = 1.0
    """Gradient-norm clipping of Adam's steps (the paper's clipping); <= 0 disables it."""
    chamfer_refresh: int = 5
    """Adam re-finds the Chamfer nearest neighbours every this many iterations."""
    lm_iterations: int = 30
    """Maximum Levenberg-Marquardt iterations."""
    lm_damping: float = 1e-3
    """Initial LM damping (multiplies diag(J^T J)); divided by 10 on success, times 10 on failure."""
    lm_step_tol: float = 1e-6
    """LM stops when the step's largest component is below this (radians / metres). 1e-9 until
    issue 30: the steps below a micrometre (its last 10-20 iterations, each a Jacobian and fresh
    Chamfer neighbours) moved the offsets by less than 1e-6 m."""
    max_translation_m: float = 0.5
    """A translation change larger than this is flagged as diverged, metres."""
    max_yaw_deg: float = 10.0
    """A yaw change larger than this is flagged as diverged, degrees."""
    drift_knot_frames: int = 45
    """Slow VIO drift: the correction of each view is a piecewise-linear function of the frame,
    with a knot every this many frames (45 = 1.5 s at 30 fps; a view shorter than two spacings, or
    0, gets one rigid yaw + translation, the refinement before drift). A handheld VIO track errs
    with the path walked (a scale error, drift of a per cent or two of the path), which no single
    offset fits at every frame."""
    drift_sigma_m: float = 0.2
    """Smoothness prior of the drift knots: neighbouring knots' translations differ by about this
    much, metres, in the units of the normalised objective (larger = freer drift)."""
    drift_sigma_deg: float = 2.0
    """Smoothness prior of the drift knots' yaw, degrees (as ``drift_sigma_m``)."""
    w_drift: float = 1.0
    """Weight of the drift smoothness prior (mean over each view's neighbouring knot pairs)."""
    inlier_ratio: float = 3.0
    """A residual counts as an inlier when its norm is below this many robust scales."""
    min_inlier_fraction: float = 0.75
    """After refinement, a term with fewer inliers than this gets a warning: the terms disagree
    (one pulls the view away from where another wants it) or that term's data are bad."""


@dataclass(frozen=True)
class CalibrateConfig:
    """How Stage III registers and refines the two views."""

    register: RegisterConfig = field(default_factory=RegisterConfig)
    """Registration of view frames into the scene's sparse model."""
    offset: RobustOffsetConfig = field(default_factory=RobustOffsetConfig)
    """Robust yaw-only fit of the initial offset."""
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Joint refinement (losses, weights, solvers)."""
    refine_views: bool = True
    """Run the joint refinement (False = keep the registration-only offsets)."""
    retry_below_fraction: float = 0.5
    """A view registering fewer of its sampled frames than this is registered again against
    ``retry_candidates_factor`` times more candidate key frames."""
    retry_candidates_factor: int = 3
    """How many times more candidate key frames the retry matches against."""
    min_registered_fraction: float = 0.2
    """Fewer registered frames than this fraction of those tried is an error for the view."""
    vio_max_disagreement_m: float = 0.10
    """VIO check (:mod:`embodmocap.calibrate.consistency`): two registered frames whose relative
    motion differs from the VIO's by more than this (metres) disagree."""
    vio_max_disagreement_deg: float = 3.0
    """VIO check: the rotation limit of the same test, degrees."""
    min_consistent_fraction: float = 0.25
    """A view whose largest VIO-consistent group of registered frames holds fewer than this share
    of them (or fewer than ``min_registered_frames``) disagrees with its VIO everywhere: an error
    (the wrong scene capture, most likely)."""
    min_registered_frames: int = 5
    """Fewer registered frames than this is an error for the view."""
    place_by_performer: bool = True
    """A view whose registered frames disagree with its VIO (too little texture, other light) while
    the other view registers is placed through the performer both film: its keypoints, back-projected
    with depth, are fitted onto the other view's (yaw + translation), and the placement is kept
    only if the view's background depth then lies on the scene mesh (``performer_min_on_mesh``);
    otherwise (the wrong scene, most likely) the view's error stands."""
    performer_min_on_mesh: float = 0.8
    """A performer-placed view's share of background depth points within ``performer_on_mesh_m``
    of the scene mesh must reach this fraction of the registered view's own share."""
    performer_on_mesh_m: float = 0.10
    """Distance to the scene mesh within which a background point counts as on it, metres."""
    max_refine_shift_m: float = 0.15
    """A refinement moving a view further than this from its registration offset is warned about."""
    max_refine_yaw_deg: float = 3.0
    """A refinement turning a view more than this from its registration offset is warned about."""
    chamfer_frames: int = 30
    """Frames per view whose background depth feeds the Chamfer term (evenly spread)."""
    chamfer_points_per_frame: int = 400
    """Background points per frame for the Chamfer term."""
    scene_points: int = 50000
    """Points sampled on the scene mesh for the Chamfer term."""
    track_frames: int = 300
    """At most this many sequence frames (evenly spread) give the cross-view track term its
    keypoint pairs (a 6 s sequence uses all its frames; a 60 s one 1 in 6: the term fixes 8
    parameters, and each frame read costs two depth maps)."""
    presync: bool = False
    """Before the refinement, measure the sub-frame sync on the registration-only cameras (the
    geometric sync and the choice of step 4, :mod:`embodmocap.calibrate.presync`) and pair the
    cross-view track term's points at view 1's instants by it (view 2's interpolated between its
    two nearest frames). Without it the track term pairs the same sequence frame of both views, and
    a phone filming a fraction of a frame off the other pulls view 2 towards "in phase" (by the
    performer's motion over that fraction), which the sync measured afterwards partly takes for
    the truth. Step 4 measures the sync again (what is applied) on the cameras ``sync_cameras`` names.
    Off by default: on the 10 random-phase hard seeds (2026-12-05-s11-phase) it, with
    ``sync_cameras = "registration"``, cut the sub-frame error where the geometry was chosen
    (0.385 / 0.232 / 0.222 -> 0.001 / 0.071 / 0.019 frame) but left WA / PA 0.1-0.7 mm worse on
    two seeds and W-MPJPE swinging both ways (one seed 32 -> 61 mm)."""
    presync_max_frames: float = 1.0
    """The sub-frame sync before the refinement is applied to the track pairs only when within
    this many frames of the slicing (a farther choice is another integer offset: step 4's call)."""
    sync_cameras: Literal["refined", "registration"] = "refined"
    """The cameras on which step 4 measures the geometric sync: the refined ones (drift included),
    or the registration-only ones (before the refinement, which the performer's keypoints took part
    in: with a sub-frame phase they are pulled towards it; the sync measured on them is
    independent of the track term). The world cameras written are the refined ones either way.
    ``refined`` by default (see ``presync``, with which ``registration`` was measured)."""
    geosync: GeoSyncConfig = field(default_factory=GeoSyncConfig)
    """Geometric sync after registration (keypoint rays meeting) and the choice of sync source."""
