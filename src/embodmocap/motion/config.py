"""Stage IV settings: :class:`MotionConfig` (the ``[motion]`` table and ``embodmocap motion``'s options; also
importable from :mod:`embodmocap.motion.stage`), :class:`SmplifyConfig` (also from
:mod:`embodmocap.motion.smplify`) and :class:`ContactConfig` (also from :mod:`embodmocap.motion.contact`).

This module imports no solver code (no torch), so the command line can build its options from it."""

from __future__ import annotations

from dataclasses import dataclass, field

from embodmocap.geometry.triangulation import TriangulationConfig
from embodmocap.motion.label_track import LabelTrackConfig
from embodmocap.motion.depth_points import DepthPointsConfig
from embodmocap.motion.leg_sides import LegSidesConfig
from embodmocap.motion.lift import LiftConfig
from embodmocap.motion.quality import QualityConfig
from embodmocap.motion.temporal import TemporalConfig


#: Lowest 2D confidence that Stage IV triangulates. A weak detection is usually a joint the
#: detector half sees (occluded, blurred), roughly in place: on the ten hard studio sessions
#: detections at confidence 0.1-0.3 were 19 px off (median), 1 % more than 60 px, like those at
#: 0.3-0.5 (21 px, 14 % > 60 px), while the blunders sit below 0.05 (391 px median). Leaving
#: them out left knees and ankles seen well by one view and weakly by the other untriangulated,
#: their depth free along the first view's ray (knees 150-290 mm off over 30 frames in seed 6);
#: the bone-length gate, the swap checks and the robust 3D term still judge every point.
TRIANGULATION_MIN_CONF = 0.1


