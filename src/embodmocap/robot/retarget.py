"""World SMPL motion -> robot body targets -> robot motion, in the captured scene.

**Scaling (leg length).** ``s = L_robot / L_human`` where a leg length is hip -> knee -> ankle
(the bodies the robot config maps to ``left_hip``, ``left_knee``, ``left_ankle`` and the right ones,
mean of both legs) measured in each one's rest pose (SMPL's zero pose at the performer's betas; the
MJCF's zero pose), so a robot with shorter legs gets a proportionally smaller copy of the motion.
(``scale_from = "height"`` uses the robot's ``height_m`` over the performer's rest height.)

**The scaled human.** Every SMPL joint ``x`` is mapped to ``a + s (x - a)`` where the anchor ``a``
is the floor height under the performer (the median of the scene's height map) and, horizontally,
the mean pelvis position of the sequence. A similarity keeps every still point still, so a foot
that stands still for the human stands still for the robot and the feet stay on the floor; its
cost is that the path shrinks towards the anchor (furniture contacts are off by ``(1 - s)`` times
their distance to it). With ``keep_path`` the pelvis follows the human's path at full size
instead. Then the whole scaled body is lowered by ``s * a_h - a_r`` (``a_h``: the human's ankle
height above the sole at rest, ``a_r``: the robot foot body's height above its lowest collision
point at its zero pose), so the robot's soles, not its ankles, meet the floor.

**Targets.** A link's position target is its joint's scaled position; its orientation target is
the joint's world rotation composed with the change of axes from SMPL's canonical frame (x left,
y up, z forward) to the robot's (x forward, y left, z up) and the body's rest rotation in the
robot's zero pose. The root's target is moved by the difference between the robot's and the scaled
human's pelvis-above-hips offsets (rest poses, root frame), so that the root and hip targets agree.

**Contacts.** A human foot is in contact when its ankle is within ``contact_height_m`` of its
rest height above the scene and moves slower than ``contact_speed_mps`` horizontally, for at least
``contact_min_frames`` frames. During a contact run the robot foot's target (position and
orientation) stays at its value at the run's first frame, with ``foot_pin_weight`` times its cost.

**Above the scene.** After each frame's IK the robot is lifted (root z) by the deepest penetration
of any foot or hand collision point below the scene's height map at its (x, y).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from embodmocap.body.humanoid import R_HUMANOID_SMPL
from embodmocap.body.joints import SMPL_JOINT_NAMES, SMPL_PARENTS
from embodmocap.geometry.heightmap import HeightMap
from embodmocap.geometry.rotations import quat_to_matrix, rotvec_to_matrix, wxyz_to_xyzw
from embodmocap.robot.config import RetargetConfig
from embodmocap.robot.ik import Targets, track
from embodmocap.robot.model import RobotModel, mujoco_module
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: The change of axes from SMPL's canonical frame to a robot body frame (x forward, y left, z up).
C_ROBOT_SMPL = R_HUMANOID_SMPL


def heights_at(hm: HeightMap | None, xy: NDArray, fill: float) -> NDArray[np.float64]:
    """(...,) scene height under points (..., 2) from the nearest height-map cell; ``fill`` outside
    the map, on empty cells, or without a map."""
    xy = np.asarray(xy, np.float64)
    if hm is None:
        return np.full(xy.shape[:-1], fill)
    col = np.floor((xy[..., 0] - hm.origin[0]) / hm.cell_m).astype(np.int64)
    row = np.floor((xy[..., 1] - hm.origin[1]) / hm.cell_m).astype(np.int64)
    H, W = hm.heights.shape
    inside = (row >= 0) & (row < H) & (col >= 0) & (col < W)
    h = hm.heights[np.clip(row, 0, H - 1), np.clip(col, 0, W - 1)].astype(np.float64)
    return np.where(inside & np.isfinite(h), h, fill)


def floor_height(hm: HeightMap | None, fallback: float) -> float:
    """The floor's height: the median of the height map's cells (the floor covers most of a room)."""
    if hm is None or not np.isfinite(hm.heights).any():
        return float(fallback)
    return float(np.nanmedian(hm.heights))


def smpl_global_rotations(params: SmplParams) -> NDArray[np.float64]:
    """(T, 24, 3, 3) world rotation of every SMPL joint's frame (chain of the local rotations)."""
    T = len(params)
    local = rotvec_to_matrix(params.poses.reshape(T, 24, 3))
    glob = np.empty_like(local)
    for j, p in enumerate(SMPL_PARENTS):  # parents come before children
        glob[:, j] = local[:, j] if p < 0 else glob[:, p] @ local[:, j]
    return glob


