"""Robot retargeting: configs, the IK round trip on the G1, and the files of a retargeted session."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("mink")
pytest.importorskip("mujoco")

from embodmocap.errors import InputError  # noqa: E402
from embodmocap.robot.config import RetargetConfig, load_robot_config, robot_config_to_toml  # noqa: E402
from embodmocap.robot.g1 import G1  # noqa: E402
from embodmocap.robot.ik import Targets, track  # noqa: E402
from embodmocap.robot.model import RobotModel  # noqa: E402

# mjlab's csv_to_npz joint list for the G1 (its scripts/csv_to_npz.py), written out independently.
MJLAB_G1_JOINTS = [
    f"{s}_{j}_joint" for s in ("left", "right")
    for j in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
] + ["waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint"] + [
    f"{s}_{j}_joint" for s in ("left", "right")
    for j in ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw")
]


@pytest.fixture(scope="module")
def g1() -> RobotModel:
    return RobotModel.load(G1)


def _random_motion(g1: RobotModel, T: int, fps: float, seed: int):
    """A smooth random G1 motion inside its joint ranges (0.1 rad clear) and speed limits."""
    rng = np.random.default_rng(seed)
    lo, hi = g1.joint_range.T
    t = np.arange(T) / fps
    centre = lo + (hi - lo) * rng.uniform(0.35, 0.65, len(lo))
    amp = np.clip(np.minimum(centre - lo, hi - centre) - 0.1, 0.0, 0.5)
    freq = rng.uniform(0.2, 0.8, len(lo))
    J = centre + amp * np.sin(2 * np.pi * freq * t[:, None] + rng.uniform(0, 2 * np.pi, len(lo)))
    root = np.stack([0.4 * t, -0.2 * t, 0.7 + 0.03 * np.sin(3 * t)], axis=1)
    quat = Rotation.from_euler("zyx", np.stack([0.6 * t, 0.1 * np.sin(2 * t), 0.08 * np.cos(t)], 1)).as_quat()
    return g1.qpos(root, quat[:, [3, 0, 1, 2]], J)


def test_ik_round_trip_recovers_random_g1_poses(g1):
    """Random G1 poses -> their body poses -> retargeted back: joints within 1 deg, bodies within 1 mm."""
    T, fps = 25, 30.0
    q = _random_motion(g1, T, fps, seed=1)
    P, Q = g1.forward(q)
    R = Rotation.from_quat(Q.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix().reshape(T, -1, 3, 3)
    B = len(g1.body_names)
    targets = Targets(g1.body_names, P, R, np.ones((T, B)), np.ones((T, B)))
    back = track(g1, targets, fps, RetargetConfig(iterations=30))
    _, _, J_back = g1.split(back)
    _, _, J_true = g1.split(q)
    assert np.degrees(np.abs(J_back - J_true)).max() < 1.0
    P_back, _ = g1.forward(back)
    assert np.linalg.norm(P_back - P, axis=-1).max() < 1e-3


def test_ik_respects_joint_limits_and_speed_limits(g1):
    """Targets out of reach (a wrist far away, fast) never push a joint past its range or speed."""
    T, fps = 12, 30.0
    q = _random_motion(g1, T, fps, seed=2)
    P, Q = g1.forward(q)
    R = Rotation.from_quat(Q.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix().reshape(T, -1, 3, 3)
    wrist = g1.body_names.index("left_wrist_yaw_link")
    P[:, wrist] += np.linspace(0, 3.0, T)[:, None] * np.array([1.0, 1.0, 1.0])  # unreachable, moving 7.5 m/s
    B = len(g1.body_names)
    back = track(g1, Targets(g1.body_names, P, R, np.ones((T, B)), np.ones((T, B))), fps)
    _, _, J = g1.split(back)
    lo, hi = g1.joint_range.T
    assert np.all(J >= lo) and np.all(J <= hi)
    speed = np.abs(np.diff(J, axis=0)) * fps
    assert np.all(speed <= g1.velocity_limit * (1 + 1e-6))


def test_g1_config_round_trips_through_toml_and_loads_the_mjlab_model(tmp_path, g1):
    path = tmp_path / "g1.toml"
    path.write_text(robot_config_to_toml(G1))
    assert load_robot_config(path) == G1
    assert g1.joint_names == tuple(MJLAB_G1_JOINTS)  # the CSV's actuated order is mjlab's
    assert g1.body_names[0] == "pelvis" and len(g1.body_names) == 30


def test_bad_robot_configs_get_one_clear_error(tmp_path):
    text = robot_config_to_toml(G1)
    bad = tmp_path / "bad.toml"
    bad.write_text("wheels = 4\n" + text)
    with pytest.raises(InputError, match="unknown key.*wheels"):
        load_robot_config(bad)
    bad.write_text(text.replace('smpl_joint = "left_knee"', 'smpl_joint = "left_kneee"'))
    with pytest.raises(InputError, match="unknown SMPL joint 'left_kneee'"):
        load_robot_config(bad)
    bad.write_text(text.replace('"left_knee_link"', '"left_shin"'))
    with pytest.raises(InputError, match="names body 'left_shin'"):
        RobotModel.load(load_robot_config(bad))
    with pytest.raises(InputError, match="not found"):
        load_robot_config(tmp_path / "missing.toml")


def test_the_g1_toml_in_docs_is_the_built_in_g1(tmp_path):
    text = (Path(__file__).parents[1] / "docs" / "robot.md").read_text()
    block = text.split("```toml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "g1.toml").write_text(block)
    assert load_robot_config(tmp_path / "g1.toml") == G1