@dataclass(frozen=True)
class SmplifyConfig:
    """Weights, schedules and robust scales of the world-space SMPLify."""

    w_kp3d: float = 0.25
    """Weight of the 3D keypoint term (robust, dimensionless). A quarter of the two views'
    reprojection weights together: a triangulated point fuses both views, so one view's wrong
    detection moves it (with two views, along the other view's ray, unseen), while each view's
    robust 2D term writes off that view's blunder alone. Measured on ten hard studio sessions
    without a prior (BENCHMARKS.md, issue 11, second pass): 1.0 -> 0.25 (with ``w_kp3d_start``)
    took the median PA-MPJPE from 39.9 to 36.2 mm and RTE from 1.44 to 1.25 %, the clean session's
    PA-MPJPE from 16.9 to 14.2 mm."""
    w_kp3d_start: float = 1.0
    """Weight of the 3D keypoint term in phase 1 and at the start of phase 2, from where it shrinks
    geometrically to ``w_kp3d`` over the first ``gnc_fraction`` of phase 2: from a start far off
    (a perturbed start, each window of a long sequence) the 3D points pull hardest, and the windows
    converge alike (no seam); the end balance is ``w_kp3d``'s. With ``w_kp3d`` 0 there is no 3D
    term in any phase."""
    w_reproj: float = 0.5
    """Weight of the reprojection term of each view (robust, dimensionless)."""
    w_joint_vel: float = 0.0
    """Weight of the joint velocity term (per m^2 of frame-to-frame joint displacement). Off by
    default: it biases every real movement towards standing still; acceleration smooths without
    that bias."""
    w_joint_acc: float = 30.0
    """Weight of the joint acceleration term (per m^2 of second difference per frame^2). 45 lowered
    WA/PA on the hard studio seeds by about 1 mm but moved W-MPJPE c100 by -6..+11 mm per seed
    (its two anchor frames) and slowed a plain noisy-keypoint fit from the IK start (tests/
    test_motion_ik.py: 19.3 -> 22.5 mm at 150 phase-2 steps): kept at 30
    (benchmarks/history/2026-12-06-s12-yaw.md)."""
    w_transl_vel: float = 0.0
    """Weight of the translation velocity term (per m^2)."""
    w_transl_acc: float = 30.0
    """Weight of the translation acceleration term (per m^2)."""
    w_edge_vel: float = 100.0
    """Weight of the edge velocity term (per m^2 of frame-to-frame displacement of the joints
    relative to the pelvis, mean over joints and over all of the sequence's frame differences,
    those outside the edges counting 0): applied only over the first and last ``edge_frames``
    frames of each run of frames where the body can be placed (the sequence's ends, the frames
    next to unplaceable ones; :func:`embodmocap.motion.terms.edge_weights`). Inside a run a limb that the
    keypoints do not pin (seen in one view only, or triangulated wrong) is held by the
    acceleration term between well-seen neighbours on both sides; at an end there is a neighbour
    on one side only, and an acceleration term lets such a limb drift at constant velocity (a
    straight-line extrapolation) into the first frames. This term makes that drift cost: the
    limb's articulation holds still beyond the frames that pin it, while the body itself (the
    pelvis) moves freely. 0 = off. Measured on the ten hard studio sessions without a prior
    (BENCHMARKS.md, issue 11, fourth pass): the first frames of a sequence (the ones W-MPJPE's
    alignment uses) had an arm or leg 100-350 mm off, turning the whole chunk by 4-17 degrees;
    a weight of 300 or more freezes real movement at the start (worse). Per joint and frame it
    holds only what no detection pins (:func:`embodmocap.motion.terms.edge_hold_weights`): a
    joint no view sees entirely, one a single view sees along that view's ray, one both views see
    not at all (fifth pass: holding everything froze the walking legs of the hard outdoor session
    at its first placeable frames, after 32 frames in which only view 2 saw the body: W-MPJPE 65
    mm, 26 without the term)."""
    edge_hold: str = "unseen"
    """What ``w_edge_vel`` holds still: ``unseen`` (per joint and frame, what no detection pins:
    see above) or ``all`` (every joint's whole articulation: the fourth pass)."""
    edge_frames: int = 10
    """Frames at each edge of a run of placeable frames covered by ``w_edge_vel``."""
    w_pose_prior: float = 0.01
    """Weight of the pull towards the prior body pose (per rad^2 summed over the 69 angles);
    used only when a prior pose is given."""
    w_joint_limits: float = 1.0
    """Weight of the one-way hinge term for knees and elbows (per rad^2)."""
    w_rest_pose: float = 0.01
    """Without a prior pose: weight of a pull of the joints that no keypoint pins (feet, wrists,
    hands, collars, neck, head) towards SMPL's neutral pose (per rad^2 summed over them), so that
    what the keypoints cannot see stays plausible instead of drifting."""
    rest_pose_ankles: bool = False
    """Also pull the ankles (SMPL 7, 8) towards neutral without a prior: COCO-17 has no foot
    keypoint, so nothing else pins the foot's angle to the shin."""
    w_joint_range: float = 1.0
    """Weight of the per-axis anatomical ranges of every joint (per rad^2 outside the range,
    :data:`embodmocap.motion.terms.ANATOMICAL_RANGES`): the pose prior that ships with the package."""
    w_shape_prior: float = 0.01
    """Weight of the betas L2 prior (per unit of mean squared beta)."""
    w_floor: float = 1000.0
    """Weight of the floor term (per m^2 of a foot joint below its lowest height over Stage I's
    floor, :mod:`embodmocap.motion.floor`): a leg that both views lose must not sink its foot
    through the floor. 0 = off (the fit does not read the scene mesh)."""
    floor_max_tilt_deg: float = 3.0
    """Stage I's floor is used only when it is within this of horizontal (a tilted floor means
    wrong gravity or a sloping ground, where one plane would push feet up wrongly)."""
    kp3d_kernel: str = "geman_mcclure"
    """Robust kernel of the 3D term: ``l2``, ``huber`` or ``geman_mcclure``."""
    kp3d_scale_m: float = 0.05
    """Robust scale of the 3D term, metres (a triangulation error of a few cm is normal; a
    mis-triangulated point 20 cm off stops pulling)."""
    reproj_kernel: str = "geman_mcclure"
    """Robust kernel of the reprojection term."""
    reproj_scale_px: float = 20.0
    """Robust scale of the reprojection term, pixels."""
    gnc_factor: float = 1.0
    """Graduated non-convexity of phase 2: its 3D and 2D robust scales start this many times larger
    (the terms multiplied by its square, so small residuals weigh the same) and shrink
    geometrically to their set values over the first ``gnc_fraction`` of its iterations. From a
    start with a limb far from its keypoints (a wrong early triangulation, a limb seen in one view
    only), every keypoint pulls at first instead of being written off as an outlier; 1 = off."""
    gnc_fraction: float = 0.5
    """Share of phase 2's iterations over which the robust scales shrink (``gnc_factor``) and the
    3D weight goes from ``w_kp3d_start`` to ``w_kp3d``."""
    min_conf: float = 0.1
    """Keypoints (3D and 2D) with confidence below this are ignored."""
    solver: str = "adam"
    """``adam`` or ``lbfgs`` (torch's L-BFGS with strong-Wolfe line search)."""
    phase1_iterations: int = 60
    """Iterations of phase 1 (Adam steps, or L-BFGS outer iterations)."""
    phase1_lr: float = 0.03
    """Adam learning rate of phase 1 (radians / metres / beta units per step at the start)."""
    torso_iterations: int = 0
    """Iterations of the torso stage (between phase 1 and the limbs); 0 = skipped. Off by default:
    after the keypoint start (whose own steps are global, torso, limbs) it changed nothing on the
    hard benchmark, and from a start perturbed everywhere it slowed phase 2's convergence."""
    limbs_iterations: int = 0
    """Iterations of the limbs stage (between the torso and phase 2); 0 = skipped (see above)."""
    stage_pose_lr: float = 0.03
    """Adam learning rate of the pose in the torso and limbs stages."""
    init_smooth_frames: float = 1.0
    """Std (frames) of a Gaussian through time applied to the start's rotations (per joint, as
    quaternions) and translation before the fit, within each run of placeable frames
    (:func:`embodmocap.motion.smplify.smooth_motion`); 0 = off. Why: a start built frame by frame
    from noisy keypoints jitters; the smoothness terms' large gradients at such a start fill Adam's
    second-moment estimates (which remember about 1000 steps) and shrink every later step, so the
    fit converges slowly, the more so the stronger the smoothing. A plain noisy-keypoint fit
    (tests/test_motion_ik.py: 4 s, 2.5 cm noise, 3 % outliers, 150 phase-2 steps; three noise
    draws): 19.3 / 19.6 / 21.5 mm from the truth -> 17.8 / 17.5 / 17.9 with the start smoothed; with
    ``w_joint_acc`` 45: 22.5 -> 17.7 (seed 1). On since session 12 with ``output_smooth_frames``
    (see there for the hard studio seeds)."""
    output_smooth_frames: float = 0.6
    """Std (frames) of a Gaussian through time applied to the fitted rotations and translation
    after the fit, within each run of placeable frames (the frames flagged unplaceable left as
    fitted); 0 = off. The fitted joints keep a frame-to-frame jitter that the keypoints' noise
    drives and the acceleration terms only partly resist (0.7-1.4e-2 rad^2/frame^2 of trunk
    angular acceleration against 1e-4 in the studio's truth); a filter this narrow (half power at
    about 6.6 Hz at 30 fps) removes it and leaves a person's movements alone. Session 12, Stage IV
    in memory on the ten hard studio seeds, both filters on (1 and 0.6) against both off:
    WA-MPJPE median 20.16 -> 18.98 mm and PA 17.47 -> 16.45, lower on all ten seeds; RTE 0.444 ->
    0.434 %, lower on nine; W-MPJPE c100 with a chunk at every start (median per seed) lower on
    nine, median 33.6 -> 31.4; W-MPJPE c100 itself (set by each chunk's first two frames: one
    anchor per seed here) moved -2.3..+3.7 mm per seed, median 30.9 -> 31.7, worst 37.1 -> 34.9;
    first five frames / median frame worst 1.39 -> 1.41. 1.0 lowered WA / PA by another mm but
    raised one seed's W c100 by 10.5 mm (29.6 -> 40.2): benchmarks/history/2026-12-06-s12-yaw.md."""
    phase2_iterations: int = 300
    """Iterations of phase 2 (200 was tried for issue 30: W-MPJPE of one of three sessions 58 ->
    96 mm, so kept at 300)."""
    phase2_stop_tol: float = 3e-4
    """Phase 2 of a window (and of the shape fit) ends early once the window's own loss fell by
    less than this fraction of itself over the last 10 steps, checked once its objective is fixed
    (after the first ``gnc_fraction`` of the iterations); 0 = always ``phase2_iterations``. Each
    window stops on its own loss, so the answer does not depend on ``workers``. Session 12 (issue
    30), Stage IV in memory on four hard studio seeds: 3e-4 left W-MPJPE c100, WA, PA within
    0.4 % and RTE within 0.8 % of the full schedule for 5-25 % less CPU; 1e-3 saved more but
    raised one seed's RTE by 4 %."""
    phase2_lr: float = 0.03
    """Adam learning rate of phase 2."""
    lr_final_ratio: float = 0.02
    """Adam learning rates decay (cosine) to this fraction of their start within each phase:
    large steps find the basin, small ones settle in it without Adam's jitter."""
    betas_lr_scale: float = 3.0
    """Betas learn this many times faster than the rest (they move by O(1) units, the angles by
    O(0.1) rad)."""
    window_frames: int = 300
    """Frames per window for long sequences (a sequence this long or shorter is one window)."""
    overlap_frames: int = 30
    """Frames shared by consecutive windows, blended linearly."""
    shape_frames: int = 100
    """Frames (spread evenly over the sequence) on which betas are fitted when there are several
    windows."""
    device: str = "auto"
    """``auto`` (CUDA if available, else CPU), ``cpu`` or ``cuda`` (an error where torch sees no
    CUDA device). The commands' ``--device`` sets it (:func:`embodmocap.device.motion_on_device`)."""
    dtype: str = "float32"
    """``float32`` or ``float64``. Single precision (the default since issue 30) is about 1.4x
    faster on the CPU for the same fitted keypoints (the finest Adam steps, ~6e-4 rad, are far above
    its resolution); ``float64`` for checks that compare fits to 1e-9."""
    threads: int = 1
    """Torch CPU threads while the fit runs (set for the fit, restored after); 0 leaves torch's own
    setting. One by default: the fit's tensors are small (a step is hundreds of ops on a few
    thousand numbers), so a second thread buys little on a quiet machine and, on a loaded one,
    its synchronisation at every op multiplied the fit's CPU time by up to 15 (issue 30)."""
    workers: int = 1
    """Processes that fit the windows of a long sequence (more than ``window_frames``), this one
    included, each its share of the windows as one batch with ``threads`` torch threads; 1 = this
    process only (always so on a CUDA device); never more than the usable cores. The others are
    fresh Python interpreters started when the shape fit begins (:mod:`embodmocap.motion.fit_workers`),
    never forks of this one (session 10's forked workers deadlocked on a PyAV slice-thread lock an
    earlier video read had left). The answer does not depend on it (the windows are independent:
    bit-identical). One by default (session 11): with 2, the fit's own process did 15 of its 28
    CPU s on a 60 s studio problem (the rest beside it, in the worker), so on two otherwise idle cores the
    windows' wall time nearly halves, but a worker costs about 20 % more CPU in all (its imports,
    each batch's per-step overhead), and on the shared, loaded benchmark machine Stage IV's wall
    time was not lower (the scheduler gives one session's processes one share). Set 2 where Stage IV
    has the second core to itself (``embodmocap motion`` on a quiet machine). ``embodmocap run``
    does so itself when its other worker has nothing left to do (:func:`embodmocap.schedule.cores_for`,
    :func:`embodmocap.parallel.lent_cores`): the fingerprints stay those of this setting. The
    fitted motion's per-frame quality (the mesh and the depth tests) runs on as many threads, in
    pieces of frames fixed by the sequence's length (:func:`embodmocap.motion.solve.fit_quality`:
    the same answer on any number)."""


