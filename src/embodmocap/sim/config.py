"""Settings of the simulation package (``embodmocap export --to mjcf`` and ``embodmocap sim``).

Every number a figure depends on is here, each with its unit and effect; defaults live only here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class HumanoidConfig:
    """How the performer's MuJoCo model is built from the fitted body (:mod:`embodmocap.sim.model`)."""

    density_kg_m3: float = 1000.0
    """Body density, kg/m^3: each geom's mass is its volume times this (the human body is close to water)."""
    capsule_radius_percentile: float = 60.0
    """Capsule radius = this percentile of the distances of a body's surface samples from the capsule
    axis (0-100): the median-ish fits the limb's cross-section without swallowing outliers."""
    box_bodies: tuple[str, ...] = ("L_Ankle", "R_Ankle", "L_Toe", "R_Toe")
    """Bodies modelled as boxes (the bounding box of their vertices, body frame) instead of capsules:
    the feet, whose flat soles carry the weight."""
    kp_nm_rad: float = 1000.0
    """PD stiffness of the legs' and spine's position actuators, N m/rad (300 lets a 73 kg body's
    replay of standing sag and fall within 2 s; 1000 holds it)."""
    kp_arm_nm_rad: float = 300.0
    """PD stiffness of the arms, neck, head and hands (shoulder and below, neck and head), N m/rad."""
    kd_ratio_s: float = 0.1
    """PD damping as a fraction of the stiffness, seconds (kd = kd_ratio_s * kp)."""
    max_torque_nm: float = 800.0
    """Largest torque one actuator may apply, N m (legs and spine); arms get a quarter of it."""
    joint_damping: float = 0.5
    """Passive damping of every hinge, N m s/rad (keeps the free fall of an unactuated limb calm)."""
    armature: float = 0.1
    """Inertia added to every hinge, kg m^2: keeps the stiff PD springs of the light distal bodies
    stable at the time step (with 0.02, random actions made 14 of 1,500 steps diverge; 0.1: none)."""
    timestep_s: float = 1.0 / 180.0
    """Physics time step, seconds (6 steps per 30 Hz control step)."""
    friction: float = 1.0
    """Sliding friction coefficient of the body against the scene."""


@dataclass(frozen=True)
class SceneCollisionConfig:
    """How the scene becomes collision geometry (:mod:`embodmocap.sim.scene`)."""

    heightmap_cell_m: float = 0.05
    """Heightfield cell size, metres (the paper samples the scene at 0.05 m)."""
    cap_above_motion_m: float = 0.5
    """Surfaces higher than the performer's highest vertex plus this (ceilings, lamp shades) are no
    support and are left out of the heightfield, metres; a solid wall rising through that height
    becomes a column at the cap."""
    margin_m: float = 0.5
    """The heightfield covers the motion's footprint grown by this much (at least the mesh under it), metres."""
    collision: Literal["heightfield", "coacd", "both"] = "heightfield"
    """Scene collision geometry: the support heightfield, convex pieces of the scene mesh (coacd:
    overhangs such as a table top's underside or the space under a chair stay open), or both.
    The pieces cover the same footprint and cap as the heightfield."""
    coacd_threshold: float = 0.05
    """coacd concavity threshold (its ``threshold``; smaller = more, tighter pieces, slower)."""
    coacd_max_pieces: int = 64
    """At most this many convex pieces per concave part of the mesh (coacd ``max_convex_hull``)."""
    coacd_resolution: int = 50
    """coacd's voxel resolution for making an open (scanned) mesh manifold (``preprocess_resolution``)."""
    convex_tolerance: float = 0.01
    """A closed connected part whose volume is within this fraction of its convex hull's is used
    as its hull directly (the studio's boxes, a box-like scan part), without coacd."""


