"""The retargeting's steps, declared once (:mod:`embodmocap.io.steps`): their fingerprints, the
coverage test of :class:`~embodmocap.robot.config.RetargetConfig` and the architecture doc's table
come from here. The robot itself (its :class:`~embodmocap.robot.config.RobotConfig`, built in or
from a TOML file) is the run-time fact ``robot``."""

from __future__ import annotations

from embodmocap.io.steps import StageSteps, Step
from embodmocap.robot.config import RetargetConfig

_DIR = "sequences/<seq>/robot/<robot>/"

STEPS = StageSteps("robot", RetargetConfig, (
    # the height map's cell is the retargeting's (it keeps the robot above the scene); the scene
    # files and the report, which come after it, use the same map
    Step("retarget", reads=("sequences/<seq>/smpl_world.npz", "scene mesh", "body model", "robot MJCF"),
         context=("robot",),
         settings=("scale_from", "scale", "keep_path", "iterations", "first_frame_iterations", "tolerance_m",
                   "posture_weight", "foot_pin_weight", "lm_damping", "contact_height_m", "contact_speed_mps",
                   "contact_min_frames", "heightmap_cell_m"),
         writes=(_DIR + "qpos.npz",), doc="the robot's motion (checkpointed to qpos_partial.npz while it runs)"),
    Step("export", after=("retarget",), reads=("qpos.npz",), settings=("tracking_fps",),
         writes=(_DIR + "motion.csv", _DIR + "motion.npz", _DIR + "motion_gmr.pkl", _DIR + "scene.obj",
                 _DIR + "scene.xml"), doc="the motion in the trackers' formats, the scene MJCF"),
    Step("report", after=("retarget",), reads=("qpos.npz",), settings=("self_collision_depth_m",),
         writes=(_DIR + "robot_report.json",), doc="quality figures of the robot's motion"),
), not_fingerprinted={
    "checkpoint_frames": "how often an unfinished retargeting is saved to resume from, not what it solves",
})
