"""Stage IV's steps, declared once (:mod:`embodmocap.io.steps`): their fingerprints, the coverage
test of :class:`~embodmocap.motion.config.MotionConfig` and the architecture doc's table come from here."""

from __future__ import annotations

from embodmocap.io.steps import StageSteps, Step
from embodmocap.motion.config import MotionConfig

_DIR = "sequences/<seq>/"

STEPS = StageSteps("motion", MotionConfig, (
    # One step, two recipes: two views triangulate; one view lifts its keypoints with its depth
    # (recorded as `lift`). Both share the keypoint checks (label_track, temporal).
    Step("triangulate", context=("one_view",),
         reads=("<view>/keypoints2d.npz", "<view>/cameras_world.npz", "<view>/depth.npy", "<view>/masks.npy"),
         settings=("triangulation", "fix_swaps", "label_track", "temporal", "lift"),
         writes=(_DIR + "keypoints3d.npz",), doc="3D keypoints (one view: `lift`, from its depth)"),
    Step("fit", after=("triangulate",), reads=("<view>/body_prior.npz", "body model", "<view>/depth.npy", "<view>/masks.npy", "scene mesh"), context=("layout", "gender"),
         settings=("smplify", "use_body_prior", "min_prior_fraction", "min_frame_joints", "max_poor_fraction",
                   "min_valid_joints", "prior_disagree_m", "prefer_keypoints", "prior_limb_disagree_m", "bone_tol", "torso_tol_m", "bone_anchor_torso",
                   "propagate_limbs", "turn_unplaced", "kp3d_conf", "kp3d_min_view_conf", "init_median_frames",
                   "reach_min_conf_one_view", "quality", "leg_sides", "depth_points"),
         writes=(_DIR + "smpl_fit.npz",), doc="world SMPLify on the 3D and 2D keypoints"),
    Step("align", after=("fit",), reads=("<view>/cameras_world.npz",), context=("contacts",),
         settings=("contact", "align_contacts"),
         writes=(_DIR + "smpl_world.npz", _DIR + "joints_world.npz", _DIR + "<view>/cameras_final.npz"),
         doc="contact-marker alignment (the final outputs, written without markers too)"),
))
