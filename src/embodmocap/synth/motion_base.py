"""What the scripted performer's modules share (:mod:`embodmocap.synth.motion` and its parts
:mod:`~embodmocap.synth.motion_body`, :mod:`~embodmocap.synth.motion_place`,
:mod:`~embodmocap.synth.motion_skills`): the script's settings, the SMPL joint ids, the supports
and the easing and furniture helpers. Below them all, so none imports another back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.synth.spec import Furniture, SceneSpec

# SMPL joint ids used below (body_pose holds joints 1..23).
_L_HIP, _R_HIP, _SPINE1, _L_KNEE, _R_KNEE, _SPINE2, _L_ANKLE, _R_ANKLE, _SPINE3 = 1, 2, 3, 4, 5, 6, 7, 8, 9
_NECK, _HEAD, _L_SHOULDER, _R_SHOULDER, _L_ELBOW, _R_ELBOW = 12, 15, 16, 17, 18, 19

#: Interaction names :attr:`MotionScriptConfig.interactions` accepts. ``chair``/``sit``,
#: ``sofa``, ``box``/``climb`` and ``table``/``support`` are the original four under their
#: furniture and skill names; ``lie`` and ``prone`` use the bed (skipped in a room with a sofa);
#: ``follow`` walks a smooth curved path through the walk area without stopping.
INTERACTIONS: tuple[str, ...] = ("chair", "sit", "sofa", "box", "climb", "table", "support", "lie", "prone", "follow")

#: Furniture whose top the body rests on (a support); the table is only touched by the hands.
SUPPORTS: tuple[str, ...] = ("box", "chair", "sofa", "bed")

#: Supports that are a slab on legs rather than solid to the floor: only vertices less than this
#: far below their top are held up by them (feet may go under a chair's seat), metres.
SLAB_DEPTH: dict[str, float] = {"chair": 0.2}


@dataclass(frozen=True)
class MotionScriptConfig:
    """How the performer moves."""

    idle_s: float = 1.5
    """Standing still at the start (the laser sync event happens then), seconds."""
    walk_speed_mps: float = 1.15
    """Cruising walking speed, m/s (step length x cadence: 0.64 m x 1.8 steps/s)."""
    cadence_steps_per_s: float = 1.8
    """Steps per second at cruising speed; the gait phase advances with distance walked, so the
    step length is ``walk_speed_mps / cadence_steps_per_s``."""
    ease_s: float = 0.5
    """Time to speed up from standing to cruising speed (and to slow down), seconds."""
    turn_speed_dps: float = 180.0
    """Average turning speed when turning on the spot, degrees per second."""
    min_turn_s: float = 0.4
    """Shortest turn, seconds (small corrections are not instantaneous)."""
    sit_transition_s: float = 1.2
    """Time to sit down and to stand up, seconds."""
    step_s: float = 2.4
    """Time to step onto the box and to step off it, seconds."""
    lean_transition_s: float = 1.0
    """Time to lean onto the table and to straighten up, seconds."""
    hold_s: float = 1.5
    """How long the performer stays seated / on the box / leaning, seconds (shortened when the
    clip is too short for the first interaction)."""
    arm_swing_deg: float = 16.0
    """Arm swing amplitude at cruising speed, degrees (opposite to the legs)."""
    hip_swing_deg: float = 20.0
    """Hip flexion/extension amplitude at cruising speed, degrees."""
    knee_swing_deg: float = 55.0
    """Peak extra knee flexion in the swing phase at cruising speed, degrees."""
    interactions: tuple[str, ...] = ("chair", "box", "table", "sofa")
    """Interactions to perform, as many as fit: the nearest first, then the others in a random
    order; ``"sofa"`` means whichever of sofa / bed the scene has. Any of :data:`INTERACTIONS`:
    ``"sit"`` = ``"chair"``, ``"climb"`` = ``"box"``, ``"support"`` = ``"table"`` (both hands on
    the table top, feet together), ``"lie"`` / ``"prone"`` (on the bed, back / front down; a room
    with a sofa has no bed and skips them), ``"follow"`` (a curved walk along a path); ``()`` walks
    only."""
    lie_transition_s: float = 2.0
    """Time to lie down on the bed (from standing beside it) and to get up again, seconds."""
    follow_waypoints: int = 4
    """Control points of the curved path a ``"follow"`` interaction walks (besides the start)."""
    chunk_frames: int = 128
    """Frames skinned at once (bounds memory: the skinning holds per-vertex transforms)."""


def _ease(u: NDArray) -> NDArray:
    """Quintic smoothstep on [0, 1] (clipped): zero velocity and acceleration at both ends."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


def _supports(spec: SceneSpec) -> list[Furniture]:
    return [f for n, f in spec.furniture.items() if n in SUPPORTS and f.name in SUPPORTS]


def _in_footprint(f: Furniture, xy: NDArray) -> NDArray[np.bool_]:
    """(...,) True where points xy (..., 2) are inside the furniture's footprint."""
    d = xy - np.asarray(f.centre_xy)
    c, s = np.cos(f.yaw), np.sin(f.yaw)
    lx, ly = d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c
    return (np.abs(lx) < f.size[0] / 2) & (np.abs(ly) < f.size[1] / 2)


def _heading(f: Furniture) -> NDArray:
    return np.array([np.cos(f.yaw), np.sin(f.yaw)])