@dataclass(frozen=True)
class HumanRest:
    """What the retargeting needs of the performer's rest pose (SMPL canonical frame, metres)."""

    joints: NDArray[np.float64]
    """(24, 3) rest joints."""
    ankle_height_m: float
    """Mean ankle joint height above the lowest vertex (the sole)."""
    height_m: float
    """Rest height (top vertex minus lowest vertex)."""

    @classmethod
    def of(cls, model, betas: NDArray) -> "HumanRest":
        import torch

        z = np.zeros((1, 3))
        out = model.forward(betas, z, np.zeros((1, 69)), z, dtype=torch.float64)
        v = out.vertices.numpy()[0]
        j = out.joints.numpy()[0]
        low = v[:, 1].min()
        ankles = j[[SMPL_JOINT_NAMES.index("left_ankle"), SMPL_JOINT_NAMES.index("right_ankle")], 1]
        return cls(model.rest_joints(betas), float(ankles.mean() - low), float(v[:, 1].max() - low))


@dataclass(frozen=True)
class RobotRest:
    """The robot's zero pose (root at the origin, identity)."""

    pos: dict[str, NDArray]
    """Body name -> (3,) rest position."""
    rot: dict[str, NDArray]
    """Body name -> (3, 3) rest rotation."""
    foot_height_m: float
    """Mean height of the foot bodies' origins above their lowest collision points."""

    @classmethod
    def of(cls, robot: RobotModel) -> "RobotRest":
        q = np.array(robot.model.qpos0, np.float64)
        q[robot.root_qpos:robot.root_qpos + 7] = [0, 0, 0, 1, 0, 0, 0]
        P, Q = robot.forward(q[None])
        R = quat_to_matrix(wxyz_to_xyzw(Q[0]))
        pos = {n: P[0, i] for i, n in enumerate(robot.body_names)}
        rot = {n: R[i] for i, n in enumerate(robot.body_names)}
        heights = []
        for f in robot.cfg.feet:
            pts, r = robot.contact_points(f)
            heights.append(-float(np.min((rot[f] @ pts.T).T[:, 2] - r)))
        return cls(pos, rot, float(np.mean(heights)))


def _leg_length(points: Callable[[str], NDArray]) -> float:
    legs = []
    for side in ("left", "right"):
        a, b, c = (points(f"{side}_{j}") for j in ("hip", "knee", "ankle"))
        legs.append(np.linalg.norm(b - a) + np.linalg.norm(c - b))
    return float(np.mean(legs))


def retarget_scale(robot: RobotModel, human: HumanRest, robot_rest: RobotRest, cfg: RetargetConfig) -> float:
    """The scale ``s`` of the human motion (module docstring)."""
    if cfg.scale is not None:
        return float(cfg.scale)
    if cfg.scale_from == "height":
        return robot.cfg.height_m / human.height_m
    if cfg.scale_from != "leg":
        raise ValueError(f"scale_from must be 'leg' or 'height', got {cfg.scale_from!r}")
    robot_leg = _leg_length(lambda j: robot_rest.pos[_link(robot, j).body])
    human_leg = _leg_length(lambda j: human.joints[SMPL_JOINT_NAMES.index(j)])
    return robot_leg / human_leg


def _link(robot: RobotModel, smpl_joint: str):
    lk = robot.cfg.link(smpl_joint)
    if lk is None:
        from embodmocap.errors import InputError

        raise InputError(None, f"robot config {robot.cfg.name!r} maps no body to SMPL joint {smpl_joint!r}",
                         "the leg bodies (hips, knees, ankles) must be mapped: they measure the scale")
    return lk


