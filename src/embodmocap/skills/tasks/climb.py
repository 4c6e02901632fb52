"""Climb: the root to 94 cm above the centre of the object's top (the supplement's "Climb Skill").

- observation g^m (27), heading frame: target (3), the eight box corners (24).
- reward ``0.5 r_near + 0.2 r_far`` when the root is more than 0.7 m (2D) from the object, else
  ``0.5 r_near + 0.2 + 0.3 r_foot``; ``r_near = exp(-10 |x_tar - x_root|^2)``,
  ``r_far = exp(-2 (1.5 - d* . v_root_2d)^2)``, ``r_foot = exp(-50 ((h_tar - 0.94) - h_feet)^2)``
  with ``h_feet`` the mean height of the feet (their soles).
- success: ``|x_tar - x_root| < 0.2`` m.
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import far_speed_reward, heading_frame, norm, ops, sqnorm
from embodmocap.skills.tasks.objects import local_points

OBS_SIZE = 27
SUCCESS_M = 0.2
TARGET_ABOVE_TOP_M = 0.94
NEAR_RADIUS_M = 0.7
W_NEAR, W_FAR, W_FOOT = 0.5, 0.2, 0.3
K_NEAR, K_FAR, K_FOOT, FAR_SPEED = 10.0, 2.0, 50.0, 1.5


def observation(root_pos, root_rot, target, box_corners):
    """(N, 27) task observation."""
    H = heading_frame(root_rot)
    return ops(root_pos).cat([local_points(target[:, None], root_pos, root_rot, H),
                              local_points(box_corners, root_pos, root_rot, H)], -1)


def reward(root_pos, root_vel, target, box_center, foot_pos):
    """(N,) the climb reward; ``foot_pos`` (N, 2, 3) the feet (z: sole height)."""
    o = ops(root_pos)
    near = o.exp(-K_NEAR * sqnorm(target - root_pos))
    far = far_speed_reward(root_pos, root_vel, box_center[:, :2], FAR_SPEED, K_FAR)
    feet_h = o.sum(foot_pos[:, :, 2], -1) / foot_pos.shape[1]
    foot = o.exp(-K_FOOT * ((target[:, 2] - TARGET_ABOVE_TOP_M) - feet_h) ** 2)
    away = norm(box_center[:, :2] - root_pos[:, :2]) > NEAR_RADIUS_M
    return W_NEAR * near + o.where(away, W_FAR * far, W_FAR + W_FOOT * foot)


def error(root_pos, target):
    """(N,) root to target distance, metres."""
    return norm(target - root_pos)


def success(root_pos, target, threshold_m: float = SUCCESS_M):
    """(N,) bool: root within ``threshold_m`` of the target."""
    return error(root_pos, target) < threshold_m
