"""The torso's orientation held smooth through time: a term of the world SMPLify (Stage IV).

Why a term of its own: the body's heading is read off the hip and shoulder keypoints, two pairs of
points 26 cm (hips) and 35 cm (shoulders) apart. A detector's frame-to-frame jitter of a
centimetre or two on each turns the line between them by several degrees, so the fitted torso
turns by 3-10 degrees from one frame to the next while the person turns smoothly (ten hard studio
seeds: the torso's heading off the truth by 2-4 degrees median, up to 11; the fitted trunk's
angular acceleration 40-180 times the truth's). The joint acceleration term hardly resists this:
it weighs a turn by the squared distance of the joints it moves from the body's centre (a few
hundredths of a m^2). W-MPJPE aligns each 100-frame chunk on its first two frames, so a few degrees
of heading there turn the whole chunk (a body 2 m from the anchor moves 35 mm per degree).

The term is the angular acceleration of the torso frame that the hips, shoulders, pelvis and neck
make (:func:`torso_frames`), rad^2 per frame^2. It is measured on the joints, not on the pelvis and
spine rotations: smoothing those (tried first) let the collars take up the shoulders' jitter and
left a bias of 2 degrees in the heading. A real turn (a quarter turn in a second at 30 fps) has an
angular acceleration of about 0.01 rad per frame^2 (the studio truth's mean square: 1e-4), the
keypoints' wobble about 0.1, so a small weight removes the wobble and leaves real turns alone. A
large one (100 per rad^2 and more) slows the fit's convergence (Adam, 300 steps): the heading is then
biased, and WA-MPJPE and RTE get worse (benchmarks/history/2026-12-05-s10-yaw.md).
"""

from __future__ import annotations

import torch
from embodmocap.motion.terms import same_run_triples

#: SMPL joints of the torso frame: pelvis, hips, neck, shoulders.
PELVIS, L_HIP, R_HIP, NECK, L_SHOULDER, R_SHOULDER = 0, 1, 2, 12, 16, 17


def torso_frames(joints: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) torso rotations (columns: the body's left, up and forward in the world) of SMPL
    joints (..., 24, 3): left = the mean of the hips' and the shoulders' right -> left directions,
    up = pelvis -> neck made orthogonal to it, forward = left x up. The heading the hip and
    shoulder keypoints give, whatever pelvis, spine and collar rotations make it."""
    unit = lambda v: v / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # noqa: E731
    left = unit(unit(joints[..., L_HIP, :] - joints[..., R_HIP, :])
                + unit(joints[..., L_SHOULDER, :] - joints[..., R_SHOULDER, :]))
    up = joints[..., NECK, :] - joints[..., PELVIS, :]
    up = unit(up - (up * left).sum(-1, keepdim=True) * left)
    return torch.stack([left, up, torch.linalg.cross(left, up)], -1)


def torso_acc_term(joints: torch.Tensor, placed: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared angular acceleration of the torso frame (:func:`torso_frames`) of joints
    (T, 24, 3), rad^2 per frame^2; 0 for fewer than 3 frames.

    For rotations ``R_t`` the second difference ``R_{t+1} - 2 R_t + R_{t-1}`` is ``R_t [a]x`` plus
    terms of the squared angular velocity, so half its squared Frobenius norm is ``|a|^2`` for
    small steps (``a`` the angular acceleration in rad per frame^2); a turn at a constant rate of
    ``w`` rad per frame costs about ``w^4`` (1e-5 for a quarter turn per second). Mean over the
    ``T - 2`` frames. ``placed`` (T,) 1 for a placeable frame, 0 not (``SmplifyConfig.acc_cut_unplaced``):
    the second differences whose three frames mix both count 0 (still divided by ``T - 2``).
    """
    if joints.shape[0] < 3:
        return joints.sum() * 0.0
    R = torso_frames(joints)
    d2 = 0.5 * ((R[2:] - 2.0 * R[1:-1] + R[:-2]) ** 2).sum((-1, -2))  # (T-2,)
    if placed is not None:  # (T,) 1 placeable, 0 not: a difference spanning both counts 0
        d2 = d2 * same_run_triples(placed)
    return d2.mean()