@dataclass(frozen=True)
class ContactConfig:
    """How the contact-marker alignment is fitted and when it is refused."""

    max_residual_m: float = 0.10
    """Largest distance (metres) allowed between a contact point and its marker *after* the fit
    (horizontal distance, or 3D with ``fit_z``). Above it the markers disagree with the motion
    (or with each other) and the alignment is refused. People never stand exactly centred on a
    marker: a few centimetres are normal."""
    fit_z: bool = False
    """Also fit a vertical shift (the mean height gap between markers and feet). Off by default:
    the world is gravity-aligned and the floor height from Stage I is trusted."""
    min_yaw_baseline_m: float = 0.5
    """The yaw is fitted only when the markers spread at least this far (RMS horizontal distance
    from their centroid, metres). With one marker, or markers close together, the yaw would be
    fitted to noise, so only the translation is corrected."""
    max_yaw_deg: float = 10.0
    """Largest yaw correction (degrees) accepted. Stage III leaves errors of a degree or two; a
    larger fit means wrong annotations, and the alignment is refused."""
    max_shift_m: float = 0.5
    """Largest translation (metres, at the contacts' centroid) accepted; larger is refused like
    ``max_yaw_deg``."""
    sole_band_m: float = 0.01
    """A foot's contact point is the centre of its vertices within this height (metres) of its
    lowest vertex (its sole patch), so that the point does not jump between heel and toe when the
    foot pitches by a fraction of a degree."""


