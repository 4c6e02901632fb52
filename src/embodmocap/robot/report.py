"""Quality figures of a retargeted motion (``robot_report.json``): pure functions of the result.

Every figure is in SI units (metres, radians, rad/s) and named with its unit where ambiguous.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.heightmap import HeightMap
from embodmocap.robot.model import RobotModel, mujoco_module
from embodmocap.robot.retarget import HumanTargets, true_runs, heights_at, lowest_points


def keypoint_residual(robot: RobotModel, qpos: NDArray, ht: HumanTargets) -> tuple[NDArray[np.float64], list[str]]:
    """``(T, K)`` distance between each position-tracked robot body and the scaled human's joint,
    metres, and the K body names."""
    body_pos, _ = robot.forward(qpos)
    weights = {lk.body: lk.position_weight for lk in robot.cfg.links}
    keep = [i for i, b in enumerate(ht.targets.bodies) if weights.get(b, 0) > 0]
    idx = [robot.body_names.index(ht.targets.bodies[i]) for i in keep]
    return np.linalg.norm(body_pos[:, idx] - ht.scaled[:, keep], axis=-1), [ht.targets.bodies[i] for i in keep]


def joint_speeds(joint_pos: NDArray, fps: float) -> NDArray[np.float64]:
    """(T, J) absolute joint speeds, rad/s (central differences; 0 for a single frame)."""
    q = np.asarray(joint_pos, np.float64)
    return np.abs(np.gradient(q, axis=0)) * fps if len(q) > 1 else np.zeros_like(q)


def foot_figures(robot: RobotModel, qpos: NDArray, contacts: NDArray, hm: HeightMap | None, floor_z: float) -> dict:
    """Skating (horizontal drift of each foot body from where a human contact run began) and
    penetration (lowest foot collision point below the scene's height map)."""
    mj = mujoco_module()
    data = mj.MjData(robot.model)
    fids = [robot.body_id(f) for f in robot.cfg.feet]
    lows = [lowest_points(robot, (f,)) for f in robot.cfg.feet]
    T = len(qpos)
    xy = np.empty((T, 2, 2))
    pen = np.empty((T, 2))
    for t in range(T):
        data.qpos[:] = qpos[t]
        mj.mj_kinematics(robot.model, data)
        for k, (bid, low) in enumerate(zip(fids, lows)):
            xy[t, k] = data.xpos[bid, :2]
            p = low(data.xpos, data.xmat)
            pen[t, k] = float(np.max(heights_at(hm, p[:, :2], floor_z) - p[:, 2]))
    in_contact = np.asarray(contacts, bool)
    gap = -pen  # sole height above the scene
    drift, slide = [], []
    for k in range(2):
        for a, b in true_runs(contacts[:, k]):
            d = np.linalg.norm(xy[a:b, k] - xy[a, k], axis=-1)
            drift.append(float(d.max()))
            if b - a > 1:
                slide.append(np.linalg.norm(np.diff(xy[a:b, k], axis=0), axis=-1))
    steps = np.concatenate(slide) if slide else np.zeros(0)
    return {
        "contact_runs": len(drift),
        "foot_skating_max_m": max(drift) if drift else 0.0,
        "foot_skating_mean_m": float(np.mean(drift)) if drift else 0.0,
        "foot_slide_per_frame_mean_m": float(steps.mean()) if len(steps) else 0.0,
        "foot_penetration_max_m": float(max(pen.max(), 0.0)),
        "foot_penetration_frames_over_1cm": int(np.sum(pen.max(axis=1) > 0.01)),
        "foot_height_min_m": float(-pen.max()),
        "foot_contact_height_max_m": float(gap[in_contact].max()) if in_contact.any() else 0.0,
        "foot_contact_height_mean_m": float(gap[in_contact].mean()) if in_contact.any() else 0.0,
    }


def self_collision_frames(robot: RobotModel, qpos: NDArray, depth_m: float) -> tuple[int, list[int]]:
    """Frames where two of the robot's collision geoms overlap by more than ``depth_m`` (the MJCF's
    own exclusions and parent-child pairs excepted): ``(count, first frames (up to 20))``."""
    mj = mujoco_module()
    data = mj.MjData(robot.model)
    hits = []
    for t in range(len(qpos)):
        data.qpos[:] = qpos[t]
        mj.mj_kinematics(robot.model, data)
        mj.mj_collision(robot.model, data)
        if data.ncon and np.min(data.contact.dist[:data.ncon]) < -depth_m:
            hits.append(t)
    return len(hits), hits[:20]


def robot_report(robot: RobotModel, qpos: NDArray, ht: HumanTargets, fps: float, hm: HeightMap | None,
                 self_collision_depth_m: float = 0.005) -> dict:
    """Every figure of ``robot_report.json`` (see docs/formats.md)."""
    _, _, joints = robot.split(qpos)
    res, names = keypoint_residual(robot, qpos, ht)
    lo, hi = robot.joint_range.T
    violations = (joints < lo - 1e-9) | (joints > hi + 1e-9)
    speed = joint_speeds(joints, fps)
    peak = speed.max(axis=0) if len(speed) else np.zeros(len(robot.joint_names))
    vlim = robot.velocity_limit
    ratio = np.where(np.isfinite(vlim), peak / vlim, 0.0)
    worst = int(np.argmax(ratio)) if len(ratio) else 0
    n_self, first_self = self_collision_frames(robot, qpos, self_collision_depth_m)
    return {
        "robot": robot.cfg.name,
        "frames": int(len(qpos)),
        "fps": float(fps),
        "scale": float(ht.scale),
        "floor_z_m": float(ht.floor_z),
        "keypoint_residual_mean_m": float(res.mean()) if res.size else 0.0,
        "keypoint_residual_max_m": float(res.max()) if res.size else 0.0,
        "keypoint_residual_per_body_mean_m": {b: float(v) for b, v in zip(names, res.mean(axis=0))}
        if res.size else {},
        "joint_limit_violations": int(violations.sum()),
        "joint_speed_peak_rad_s": {j: float(v) for j, v in zip(robot.joint_names, peak)},
        "joint_speed_limit_rad_s": {j: (float(v) if np.isfinite(v) else None) for j, v in zip(robot.joint_names, vlim)},
        "joint_speed_max_ratio": float(ratio[worst]) if len(ratio) else 0.0,
        "joint_speed_worst_joint": robot.joint_names[worst] if len(ratio) else None,
        "joint_speed_over_limit_joints": int(np.sum(ratio > 1.0 + 1e-9)),
        **foot_figures(robot, qpos, ht.contacts, hm, ht.floor_z),
        "self_collision_frames": n_self,
        "self_collision_first_frames": first_self,
        "human_contact_fraction": [float(c) for c in ht.contacts.mean(axis=0)] if len(qpos) else [0.0, 0.0],
    }
