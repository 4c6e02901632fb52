"""Prone: lie face down with the root at the target on the object's surface (the supplement's
"Prone Skill").

- observation g^p (35), heading frame: target (3), the object's rotation (6, 6D), its
  front-facing direction (2), the eight box corners (24). The supplement lists sit's contents
  (38 numbers) but states 35: the object's root position (its box centre, which the corners
  already give) is the one left out, as for lie.
- reward ``0.7 r_near + 0.3 r_far`` when the root is more than 1.5 m (3D) from the target, else
  ``r_near``; ``r_far = 0.5 r_walk + 0.2 r_vel + 0.2 r_facing + 0.1 r_height`` towards the
  target's ground position at standing height, ``r_near = 0.6 r_pos + 0.2 r_alignment +
  0.2 r_face_down`` (the supplement's weights). Terms it names but does not write (ours, see
  docs/skills_tasks.md): as lie's (:mod:`.lie`), with ``r_height = exp(-10 (z_root - z_stand)^2)``
  and ``r_face_down = exp(-2 (1 - (-f_z))^2)``, f the body's forward axis (1 when the chest faces
  straight down).
- success: ``|x_tar - x_root| < 0.3`` m.
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import heading_frame, norm, ops, sqnorm
from embodmocap.skills.tasks.lie import alignment_reward, approach_reward
from embodmocap.skills.tasks.objects import local_facing, local_points, local_rotation6d

OBS_SIZE = 35
SUCCESS_M = 0.3
FAR_RADIUS_M = 1.5
W_NEAR_FAR, W_FAR = 0.7, 0.3
W_POS, W_ALIGN, W_DOWN = 0.6, 0.2, 0.2
K_POS, K_DOWN = 10.0, 2.0


def observation(root_pos, root_rot, target, box_rot, box_corners):
    """(N, 35) task observation."""
    H = heading_frame(root_rot)
    o = ops(root_pos)
    return o.cat([local_points(target[:, None], root_pos, root_rot, H), local_rotation6d(box_rot, root_rot, H),
                  local_facing(box_rot, root_rot, H), local_points(box_corners, root_pos, root_rot, H)], -1)


def reward(root_pos, root_rot, root_vel, target, stand_z, long_axis):
    """(N,) the prone reward; ``stand_z`` (N,) the root height of standing on the ground near the
    object, ``long_axis`` (N, 2) the object's long horizontal axis (unit)."""
    o = ops(root_pos)
    down = o.exp(-K_DOWN * (1.0 + root_rot[:, 2, 0]) ** 2)
    near = (W_POS * o.exp(-K_POS * sqnorm(target - root_pos)) + W_ALIGN * alignment_reward(root_rot, long_axis)
            + W_DOWN * down)
    goal = o.cat([target[:, :2], stand_z[:, None]], -1)
    far = approach_reward(root_pos, root_rot, root_vel, goal)
    return o.where(norm(root_pos - target) > FAR_RADIUS_M, W_NEAR_FAR * near + W_FAR * far, near)


def error(root_pos, target):
    """(N,) root to target distance, metres."""
    return norm(target - root_pos)


def success(root_pos, target, threshold_m: float = SUCCESS_M):
    """(N,) bool: root within ``threshold_m`` of the target."""
    return error(root_pos, target) < threshold_m
