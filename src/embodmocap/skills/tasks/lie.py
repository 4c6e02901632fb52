"""Lie: walk to a standing point beside the object, then lie with the root at the target on its
surface (the supplement's "Lie Skill").

- observation g^l (38), heading frame: target (3), standing point (3), the object's rotation (6,
  6D), its front-facing direction (2), the eight box corners (24). The supplement lists sit's 38
  numbers "and also" the standing point; at 38 the standing point takes the place of the
  object's root position (its box centre), which the corners already give.
- reward ``0.6 r_near + 0.4 r_far`` when the root is more than 1.5 m (3D) from the target, else
  ``r_near``; ``r_far = 0.5 r_walk + 0.2 r_vel + 0.2 r_facing + 0.1 r_stand``,
  ``r_near = 0.5 r_pos + 0.3 r_head + 0.2 r_alignment`` (the supplement's weights). The
  supplement names but does not write the terms; ours (documented in docs/skills_tasks.md), with
  the constants of its other skills: ``r_walk = exp(-0.5 |p_stand_2d - x_root_2d|^2)``,
  ``r_vel = exp(-2 (1.5 - d* . v_root_2d)^2)`` (d*: towards the standing point),
  ``r_facing = exp(-2 (1 - d* . f_2d)^2)`` (f: the character's facing), ``r_stand =
  exp(-10 (z_root - z_stand)^2)`` (the standing point is a root position), ``r_pos =
  exp(-10 |x_tar - x_root|^2)``, ``r_head = exp(-10 (z_head - z_tar)^2)`` (the head as high as
  the lying root), ``r_alignment = exp(-2 (1 - |u_2d . l|)^2)`` (u: the body's up axis, l: the
  object's long horizontal axis; 1 only for a body lying flat along the object).
- success: ``|x_tar - x_root| < 0.3`` m.
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import facing_2d, far_speed_reward, heading_frame, norm, ops, sqnorm, unit
from embodmocap.skills.tasks.objects import local_facing, local_points, local_rotation6d

OBS_SIZE = 38
SUCCESS_M = 0.3
FAR_RADIUS_M = 1.5
W_NEAR_FAR, W_FAR = 0.6, 0.4
W_WALK, W_VEL, W_FACING, W_STAND = 0.5, 0.2, 0.2, 0.1
W_POS, W_HEAD, W_ALIGN = 0.5, 0.3, 0.2
K_WALK, K_VEL, K_FACING, K_STAND, K_POS, K_HEAD, K_ALIGN, SPEED = 0.5, 2.0, 2.0, 10.0, 10.0, 10.0, 2.0, 1.5


def observation(root_pos, root_rot, target, stand_point, box_rot, box_corners):
    """(N, 38) task observation."""
    H = heading_frame(root_rot)
    o = ops(root_pos)
    return o.cat([local_points(target[:, None], root_pos, root_rot, H), local_points(stand_point[:, None], root_pos, root_rot, H),
                  local_rotation6d(box_rot, root_rot, H), local_facing(box_rot, root_rot, H),
                  local_points(box_corners, root_pos, root_rot, H)], -1)


def approach_reward(root_pos, root_rot, root_vel, goal):
    """(N,) ``0.5 r_walk + 0.2 r_vel + 0.2 r_facing + 0.1 r_stand`` towards the root position ``goal`` (N, 3)."""
    o = ops(root_pos)
    walk = o.exp(-K_WALK * sqnorm(goal[:, :2] - root_pos[:, :2]))
    vel = far_speed_reward(root_pos, root_vel, goal[:, :2], SPEED, K_VEL)
    d = unit(goal[:, :2] - root_pos[:, :2])
    facing = o.exp(-K_FACING * (1.0 - o.sum(d * facing_2d(root_rot), -1)) ** 2)
    stand = o.exp(-K_STAND * (root_pos[:, 2] - goal[:, 2]) ** 2)
    return W_WALK * walk + W_VEL * vel + W_FACING * facing + W_STAND * stand


def alignment_reward(root_rot, long_axis):
    """(N,) ``exp(-2 (1 - |u_2d . l|)^2)``: the body's up axis lying along ``long_axis`` (N, 2) (unit)."""
    o = ops(root_rot)
    a = o.abs(o.sum(root_rot[:, :2, 2] * long_axis, -1))
    return o.exp(-K_ALIGN * (1.0 - a) ** 2)


def reward(root_pos, root_rot, root_vel, head_pos, target, stand_point, long_axis):
    """(N,) the lie reward; ``head_pos`` (N, 3), ``stand_point`` (N, 3) a standing root position,
    ``long_axis`` (N, 2) the object's long horizontal axis (unit)."""
    o = ops(root_pos)
    near = (W_POS * o.exp(-K_POS * sqnorm(target - root_pos)) + W_HEAD * o.exp(-K_HEAD * (head_pos[:, 2] - target[:, 2]) ** 2)
            + W_ALIGN * alignment_reward(root_rot, long_axis))
    far = approach_reward(root_pos, root_rot, root_vel, stand_point)
    return o.where(norm(root_pos - target) > FAR_RADIUS_M, W_NEAR_FAR * near + W_FAR * far, near)


def error(root_pos, target):
    """(N,) root to target distance, metres."""
    return norm(target - root_pos)


def success(root_pos, target, threshold_m: float = SUCCESS_M):
    """(N,) bool: root within ``threshold_m`` of the target."""
    return error(root_pos, target) < threshold_m
