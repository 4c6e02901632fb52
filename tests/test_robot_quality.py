"""Retargeting the studio's scripted walk and sit to the G1, in the studio's own scene."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.slow  # ~15 s of CPU (scene height map, 270 frames of IK)

pytest.importorskip("mink")
pytest.importorskip("mujoco")

from embodmocap.body.model import load_body_model  # noqa: E402
from embodmocap.robot.config import RetargetConfig  # noqa: E402
from embodmocap.robot.g1 import G1  # noqa: E402
from embodmocap.robot.model import RobotModel  # noqa: E402
from embodmocap.robot.report import robot_report  # noqa: E402
from embodmocap.robot.retarget import HumanRest, ground_heightmap, retarget  # noqa: E402
from embodmocap.synth.motion import MotionScriptConfig, script_motion  # noqa: E402
from embodmocap.synth.scene import build_scene  # noqa: E402


def retarget_studio_walk_sit(seed: int, seconds: float = 9.0):
    """The studio's walk-to-the-chair-and-sit script for ``seed``: (segments, report, qpos, targets)."""
    body = load_body_model(None)
    built = build_scene("indoor", np.random.default_rng(seed))
    betas = np.zeros(10)
    betas[:4] = np.random.default_rng(seed).normal(0, [0.8, 0.6, 0.5, 0.5])
    script = script_motion(built.spec, body, betas, seconds, 30.0, np.random.default_rng(seed),
                           MotionScriptConfig(idle_s=0.5, interactions=("chair",)))
    with torch.no_grad():
        joints = body.from_params(script.params, dtype=torch.float64).joints.numpy()
    hm = ground_heightmap(built.vertices, built.faces, joints)
    robot = RobotModel.load(G1)
    q, ht = retarget(robot, script.params, joints, HumanRest.of(body, betas), hm, RetargetConfig())
    return script.segments, robot_report(robot, q, ht, 30.0, hm), q, ht


@pytest.fixture(scope="module")
def walk_sit():
    return retarget_studio_walk_sit(0)


def test_walk_and_sit_meet_the_issue_figures(walk_sit):
    segments, rep, q, ht = walk_sit
    names = {n for n, _, _ in segments}
    assert {"walk", "sit"} <= names  # the script really walks and sits
    assert ht.contacts.any(axis=0).all() and rep["contact_runs"] >= 4
    assert rep["keypoint_residual_mean_m"] <= 0.040
    assert rep["joint_limit_violations"] == 0
    assert rep["foot_penetration_max_m"] <= 0.01  # feet never more than 1 cm below the floor
    assert rep["foot_skating_max_m"] <= 0.01  # during the human's contacts
    assert rep["joint_speed_over_limit_joints"] == 0
    assert rep["self_collision_frames"] == 0  # the hands stay clear of the hips


def test_the_robot_is_smaller_and_moves_with_the_human(walk_sit):
    _, rep, q, ht = walk_sit
    assert 0.7 < rep["scale"] < 0.9  # G1 legs (0.62 m) vs the studio performer's
    # The pelvis path is the human's, scaled about its mean: compare displacements.
    human = ht.joints[:, 0, :2] - ht.joints[:, 0, :2].mean(axis=0)
    robot = q[:, :2] - q[:, :2].mean(axis=0)
    np.testing.assert_allclose(robot, rep["scale"] * human, atol=0.05)
