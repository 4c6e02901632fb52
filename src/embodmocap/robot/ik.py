"""Per-frame differential inverse kinematics with mink: body pose targets -> robot qpos.

Each frame starts from the previous frame's solution (warm start) and takes at most
``iterations`` steps of mink's QP: minimise the weighted position and orientation errors of the
tracked bodies (``FrameTask``) plus a small pull towards the MJCF's zero pose
(``PostureTask``), subject to the joint ranges shrunk by the robot's margin (``ConfigurationLimit``)
and the joints' speed limits (``VelocityLimit``), and the body pairs of the robot's ``avoid_collisions`` kept at least 1 cm
apart (``CollisionAvoidanceLimit``). The speed limits hold across a whole frame: each
step lasts ``1 / (fps * iterations)`` seconds, so all the steps of one frame together move a joint
at most ``limit / fps``. The first frame starts from the MJCF's zero pose placed at the first root
target and has no speed limit (there is no previous frame). The result is clipped to the joint
ranges, so it never violates them even when the solver stops early.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import require
from embodmocap.robot.config import RetargetConfig
from embodmocap.robot.model import RobotModel

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Targets:
    """Pose targets of some robot bodies over T frames.

    Attributes:
        bodies: names of the B tracked bodies.
        pos: (T, B, 3) world positions, metres (NaN = not tracked this frame).
        rot: (T, B, 3, 3) world orientations (ignored where ``rot_weight`` is 0).
        pos_weight: (T, B) position costs.
        rot_weight: (T, B) orientation costs.
    """

    bodies: tuple[str, ...]
    pos: NDArray[np.float64]
    rot: NDArray[np.float64]
    pos_weight: NDArray[np.float64]
    rot_weight: NDArray[np.float64]


def track(robot: RobotModel, targets: Targets, fps: float, cfg: RetargetConfig = RetargetConfig(), *,
          q_start: NDArray | None = None, start_frame: int = 0,
          after_frame: Callable[[int, NDArray], NDArray] | None = None,
          progress: Callable[[int, NDArray], None] | None = None) -> NDArray[np.float64]:
    """Solve frames ``start_frame..T-1`` of ``targets``; returns qpos (T - start_frame, nq).

    Args:
        robot: the loaded robot.
        targets: body targets (see :class:`Targets`).
        fps: frame rate (sets the speed limits' step).
        cfg: iteration counts, tolerance, posture weight, damping.
        q_start: the solution of frame ``start_frame - 1`` (warm start, speed limits from it);
            None = the zero pose at the first root target, no speed limit on the first frame.
        after_frame: ``f(t, qpos) -> qpos`` applied to each frame's solution before it becomes
            the next frame's start (e.g. lifting the robot above the scene).
        progress: ``g(t, qpos)`` called after each frame (checkpoints, progress lines).
    """
    mink = require("mink", "robot")
    model = robot.model
    conf = mink.Configuration(model)
    tasks = {}
    for b in targets.bodies:
        tasks[b] = mink.FrameTask(b, "body", position_cost=1.0, orientation_cost=1.0, lm_damping=cfg.lm_damping)
    posture = mink.PostureTask(model, cost=cfg.posture_weight)
    # Towards the MJCF's zero pose, not the previous frame: joints the targets leave free (an upper
    # arm's twist) then stay near neutral instead of keeping whatever the first frame found.
    posture.set_target(np.array(model.qpos0, np.float64))
    vlim = {n: v for n, v in zip(robot.joint_names, robot.velocity_limit) if np.isfinite(v)}
    limits_first = [mink.ConfigurationLimit(model, min_distance_from_limits=robot.cfg.joint_limit_margin_rad)]
    pairs = [(robot.collision_geoms(a), robot.collision_geoms(b)) for a, b in robot.cfg.avoid_collisions]
    pairs = [(a, b) for a, b in pairs if a and b]
    if pairs:
        limits_first.append(mink.CollisionAvoidanceLimit(model, pairs, minimum_distance_from_collisions=0.01,
                                                         collision_detection_distance=0.15))
    limits = limits_first + ([mink.VelocityLimit(model, vlim)] if vlim else [])
    lo, hi = robot.joint_range[:, 0], robot.joint_range[:, 1]
    jq = robot.joint_qpos

    T = targets.pos.shape[0]
    if q_start is None:
        q = np.array(model.qpos0, np.float64)
        root = targets.bodies.index(robot.cfg.root_body) if robot.cfg.root_body in targets.bodies else None
        if root is not None and np.all(np.isfinite(targets.pos[start_frame, root])):
            q[robot.root_qpos:robot.root_qpos + 3] = targets.pos[start_frame, root]
        first = True
    else:
        q = np.array(q_start, np.float64)
        first = False
    out = np.empty((T - start_frame, model.nq))
    body_ids = [robot.body_id(b) for b in targets.bodies]
    for t in range(start_frame, T):
        active = []
        for i, b in enumerate(targets.bodies):
            pw, rw = float(targets.pos_weight[t, i]), float(targets.rot_weight[t, i])
            if pw <= 0 and rw <= 0 or not np.all(np.isfinite(targets.pos[t, i])):
                continue
            task = tasks[b]
            task.set_position_cost(pw)
            task.set_orientation_cost(rw)
            R = targets.rot[t, i] if rw > 0 else np.eye(3)
            task.set_target(mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(R), targets.pos[t, i]))
            active.append(task)
        conf.update(q)
        iters = cfg.first_frame_iterations if first else cfg.iterations
        dt = 1.0 / (fps * (1 if first else iters))
        prev = conf.data.xpos[body_ids].copy()
        for _ in range(iters):
            v = mink.solve_ik(conf, [*active, posture], dt, solver="daqp", damping=1e-9,
                              limits=limits_first if first else limits)
            conf.integrate_inplace(v, dt)
            now = conf.data.xpos[body_ids].copy()
            moved = float(np.max(np.linalg.norm(now - prev, axis=-1))) if len(body_ids) else 0.0
            prev = now
            if moved < cfg.tolerance_m * (0.01 if first else 1.0):
                break
        q = conf.q.copy()
        q[jq] = np.clip(q[jq], lo, hi)
        a = robot.root_qpos + 3
        q[a:a + 4] /= np.linalg.norm(q[a:a + 4])
        if after_frame is not None:
            q = after_frame(t, q)
        out[t - start_frame] = q
        first = False
        if progress is not None:
            progress(t, q)
    return out