@dataclass(frozen=True)
class SimCheckConfig:
    """Thresholds of the physical plausibility check (:mod:`embodmocap.sim.check`)."""

    contact_m: float = 0.02
    """A body vertex within this distance of the scene (or inside it) touches it, metres."""
    max_depth_m: float = 0.3
    """A vertex whose closest scene surface is farther than this is neither penetrating nor touching,
    whatever the side: a scanned mesh has holes (no floor under the performer), and the far
    surface's normal says nothing about being inside, metres."""
    skate_height_m: float = 0.025
    """MotionVAE's foot-skating height H: a foot whose lowest point is below H counts, weighted
    ``2 - 2^(h/H)``, metres."""
    vertex_stride: int = 1
    """Use every n-th body vertex (1 = all); larger is faster and coarser."""
    max_contact_points: int = 48
    """Contact points per frame used to explain the root wrench (a subsample of the touching vertices)."""
    friction: float = 1.0
    """Friction coefficient of the contact forces that may explain the motion (the pyramid's slope)."""
    repair_max_m: float = 0.15
    """``--repair``: frames whose lowest point is within this of the support (penetrating or
    floating) are moved onto it; higher ones (a jump) are left alone, metres."""
    repair_smooth: float = 10.0
    """``--repair``: weight of the vertical correction's second difference between frames (larger =
    smoother, less exact contact on abrupt changes; a steady drift is corrected exactly)."""
    side_radius_m: float = 0.3
    """Which side of the scene is solid is read from the closest triangle's normal, voted over the
    scene's surface sheet within this radius of that triangle (area-weighted): a few triangles
    facing the wrong way (a scanned floor patch turned over) are outvoted by the sheet around
    them. Also, a point behind a face that is not a wall (``|n_z| > 0.2``: a floor, a seat, a
    table top's underside) counts as inside only with surface above it within ``max_depth_m`` (a
    solid has a top; the air above a turned-over floor or beside the curled rim of a hole in a
    scanned floor has none). 0 = trust the closest triangle alone (the check's rule before
    both), metres."""
    side_sheet_m: float = 0.01
    """Only surface within this distance of the closest triangle's plane votes (the same sheet;
    the far face of a 4 cm table top or a wall meeting the floor does not), metres."""
    through_surface: bool = True
    """A body vertex behind a scene face penetrates only when its patch of such vertices got
    there through a seen surface (a body mesh edge from it to the outside crosses a face from
    behind); a patch that meets the outside only round an edge lies on the unseen side of an open
    sheet (a calf under a chair seat whose underside the scan never saw) and reads as outside,
    its distance to the sheet as a gap. False = the closest face's side alone decides (the rule
    before session 7)."""
    full_resolution_depth: bool = True
    """How deep a body vertex is inside the scene is measured on the full-resolution mesh (Stage
    I's ``mesh_raw.ply``, faces near the vertex only) rather than on the simplified mesh, which
    still decides which vertices are behind a seen surface (its side vote and ``through_surface``
    need the simplified mesh's smoothness): vertex clustering moves the surface by up to a cell,
    filling concave corners and spreading a lone vertex of the scan's noise over its neighbours'
    5 cm faces (a standing foot beside one read 3.4 cm inside the ground). The full mesh's side is
    voted over its own sheet like the simplified one's (``side_radius_m``, ``side_sheet_m``: a few
    of its triangles face the wrong way). A vertex with no full-resolution surface within its simplified depth plus 10 cm keeps
    the simplified reading. No effect where the scene mesh read is itself the full one."""


