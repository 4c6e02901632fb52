"""Support: both hands on the object's top, bearing weight, the feet together on the ground (the
supplement's "Support Skill").

- observation g^m (27), heading frame: the target, the centre of the object's top surface (3),
  and the eight box corners (24).
- reward (the supplement's, all constants as written): ``0.4 r^f + 0.6 r^s`` when the root is
  more than 1.5 m (2D) from the target, else ``r^s``;
  ``r^f = 0.5 exp(-0.5 |x_o - x_r|^2) + 0.5 exp(-2 (1.5 - d* . v_r)^2)``,
  ``r^s = 0.3 r^h + 0.2 r^g + 0.15 r^t + 0.2 r^o + 0.15 r^z`` with
  ``r^h = 0.6 exp(-20 (z_h - z_o)^2) + 0.4 exp(-5 |x_h - x_o|^2)`` (hands' mean height and 2D
  centre), ``r^g = exp(-50 (z_f - z_g)^2)`` (feet's mean sole height vs the ground),
  ``r^t = exp(-10 |x_fr - x_fl|^2)`` (feet together), ``r^o = exp(-2 (1 - u_z)^2)`` (u: the body's
  up axis), ``r^z = exp(-10 (z_r - z_o)^2)``.
- success: the hands' centre within 0.1 m (3D: its XY distance and Z deviation together) of the
  top's centre, and the feet together (ankles less than ``FEET_TOGETHER_M`` apart on the ground).
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import far_speed_reward, heading_frame, norm, ops, sqnorm
from embodmocap.skills.tasks.objects import local_points

OBS_SIZE = 27
SUCCESS_M = 0.1
FEET_TOGETHER_M = 0.4  # the clip finder's "feet together" (skills.config feet_together_m): one definition
FAR_RADIUS_M = 1.5
W_F, W_S = 0.4, 0.6
W_H, W_G, W_T, W_O, W_Z = 0.3, 0.2, 0.15, 0.2, 0.15


def observation(root_pos, root_rot, target, box_corners):
    """(N, 27) task observation."""
    H = heading_frame(root_rot)
    return ops(root_pos).cat([local_points(target[:, None], root_pos, root_rot, H),
                              local_points(box_corners, root_pos, root_rot, H)], -1)


def reward(root_pos, root_rot, root_vel, hand_pos, foot_pos, target, ground_z):
    """(N,) the support reward; ``hand_pos``/``foot_pos`` (N, 2, 3) left then right (feet: sole
    height), ``ground_z`` (N,) the ground's height under the character."""
    o = ops(root_pos)
    d2 = norm(target[:, :2] - root_pos[:, :2])
    rf = 0.5 * o.exp(-0.5 * d2 ** 2) + 0.5 * far_speed_reward(root_pos, root_vel, target[:, :2], 1.5, 2.0)
    hand = o.sum(hand_pos, 1) / 2
    rh = 0.6 * o.exp(-20.0 * (hand[:, 2] - target[:, 2]) ** 2) + 0.4 * o.exp(-5.0 * sqnorm(hand[:, :2] - target[:, :2]))
    rg = o.exp(-50.0 * (o.sum(foot_pos[:, :, 2], 1) / 2 - ground_z) ** 2)
    rt = o.exp(-10.0 * sqnorm(foot_pos[:, 1, :2] - foot_pos[:, 0, :2]))
    ro = o.exp(-2.0 * (1.0 - root_rot[:, 2, 2]) ** 2)
    rz = o.exp(-10.0 * (root_pos[:, 2] - target[:, 2]) ** 2)
    rs = W_H * rh + W_G * rg + W_T * rt + W_O * ro + W_Z * rz
    return o.where(d2 > FAR_RADIUS_M, W_F * rf + W_S * rs, rs)


def error(hand_pos, target):
    """(N,) distance of the hands' centre from the top's centre, metres (3D)."""
    return norm(ops(hand_pos).sum(hand_pos, 1) / 2 - target)


def feet_distance(foot_pos):
    """(N,) horizontal distance between the feet, metres."""
    return norm(foot_pos[:, 1, :2] - foot_pos[:, 0, :2])


def success(hand_pos, foot_pos, target, threshold_m: float = SUCCESS_M, feet_m: float = FEET_TOGETHER_M):
    """(N,) bool: hands' centre within ``threshold_m`` of the target and the feet less than ``feet_m`` apart."""
    return (error(hand_pos, target) < threshold_m) & (feet_distance(foot_pos) < feet_m)
