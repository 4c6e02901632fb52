"""The interacted object as the task observations see it (shared by sit, climb, lie, prone, support).

An object is its oriented bounding box: ``center`` (N, 3), ``rot`` (N, 3, 3) (columns: the box's
axes in the world; the first is its front, the side a person sits facing), ``corners`` (N, 8, 3)
in the order of skills.json (docs/formats.md).
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import heading_frame, ops, points_to_heading, rot6d, to_heading, unit


def local_points(points, root_pos, root_rot, H=None):
    """(N, K*3) world points (N, K, 3) in the heading frame, flattened point after point.
    ``H``: the heading frame (:func:`heading_frame`) when already at hand (it is the costly part)."""
    return points_to_heading(points, root_pos, root_rot, H).reshape(points.shape[0], -1)


def local_rotation6d(rot, root_rot, H=None):
    """(N, 6) the object's rotation relative to the heading frame, 6D (first two columns)."""
    H = heading_frame(root_rot) if H is None else H
    return rot6d(ops(rot).swap(H) @ rot)


def local_facing(rot, root_rot, H=None):
    """(N, 2) the object's front direction on the ground, in the heading frame (unit)."""
    o = ops(rot)
    f = rot[:, :, 0] * o.like([1.0, 1.0, 0.0], rot)
    return unit(to_heading(f, root_rot, H)[:, :2])
