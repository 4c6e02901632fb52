"""The retargeting's decisions as pure functions: the world motion, the body model, the scene mesh
and the robot in, the robot's motion and its report out; no paths, no file I/O
(:mod:`embodmocap.robot.stage` reads, checkpoints and writes).

1. :func:`robot_inputs`: the body's joints over the motion, the scene's ground height map around
   them and the human's rest proportions;
2. :func:`retarget_motion`: the robot's motion (:func:`~embodmocap.robot.retarget.retarget`);
3. :func:`motion_report`: its quality figures (``robot_report.json``'s content).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import NDArray

from embodmocap.robot.config import RetargetConfig
from embodmocap.types import SmplParams

if TYPE_CHECKING:
    from embodmocap.geometry.heightmap import HeightMap
    from embodmocap.robot.retarget import HumanRest


@dataclass(frozen=True)
class RobotInputs:
    """What the retargeting needs of the human and the scene.

    Attributes:
        params: the world SMPL motion (T frames, Z up, metres).
        joints: (T, 24, 3) its SMPL joints in the world.
        human: the human's rest proportions (:class:`~embodmocap.robot.retarget.HumanRest`).
        heightmap: the scene's ground height map around the motion (None without ground).
    """

    params: SmplParams
    joints: NDArray[np.float64]
    human: "HumanRest"
    heightmap: "HeightMap | None"


def robot_inputs(params: SmplParams, body, mesh_vertices: NDArray, mesh_faces: NDArray,
                 config: RetargetConfig) -> RobotInputs:
    """The body's joints (posed by ``body``), the ground height map of the scene mesh ((N, 3), (F, 3))
    around them (cell ``config.heightmap_cell_m``) and the human's rest proportions."""
    import torch

    from embodmocap.robot.retarget import HumanRest, ground_heightmap

    with torch.no_grad():
        joints = body.from_params(params, dtype=torch.float64).joints.numpy()
    hm = ground_heightmap(mesh_vertices, mesh_faces, joints, cell_m=config.heightmap_cell_m)
    return RobotInputs(params, joints, HumanRest.of(body, params.betas), hm)


def retarget_motion(rm, inp: RobotInputs, config: RetargetConfig, q_done: NDArray | None = None,
                    progress: Callable[[int, NDArray], None] | None = None):
    """The robot's motion ``(qpos (T, nq), human targets)``; ``q_done`` (the first frames, solved
    before) are kept, ``progress(t, q)`` is called per frame solved."""
    from embodmocap.robot.retarget import retarget

    return retarget(rm, inp.params, inp.joints, inp.human, inp.heightmap, config, q_done=q_done, progress=progress)


def motion_report(rm, q: NDArray, inp: RobotInputs, config: RetargetConfig) -> dict:
    """The quality figures of the robot's motion ``q`` (T, nq): ``robot_report.json``'s figures."""
    from embodmocap.robot.report import robot_report
    from embodmocap.robot.retarget import human_targets

    ht = human_targets(rm, inp.params, inp.joints, inp.human, inp.heightmap, config)
    return robot_report(rm, q, ht, inp.params.fps, inp.heightmap, config.self_collision_depth_m)
