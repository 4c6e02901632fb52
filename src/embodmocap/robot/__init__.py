"""Humanoid robot retargeting: a captured sequence's world SMPL motion -> a robot's joint
trajectories in the captured scene, BeyondMimic/mjlab-ready files and a quality report.

Configs (:mod:`.config`, :mod:`.g1`) import without optional dependencies; everything that runs
MuJoCo or mink needs the ``robot`` extra and imports it lazily. See docs/robot.md.
"""

from embodmocap.robot.config import BodyLink, RetargetConfig, RobotConfig, load_robot_config, robot_config_to_toml
from embodmocap.robot.g1 import BUILTIN_ROBOTS, G1

__all__ = ["BUILTIN_ROBOTS", "G1", "BodyLink", "RetargetConfig", "RobotConfig", "load_robot_config",
           "robot_config_to_toml", "retarget_sequence"]


def __getattr__(name: str):
    if name == "retarget_sequence":
        from embodmocap.robot.stage import retarget_sequence

        return retarget_sequence
    raise AttributeError(name)
