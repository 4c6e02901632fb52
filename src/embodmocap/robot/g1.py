"""The built-in Unitree G1 (29 DoF) config; its MJCF and meshes ship in ``robot/assets/unitree_g1``
(copied from the mjlab 1.6.0 wheel, Apache-2.0: see the NOTICE there).

Which body follows which joint: the pelvis, hips, knees and ankles (feet), the shoulders, elbows and
wrists by position; the pelvis, torso and feet also by orientation (their rest frames match SMPL's
rest frames; the arms' do not, see :class:`BodyLink`). The torso follows ``spine3`` by orientation
only (its frame origin sits at the waist, far from SMPL's chest joint). Speed limits are Unitree's
motor specifications (5020: 37 rad/s, 7520-14: 32, 7520-22: 20, 4010: 22) by joint, with the
two-motor linkages (waist roll/pitch, ankles) limited like one 5020. Each hand is kept clear of
the pelvis and its own hip and thigh (collision avoidance).
"""

from __future__ import annotations

from embodmocap.robot.config import BodyLink, RobotConfig

G1 = RobotConfig(
    name="g1",
    mjcf="embodmocap:unitree_g1/g1.xml",
    root_body="pelvis",
    links=(
        BodyLink("pelvis", "pelvis", 1.0, 1.0),
        BodyLink("left_hip_roll_link", "left_hip", 1.0, 0.0),
        BodyLink("left_knee_link", "left_knee", 1.0, 0.0),
        BodyLink("left_ankle_roll_link", "left_ankle", 1.0, 0.5),
        BodyLink("right_hip_roll_link", "right_hip", 1.0, 0.0),
        BodyLink("right_knee_link", "right_knee", 1.0, 0.0),
        BodyLink("right_ankle_roll_link", "right_ankle", 1.0, 0.5),
        BodyLink("torso_link", "spine3", 0.0, 0.5),
        BodyLink("left_shoulder_roll_link", "left_shoulder", 0.5, 0.0),
        BodyLink("left_elbow_link", "left_elbow", 1.0, 0.0),
        BodyLink("left_wrist_yaw_link", "left_wrist", 1.0, 0.0),
        BodyLink("right_shoulder_roll_link", "right_shoulder", 0.5, 0.0),
        BodyLink("right_elbow_link", "right_elbow", 1.0, 0.0),
        BodyLink("right_wrist_yaw_link", "right_wrist", 1.0, 0.0),
    ),
    feet=("left_ankle_roll_link", "right_ankle_roll_link"),
    hands=("left_wrist_yaw_link", "right_wrist_yaw_link"),
    height_m=1.32,
    joint_limit_margin_rad=0.02,
    velocity_limits=(
        (r".*_hip_pitch_joint", 32.0), (r".*_hip_yaw_joint", 32.0), (r"waist_yaw_joint", 32.0),
        (r".*_hip_roll_joint", 20.0), (r".*_knee_joint", 20.0),
        (r".*_wrist_pitch_joint", 22.0), (r".*_wrist_yaw_joint", 22.0),
        (r".*_joint", 37.0),
    ),
    # The G1's hips are wider than a scaled human's: hands hanging by the thighs would go through them.
    avoid_collisions=tuple((f"{s}_wrist_yaw_link", b) for s in ("left", "right")
                           for b in ("pelvis", f"{s}_hip_roll_link", f"{s}_hip_yaw_link")),
)

#: Built-in robots by name (``--robot``).
BUILTIN_ROBOTS: dict[str, RobotConfig] = {"g1": G1}
