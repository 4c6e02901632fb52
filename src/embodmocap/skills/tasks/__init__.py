"""The six interaction skills of the paper as pure, batched task functions (numpy or torch).

Per skill (follow, sit, climb, lie, prone, support) a module gives ``observation``, ``reward``,
``error`` and ``success`` with the supplement's contents, sizes, formulas, constants and the
paper's success thresholds (20 cm follow / sit / climb, 30 cm lie / prone, 10 cm support with the
feet together). :func:`observe`, :func:`reward`, :func:`error` and :func:`success` dispatch on the
skill's name from one :class:`CharacterState` and one :class:`SkillGoal`. Layouts and constants:
docs/skills_tasks.md.

Any trainer can use them: the arrays are batched over environments (leading axis N) and may be
numpy arrays or torch tensors (on any device); the result has the input's kind.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from embodmocap.skills.tasks import climb, follow, lie, prone, sit, support

SKILLS: tuple[str, ...] = ("follow", "sit", "climb", "lie", "prone", "support")
MODULES = {"follow": follow, "sit": sit, "climb": climb, "lie": lie, "prone": prone, "support": support}
#: Task observation size per skill (the supplement's).
OBS_SIZE: dict[str, int] = {k: m.OBS_SIZE for k, m in MODULES.items()}
#: Success threshold per skill, metres (the paper's).
SUCCESS_M: dict[str, float] = {k: m.SUCCESS_M for k, m in MODULES.items()}


@dataclass(frozen=True)
class CharacterState:
    """The simulated character, batched (N environments), world frame (Z up, metres).

    Attributes:
        root_pos: (N, 3) root (pelvis) position; root_rot: (N, 3, 3) its rotation (columns: body
            x forward, y left, z up); root_vel: (N, 3) its linear velocity, m/s.
        head_pos: (N, 3) head; hand_pos: (N, 2, 3) left, right hand; foot_pos: (N, 2, 3) left,
            right foot (x, y of the ankle, z of the sole's lowest point).
    """

    root_pos: Any
    root_rot: Any
    root_vel: Any
    head_pos: Any = None
    hand_pos: Any = None
    foot_pos: Any = None


@dataclass(frozen=True)
class SkillGoal:
    """What the skill aims at, batched (N environments), world frame; unused fields may be None.

    Attributes:
        target: (N, 3) the root target (sit, climb, lie, prone) or the top surface's centre
            (support).
        box_center: (N, 3), box_rot: (N, 3, 3), box_corners: (N, 8, 3) the object's oriented box.
        long_axis: (N, 2) the object's long horizontal axis, unit (lie, prone).
        stand_point: (N, 3) root position standing beside the object before lying (lie).
        stand_z: (N,) root height standing on the ground near the object (prone).
        ground_z: (N,) ground height under the character (support).
        path: (P, 2) or (N, P, 2) waypoints every 0.1 s (follow); time_s: (N,) seconds since the
            episode start (follow).
    """

    target: Any = None
    box_center: Any = None
    box_rot: Any = None
    box_corners: Any = None
    long_axis: Any = None
    stand_point: Any = None
    stand_z: Any = None
    ground_z: Any = None
    path: Any = None
    time_s: Any = None


def _check(skill: str) -> None:
    if skill not in MODULES:
        raise ValueError(f"unknown skill {skill!r}: one of {', '.join(SKILLS)}")


def current_waypoint(g: SkillGoal):
    """(N, 2) the follow path's waypoint at ``g.time_s``."""
    return follow.sample_path(g.path, g.time_s, [0.0])[:, 0]


def observe(skill: str, s: CharacterState, g: SkillGoal):
    """(N, OBS_SIZE[skill]) the skill's task observation."""
    _check(skill)
    if skill == "follow":
        return follow.observation(s.root_pos, s.root_rot, follow.sample_path(g.path, g.time_s))
    if skill == "sit":
        return sit.observation(s.root_pos, s.root_rot, g.target, g.box_center, g.box_rot, g.box_corners)
    if skill == "climb":
        return climb.observation(s.root_pos, s.root_rot, g.target, g.box_corners)
    if skill == "lie":
        return lie.observation(s.root_pos, s.root_rot, g.target, g.stand_point, g.box_rot, g.box_corners)
    if skill == "prone":
        return prone.observation(s.root_pos, s.root_rot, g.target, g.box_rot, g.box_corners)
    return support.observation(s.root_pos, s.root_rot, g.target, g.box_corners)


def reward(skill: str, s: CharacterState, g: SkillGoal):
    """(N,) the skill's task reward, in [0, 1] (1 at the target)."""
    _check(skill)
    if skill == "follow":
        return follow.reward(s.root_pos, current_waypoint(g))
    if skill == "sit":
        return sit.reward(s.root_pos, s.root_vel, g.target, g.box_center)
    if skill == "climb":
        return climb.reward(s.root_pos, s.root_vel, g.target, g.box_center, s.foot_pos)
    if skill == "lie":
        return lie.reward(s.root_pos, s.root_rot, s.root_vel, s.head_pos, g.target, g.stand_point, g.long_axis)
    if skill == "prone":
        return prone.reward(s.root_pos, s.root_rot, s.root_vel, g.target, g.stand_z, g.long_axis)
    return support.reward(s.root_pos, s.root_rot, s.root_vel, s.hand_pos, s.foot_pos, g.target, g.ground_z)


def error(skill: str, s: CharacterState, g: SkillGoal):
    """(N,) the skill's contact error, metres (the distance the success test thresholds)."""
    _check(skill)
    if skill == "follow":
        return follow.error(s.root_pos, current_waypoint(g))
    if skill == "support":
        return support.error(s.hand_pos, g.target)
    return MODULES[skill].error(s.root_pos, g.target)


def success(skill: str, s: CharacterState, g: SkillGoal):
    """(N,) bool: the paper's success test (apply it at the episode's end)."""
    _check(skill)
    if skill == "support":
        return support.success(s.hand_pos, s.foot_pos, g.target)
    return error(skill, s, g) < SUCCESS_M[skill]