@dataclass(frozen=True)
class HumanTargets:
    """The scaled human and what the IK tracks.

    Attributes:
        targets: the IK's targets (feet pinned during contacts).
        scaled: (T, B, 3) the scaled human's link positions before pinning (what residuals are
            measured against), same bodies as ``targets``.
        contacts: (T, 2) left/right human foot contact.
        scale: the scale ``s``.
        floor_z: the floor height used as the vertical anchor, metres.
        joints: (T, 24, 3) the human's world joints (unscaled).
    """

    targets: Targets
    scaled: NDArray[np.float64]
    contacts: NDArray[np.bool_]
    scale: float
    floor_z: float
    joints: NDArray[np.float64]


def human_targets(robot: RobotModel, params: SmplParams, joints: NDArray, human: HumanRest,
                  heightmap: HeightMap | None, cfg: RetargetConfig = RetargetConfig()) -> HumanTargets:
    """Body targets of the robot for the human motion ``params`` with world joints ``joints`` (T, 24, 3)."""
    rest = RobotRest.of(robot)
    s = retarget_scale(robot, human, rest, cfg)
    X = np.asarray(joints, np.float64)
    T = len(X)
    iL, iR = SMPL_JOINT_NAMES.index("left_ankle"), SMPL_JOINT_NAMES.index("right_ankle")
    ankles = X[:, [iL, iR]]
    floor = floor_height(heightmap, float(np.percentile(ankles[..., 2], 5)) - human.ankle_height_m)

    # The similarity (module docstring), then the sole correction.
    if cfg.keep_path:
        centre = X[:, :1].copy()
        centre[..., 2] = floor
        Xs = centre + s * (X - centre)
    else:
        anchor = np.array([*X[:, 0, :2].mean(axis=0), floor])
        Xs = anchor + s * (X - anchor)
    Xs[..., 2] -= s * human.ankle_height_m - rest.foot_height_m

    Rg = smpl_global_rotations(params)  # (T, 24, 3, 3)
    links = [lk for lk in robot.cfg.links if lk.position_weight > 0 or lk.orientation_weight > 0]
    bodies = tuple(lk.body for lk in links)
    jidx = [SMPL_JOINT_NAMES.index(lk.smpl_joint) for lk in links]
    pos = Xs[:, jidx].copy()
    rot = np.stack([Rg[:, j] @ C_ROBOT_SMPL.T @ rest.rot[b] for j, b in zip(jidx, bodies)], axis=1)
    pw = np.tile([lk.position_weight for lk in links], (T, 1)).astype(np.float64)
    rw = np.tile([lk.orientation_weight for lk in links], (T, 1)).astype(np.float64)

    # Root: the robot's and the scaled human's pelvis-above-hips offsets differ (rest poses).
    root = robot.cfg.root_body
    if root in bodies and robot.cfg.link("left_hip") and robot.cfg.link("right_hip"):
        i = bodies.index(root)
        hips_r = (rest.pos[robot.cfg.link("left_hip").body] + rest.pos[robot.cfg.link("right_hip").body]) / 2
        J = human.joints
        hips_h = (J[SMPL_JOINT_NAMES.index("left_hip")] + J[SMPL_JOINT_NAMES.index("right_hip")]) / 2
        j_root = SMPL_JOINT_NAMES.index(links[i].smpl_joint)
        d_r = rest.rot[root].T @ (rest.pos[root] - hips_r)
        d_h = C_ROBOT_SMPL @ (J[j_root] - hips_h)
        pos[:, i] += np.einsum("tab,b->ta", rot[:, i], d_r - s * d_h)
    scaled = pos.copy()

    # Foot contacts of the human, and pins.
    ground = heights_at(heightmap, ankles[..., :2], floor)
    speed = np.zeros((T, 2))
    if T > 1:
        speed = np.linalg.norm(np.gradient(ankles[..., :2], axis=0), axis=-1) * params.fps
    contacts = (ankles[..., 2] - ground - human.ankle_height_m <= cfg.contact_height_m) & (speed <= cfg.contact_speed_mps)
    for side, foot in enumerate(robot.cfg.feet):
        runs = true_runs(contacts[:, side])
        keep = np.zeros(T, bool)
        if foot not in bodies:
            continue
        i = bodies.index(foot)
        for a, b in runs:
            if b - a < cfg.contact_min_frames:
                continue
            keep[a:b] = True
            pos[a:b, i] = pos[a, i]
            rot[a:b, i] = rot[a, i]
            pw[a:b, i] *= cfg.foot_pin_weight
            rw[a:b, i] = max(rw[a, i], 0.1) * cfg.foot_pin_weight
        contacts[:, side] = keep
    return HumanTargets(Targets(bodies, pos, rot, pw, rw), scaled, contacts, s, floor, X)