@dataclass(frozen=True)
class MotionConfig:
    """How Stage IV triangulates, fits and aligns the motion."""

    triangulation: TriangulationConfig = field(default_factory=lambda: TriangulationConfig(min_conf=TRIANGULATION_MIN_CONF))
    """Triangulation of the two views' 2D keypoints. Its ``min_conf`` is
    :data:`TRIANGULATION_MIN_CONF` here (the geometry default, 0.3, is Pose2Sim's)."""
    smplify: SmplifyConfig = field(default_factory=SmplifyConfig)
    """The two-phase world SMPLify (weights, iterations, windows, device)."""
    lift: LiftConfig = field(default_factory=LiftConfig)
    """One-phone sequences only: how the view's keypoints are lifted into the world with its
    LiDAR depth in place of the triangulation (:mod:`embodmocap.motion.lift`)."""
    contact: ContactConfig = field(default_factory=ContactConfig)
    """Contact-marker alignment (used when the manifest lists contacts for the sequence)."""
    use_body_prior: bool = True
    """Initialise from the camera-space body prior (and pull the pose towards it) when the
    sequence has one; False = start from the triangulated keypoints, no pose prior."""
    align_contacts: bool = True
    """Apply the contact-marker alignment when the manifest lists contacts."""
    label_track: LabelTrackConfig = field(default_factory=LabelTrackConfig)
    """Each view's left/right arm and leg labels tracked through time (with both views' agreement)
    before the geometric swap check (:mod:`embodmocap.motion.label_track`)."""
    leg_sides: LegSidesConfig = field(default_factory=LegSidesConfig)
    """Two views: the leg labels re-tracked at the start of the fit with the side of the starting
    body's pelvis each triangulated knee and ankle lies on (:mod:`embodmocap.motion.leg_sides`)."""
    depth_points: DepthPointsConfig = field(default_factory=DepthPointsConfig)
    """Two views: limb joints that one view sees and the other does not, placed at the start of
    the fit with the seeing view's depth on the person mask (:mod:`embodmocap.motion.depth_points`)."""
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    """Runs of a view's 2D limb keypoints that jump off their own trajectory (relative to the
    torso) and back are dropped before triangulating and fitting (:mod:`embodmocap.motion.temporal`)."""
    fix_swaps: bool = True
    """Find and undo left/right swaps of the 2D keypoints (a detector labelling an arm, a leg or
    the whole body the wrong way round in one view) before triangulating and fitting."""
    min_prior_fraction: float = 0.5
    """A view's body prior is used only when at least this share of its frames has an estimate."""
    min_frame_joints: int = 8
    """A frame needs this many triangulated joints to count as well observed; a sequence where
    more than ``max_poor_fraction`` of the frames has fewer is refused (one clear error)."""
    max_poor_fraction: float = 0.5
    """Largest share of frames with fewer than ``min_frame_joints`` triangulated joints."""
    min_valid_joints: int = 4
    """A frame where fewer joints are triangulated, or fewer than two of the hips and shoulders,
    cannot place the body: it is fitted from its neighbours but flagged ``valid = False`` in
    ``smpl_world.npz``."""
    bone_tol: float = 0.3
    """Triangulated limb points whose bone to the parent point is off by more than this fraction
    of the body's (shape from the median bone lengths) are dropped from the start and the 3D term
    (a left/right confusion in one view triangulates at the wrong depth with no reprojection
    error); 0 = keep every point."""
    torso_tol_m: float = 0.1
    """Triangulated shoulders and hips that break the torso's shape (a distance between two of
    them more than this many metres off the body's; :func:`embodmocap.motion.ik.implausible_torso`)
    are dropped from the start and the 3D term like the limb points of ``bone_tol``; 0 = keep them.
    Only with ``bone_tol`` > 0 (the same step)."""
    bone_anchor_torso: bool = True
    """The bone-length check of an elbow (knee) whose shoulder (hip) was not triangulated uses the
    shoulder (hip) of the rest torso placed on the other torso points (else it is not checked)."""
    kp3d_conf: str = "min"
    """Confidence of a triangulated point in the fit: ``mean`` (the triangulation's: mean of the
    views' confidences times the share of views used) or ``min`` (the lowest confidence of the
    views used, if lower; the default since issue 29). With two views one view's occluded guess
    (confidence 0.3-0.5, 30-90 px off) moves the point along the other view's ray without any
    reprojection error; ``min`` weighs such a point as that guess (on the hard outdoor studio seed
    5, frames 132-134, the right arm seen well by view 1 only stays 11-16 cm off with either: no
    view pins its depth). ``mean`` -> ``min``
    on the ten hard studio seeds (Stage IV in memory, label_track.fresh_start on): WA-MPJPE lower on
    all ten (median 22.4 -> 22.0 mm), PA-MPJPE on nine (seed 6 equal), W-MPJPE c100 with a chunk at
    every start lower on 8 of 10 (seed 5 52.4 -> 40.9 mm), fixed-chunk W-MPJPE c100 per seed within
    +-3.3 mm except seed 7 62.9 -> 50.0 (seed 0 +3.2: its anchor frames;
    benchmarks/history/2026-12-04-s9-edges.md)."""
    kp3d_min_view_conf: float = 0.5
    """A point triangulated from two or more views, the weakest of which detected the joint below
    this confidence, gets no weight in the fit's 3D term (the views' 2D terms still see it); 0 =
    off; one view's lifted points are left alone. A detector's
    low-confidence point is a hidden joint's guess, jittered several times more than a seen one,
    and with two views it sets the point's depth along the other view's ray alone (hard studio
    seed 3, frames 133-134: view 2's guesses of the left shoulder and elbow at 0.13-0.27, 20 px
    off, put the points 8-10 cm along view 1's ray). Runs before ``depth_points`` (a joint it places
    with the seeing view's depth keeps that point's weight). 0 -> 0.5 on the ten hard studio seeds (Stage IV):
    W-MPJPE c100 median 32.0 -> 29.6 mm, worst 34.8 -> 34.6 (benchmarks/history/2026-12-06-s13-edges.md)."""
    propagate_limbs: bool = True
    """Where a limb's start (IK or prior) disagrees with its 3D and 2D keypoints and the limb pose
    carried over from the neighbouring frames where it agrees fits them better, start from that
    (:mod:`embodmocap.motion.propagate`)."""
    turn_unplaced: bool = True
    """Start the frames that cannot be placed (see ``min_valid_joints``) facing the way the views
    that still see them say: their held orientation turned about Z to the turn whose keypoints
    reproject best (:mod:`embodmocap.motion.unplaced`). Keypoint starts only: a body prior's
    own orientation for those frames is kept."""
    init_median_frames: int = 0
    """The keypoint start (not the fit) reads the 3D keypoints through a running median over this
    many frames (0 or 1 = off): a detector's one-frame blunders do not bend the starting limbs."""
    reach_min_conf_one_view: float = 0.7
    """One view only: the keypoint start bends a limb whose middle joint (elbow, knee) is hidden to
    reach its seen end point (wrist, ankle; :func:`embodmocap.motion.ik.reach_end`) only when that
    point's confidence is at least this (0.7 = the lift's ``trusted_conf``: below it a lifted depth
    may be what hides the joint). Reaching every seen end point put the slow one-phone test's hidden
    right leg and arm on such points in its first frames (W-MPJPE 161 -> 194 mm, the chunk being
    aligned on its first two frames); with the gate 161 mm, while the hard one-phone seed 3 keeps
    what reaching its confident end points gives (WA 33.3 -> 33.0 mm against 36.0 without reaching).
    A trade on the hard one-phone seeds 0-4: W c100 -12 % on seed 4, +3-4 % on seeds 0 and 2
    (PA +3 % on seed 2), WA/PA about even on the mean (history 2026-12-05-s11-onephone).
    Two views: every seen end point, as measured there; 0 = every seen end point here too."""
    prior_disagree_m: float = 0.2
    """A frame whose prior-started body is this much further (median over the triangulated joints)
    from the 3D keypoints than the keypoint-started body starts from the keypoints instead and
    gets no pull towards the prior's pose: the triangulation wins."""
    prefer_keypoints: bool = True
    """Apply ``prior_disagree_m`` (the ``prefer_keypoints`` pass of :mod:`embodmocap.motion.passes`);
    False: a prior-started body keeps the prior's start and pull in every frame."""
    prior_limb_disagree_m: float = 0.0
    """Per limb, as ``prior_disagree_m`` per frame: where the prior body's elbow and wrist (knee and
    ankle) are this much further from their 3D keypoints than the keypoint-started body's (mean
    over the limb's triangulated keypoints), the pull towards the prior takes that limb's pose
    from the keypoints instead (:mod:`embodmocap.motion.prior_limbs`); <= 0: off (the default:
    0.1 m fixed outdoor seed 3's arm on sessions of an older Stage III but, on six seeds processed
    by today's Stages I-III, raised W-MPJPE c100 median 33.1 -> 34.6 mm and the frames wrong and
    unflagged on indoor seed 2 from 3.4 to 8.6 %; BENCHMARKS.md, Stage IV)."""
    quality: QualityConfig = field(default_factory=QualityConfig)
    """The per-frame quality figures and the ``suspect`` flag written with the motion
    (:mod:`embodmocap.motion.quality`)."""
