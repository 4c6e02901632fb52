"""Settings of the skill clip finder (``embodmocap skills``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SkillsConfig:
    """How contacts are found and turned into skill clips (docs/skills.md explains each rule)."""

    cell_m: float = 0.02
    """Cell of the scene height map the surfaces are found on, metres."""
    cap_above_floor_m: float = 1.9
    """Surfaces higher than this above the floor are ignored (ceilings, shelf tops), metres."""
    surface_min_height_m: float = 0.1
    """A surface is at least this far above the floor (lower ones are floor), metres."""
    surface_step_m: float = 0.03
    """Neighbouring height-map cells more than this apart in height belong to different surfaces, metres."""
    surface_min_area_m2: float = 0.04
    """Smaller surfaces are ignored (noise, edges), square metres."""
    contact_above_m: float = 0.04
    """A body vertex up to this far above a surface touches it, metres."""
    contact_below_m: float = 0.10
    """A body vertex up to this far below a surface (inside it: fitting error) touches it, metres."""
    min_part_vertices: int = 8
    """A body part touches a surface when at least this many of its vertices do."""
    foot_on_floor_m: float = 0.025
    """A foot whose lowest vertex is at most this far above the floor stands on it, metres."""
    lowered_m: float = 0.05
    """Sit / lie / prone clips span the frames with the pelvis at least this far below its standing
    height, metres."""
    lying_pitch_deg: float = 60.0
    """Lying (on the back or the front): the pelvis-to-neck axis at least this far from vertical, degrees."""
    upright_pitch_deg: float = 45.0
    """Sitting, climbing: the pelvis-to-neck axis at most this far from vertical, degrees (support has no
    such limit: leaning on a table may bend the torso further)."""
    long_surface_m: float = 1.2
    """Lying needs a surface at least this long (its longer side), metres."""
    climb_min_height_m: float = 0.1
    """Climbing: the surface both feet stand on is at least this far above the floor, metres."""
    feet_together_m: float = 0.4
    """Support: the ankles at most this far apart, metres."""
    posture_speed_mps: float = 0.02
    """Sit, lie, prone and support clips extend outward (from the lowered pelvis, from the hands'
    hold) while the posture keeps changing: the mean speed of the joints relative to the pelvis
    in the heading frame above this, m/s, or above ``noise_factor`` times the motion's own
    noise floor (the median speed of its quietest quarter of frames) when that is higher."""
    posture_away_m: float = 0.03
    """... or while the joints (relative to the pelvis, heading frame) are on average this far
    from the standing posture (the median over the frames standing still), metres, or
    ``noise_factor`` times their distance on those frames when that is higher."""
    noise_factor: float = 2.0
    """How far above the motion's noise floor a speed must be to count as moving (a fit's jitter
    moves the joints of a still body)."""
    smooth_s: float = 0.3
    """Joint positions are averaged over this window before any speed is taken, seconds."""
    min_hold_s: float = 0.3
    """Shortest contact hold of an interaction clip, seconds."""
    gap_s: float = 0.2
    """Contact drop-outs shorter than this inside a hold are bridged, seconds."""
    follow_speed_mps: float = 0.2
    """Walking: the pelvis moves at least this fast over the ground, m/s."""
    follow_gap_s: float = 1.5
    """Walking runs separated by less than this (a turn on the spot) are one follow clip, seconds."""
    follow_min_s: float = 2.0
    """Shortest follow clip, seconds."""
    path_dt_s: float = 0.1
    """Follow: spacing of the path's waypoints, seconds (the supplement's 0.1 s)."""
    sit_target_above_m: float = 0.10
    """Sit target: this far above the centre of the seat's top (the supplement's 10 cm), metres."""
    climb_target_above_m: float = 0.94
    """Climb target: this far above the centre of the top (the supplement's 94 cm), metres."""
    lie_target_above_m: float = 0.10
    """Lie / prone target: this far above the centre of the surface the body lies on, metres."""
    chunk_frames: int = 256
    """Frames posed at once (bounds memory)."""