def true_runs(mask: NDArray) -> list[tuple[int, int]]:
    """``(start, end)`` (end exclusive) of every run of True in a 1-D mask."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[::2].tolist(), d[1::2].tolist()))


def lowest_points(robot: RobotModel, bodies: tuple[str, ...]):
    """A function ``f(xpos (nbody, 3), xmat (nbody, 9)) -> (N, 3)`` giving the lowest points of the
    collision geoms of ``bodies`` (each contact point lowered by its radius), world frame."""
    parts = []
    for b in bodies:
        pts, r = robot.contact_points(b)
        parts.append((robot.body_id(b), pts, r))

    def f(xpos: NDArray, xmat: NDArray) -> NDArray:
        out = []
        for bid, pts, r in parts:
            w = xpos[bid] + pts @ xmat[bid].reshape(3, 3).T
            w[:, 2] -= r
            out.append(w)
        return np.concatenate(out)

    return f


def lift_above_scene(robot: RobotModel, heightmap: HeightMap | None, floor_z: float) -> Callable[[int, NDArray], NDArray]:
    """``after_frame`` for :func:`embodmocap.robot.ik.track`: raise the root by the deepest
    penetration of a foot or hand collision point below the scene's height map."""
    mj = mujoco_module()
    low = lowest_points(robot, (*robot.cfg.feet, *robot.cfg.hands))
    data = mj.MjData(robot.model)
    z = robot.root_qpos + 2

    def after(t: int, q: NDArray) -> NDArray:
        data.qpos[:] = q
        mj.mj_kinematics(robot.model, data)
        p = low(data.xpos, data.xmat)
        pen = float(np.max(heights_at(heightmap, p[:, :2], floor_z) - p[:, 2]))
        if pen > 0:
            q = q.copy()
            q[z] += pen
        return q

    return after


def retarget(robot: RobotModel, params: SmplParams, joints: NDArray, human: HumanRest, heightmap: HeightMap | None,
             cfg: RetargetConfig = RetargetConfig(), *, q_done: NDArray | None = None,
             progress: Callable[[int, NDArray], None] | None = None) -> tuple[NDArray[np.float64], HumanTargets]:
    """Retarget a whole sequence: ``(qpos (T, nq), targets)``.

    ``q_done`` (K, nq): frames already solved by an interrupted run; solving resumes at frame K
    warm-started from its last one."""
    ht = human_targets(robot, params, joints, human, heightmap, cfg)
    start = 0 if q_done is None else len(q_done)
    q_start = None if q_done is None or start == 0 else q_done[-1]
    after = lift_above_scene(robot, heightmap, ht.floor_z)
    rest = track(robot, ht.targets, params.fps, cfg, q_start=q_start, start_frame=start, after_frame=after, progress=progress)
    q = rest if start == 0 else np.concatenate([q_done, rest])
    return q, ht


def ground_heightmap(vertices: NDArray, faces: NDArray, joints: NDArray, cell_m: float = 0.05,
                     headroom_m: float = 0.25) -> HeightMap:
    """The scene's height map of what the performer can stand or sit on.

    :func:`embodmocap.geometry.heightmap.support_heightmap` capped at the performer's highest joint
    over the sequence plus ``headroom_m`` (the plain highest-surface map is the ceiling indoors);
    walls rising through the cap stay solid at the cap. ``joints`` (T, 24, 3) world."""
    from embodmocap.geometry.heightmap import support_heightmap

    cap = float(np.nanmax(np.asarray(joints)[..., 2])) + headroom_m
    try:
        return support_heightmap(vertices, faces, cap, cell_m=cell_m)
    except ValueError:
        raise ValueError("no scene surface below the performer's head: is the scene Z up, in metres?") from None
