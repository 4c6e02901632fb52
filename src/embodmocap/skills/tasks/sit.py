"""Sit: the root to 10 cm above the centre of the seat's top (the supplement's "Sit Skill").

- observation g^s (38), all in the heading frame: target (3), the object's root position (3, its
  box centre), the object's root rotation (6, 6D), the object's front-facing direction (2), the
  eight box corners (24). "Root position / rotation / facing" are the object's, as in TokenHSI,
  whose sit task the paper follows (the character's own are zero / identity in its heading frame,
  and its proprioception already carries them).
- reward ``r^s = 0.7 r_near + 0.3 r_far`` when the root is more than 0.5 m (2D) from the object,
  else ``0.7 r_near + 0.3``; ``r_far = exp(-2 (1.5 - d* . v_root_2d)^2)`` (walk towards the object
  at 1.5 m/s), ``r_near = exp(-10 |x_tar - x_root|^2)``.
- success: ``|x_tar - x_root| < 0.2`` m.
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import far_speed_reward, heading_frame, norm, ops, sqnorm
from embodmocap.skills.tasks.objects import local_facing, local_points, local_rotation6d

OBS_SIZE = 38
SUCCESS_M = 0.2
TARGET_ABOVE_TOP_M = 0.10
NEAR_RADIUS_M = 0.5
W_NEAR, W_FAR = 0.7, 0.3
K_NEAR, K_FAR, FAR_SPEED = 10.0, 2.0, 1.5


def observation(root_pos, root_rot, target, box_center, box_rot, box_corners):
    """(N, 38) task observation; ``target``/``box_center`` (N, 3), ``box_rot`` (N, 3, 3), ``box_corners`` (N, 8, 3)."""
    H = heading_frame(root_rot)
    o = ops(root_pos)
    return o.cat([local_points(target[:, None], root_pos, root_rot, H), local_points(box_center[:, None], root_pos, root_rot, H),
                  local_rotation6d(box_rot, root_rot, H), local_facing(box_rot, root_rot, H),
                  local_points(box_corners, root_pos, root_rot, H)], -1)


def reward(root_pos, root_vel, target, box_center):
    """(N,) the sit reward; ``root_vel`` (N, 3) root linear velocity."""
    o = ops(root_pos)
    near = o.exp(-K_NEAR * sqnorm(target - root_pos))
    far = far_speed_reward(root_pos, root_vel, box_center[:, :2], FAR_SPEED, K_FAR)
    away = norm(box_center[:, :2] - root_pos[:, :2]) > NEAR_RADIUS_M
    return W_NEAR * near + o.where(away, W_FAR * far, far * 0 + W_FAR)


def error(root_pos, target):
    """(N,) root to target distance, metres."""
    return norm(target - root_pos)


def success(root_pos, target, threshold_m: float = SUCCESS_M):
    """(N,) bool: root within ``threshold_m`` of the target."""
    return error(root_pos, target) < threshold_m