@dataclass(frozen=True)
class TrackingConfig:
    """The scene-aware tracking task (:class:`embodmocap.sim.env.TrackingEnv`)."""

    episode_s: float = 10.0
    """Episode length, seconds (the paper: 10 s from a random frame)."""
    control_hz: float = 30.0
    """Policy rate, Hz; the physics takes ``1 / (control_hz * timestep)`` steps per action."""
    future_steps: tuple[int, ...] = (1, 2, 3)
    """Reference frames in the observation, control steps ahead (the paper: T, T+1, T+2)."""
    heightmap_size: int = 11
    """Egocentric height map grid points per side (the paper: 11)."""
    heightmap_spacing_m: float = 0.2
    """Distance between height map points, metres (the paper: 0.2, a 2 m x 2 m patch)."""
    w_pos: float = 0.25
    """Weight of the body position term ``exp(-100 mean |p - p_ref|^2)``."""
    w_rot: float = 0.25
    """Weight of the body rotation term ``exp(-10 mean angle(q, q_ref)^2)``."""
    w_vel: float = 0.25
    """Weight of the linear velocity term ``exp(-0.1 mean |v - v_ref|^2)``."""
    w_angvel: float = 0.25
    """Weight of the angular velocity term ``exp(-0.1 mean |w - w_ref|^2)``."""
    w_smooth: float = 0.02
    """Weight of the paper's jitter penalty ``|a_t - a_{t-1}|^2`` (actions in [-1, 1]^69)."""
    terminate_m: float = 0.5
    """End the episode when the mean body position error exceeds this, metres."""
    random_start: bool = True
    """Start each episode at a random reference frame (the paper); False = always frame 0."""
    root_assist: bool = False
    """Add a residual PD force and torque on the root pulling it to the reference ("hand of God",
    as residual force control does). Off for training the paper's task; used to check that the
    reference itself is reproducible by the actuators."""
    root_assist_kp: float = 2000.0
    """Root assist stiffness, N/m per 70 kg (torque gain is a tenth of it, N m/rad)."""
    success_s: float = 8.0
    """An episode succeeds when it tracks for more than this many seconds (the paper: 8 of 10)."""


@dataclass(frozen=True)
class TrainConfig:
    """PPO training (stable-baselines3) and evaluation of the tracking policy."""

    steps: int = 200_000
    """Environment steps to train for (all environments together)."""
    num_envs: int = 2
    """Parallel environments (one process each when > 1)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Torch device of the policy."""
    seed: int = 0
    """Seed of the policy and of the episodes' start frames."""
    n_steps: int = 512
    """PPO rollout length per environment between updates."""
    batch_size: int = 256
    """PPO minibatch size."""
    learning_rate: float = 3e-4
    """Adam learning rate."""
    checkpoint_every: int = 50_000
    """Save a checkpoint every this many environment steps."""
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    """The task."""
    skill: Literal["follow", "sit", "climb", "lie", "prone", "support"] | None = None
    """Train this interaction skill (``EmbodMocap/Skill-<name>-v0``: task + AMP style reward, clips
    from sequences/SEQ/skills/skills.json) instead of the tracking task."""
    skill_task: SkillConfig = field(default_factory=lambda: SkillConfig())
    """The skill task and its style reward (with ``skill``)."""


@dataclass(frozen=True)
class SkillConfig:
    """An interaction skill task (:class:`embodmocap.sim.skill_env.SkillEnv`) and its AMP style reward."""

    episode_s: float = 10.0
    """Episode length, seconds (the supplement's follow task: 10 s; the same for every skill)."""
    control_hz: float = 30.0
    """Policy rate, Hz."""
    random_start: bool = False
    """Start each episode at a random frame of the clip's approach (before its contact) instead of
    its first frame (AMP's reference state initialisation)."""
    fall_head_m: float = 0.25
    """End the episode (a fall) when the head is lower than this above the scene's floor, metres."""
    w_task: float = 0.5
    """Weight of the task reward in the training reward (TokenHSI / AMP: 0.5)."""
    w_style: float = 0.5
    """Weight of the style (discriminator) reward in the training reward (0.5)."""
    disc_hidden: tuple[int, ...] = (256, 128)
    """Hidden layer widths of the discriminator MLP."""
    disc_lr: float = 1e-4
    """Adam learning rate of the discriminator."""
    disc_grad_penalty: float = 5.0
    """Weight of the discriminator's gradient penalty on real transitions (AMP)."""
    disc_epochs: int = 2
    """Passes over each rollout's transitions per discriminator update."""
