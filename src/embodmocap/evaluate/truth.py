"""The synthetic studio's ground truth of a sequence, moved into Stage I's world and indexed by
sequence frame: what :mod:`embodmocap.evaluate.session` and the monocular errors
(:mod:`embodmocap.evaluate.mono`) compare against."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.transforms import invert_T
from embodmocap.io.ground_truth import read_truth_scene_device, read_truth_sequence
from embodmocap.io.layout import SessionLayout
from embodmocap.io.stage_files import read_cameras


@dataclass(frozen=True)
class SequenceTruth:
    """Ground truth of one sequence in Stage I's world, indexed by sequence frame.

    Attributes:
        joints: (T, 24, 3) SMPL joints, metres.
        T_world_vio: view -> (4, 4) the view's VIO world in Stage I's world.
        T_world_cam: view -> (T, 4, 4) true cameras.
        sync_frame: view -> true raw frame of the sync event.
        valid: (T,) bool sequence frames inside the scripted motion.
    """

    joints: NDArray[np.float64]
    T_world_vio: dict[str, NDArray[np.float64]]
    T_world_cam: dict[str, NDArray[np.float64]]
    sync_frame: dict[str, int]
    valid: NDArray[np.bool_]


def sequence_truth(lay: SessionLayout, scene: str, seq: str) -> SequenceTruth:
    """The synthetic truth of ``seq`` moved into Stage I's world and indexed by sequence frame."""
    gt = lay.ground_truth
    T_world_scene = invert_T(read_truth_scene_device(gt.scene_device(scene))["T_scene_vio"])
    g = read_truth_sequence(gt.sequence(seq))
    views = lay.sequence(seq).views()
    raw = read_cameras(lay.sequence(seq).view(views[0]).cameras).raw_frames.astype(np.int64)
    motion = int(g[f"{views[0]}_motion_start"]) + raw
    M_frames = len(g["joints_smpl24"])
    valid = (motion >= 0) & (motion < M_frames)
    j = g["joints_smpl24"][np.clip(motion, 0, M_frames - 1)]
    joints = j @ T_world_scene[:3, :3].T + T_world_scene[:3, 3]
    cams, vio = {}, {}
    for v in views:
        raw_v = read_cameras(lay.sequence(seq).view(v).cameras).raw_frames.astype(np.int64)
        cams[v] = T_world_scene @ g[f"{v}_T_scene_cam"][raw_v]
        vio[v] = T_world_scene @ g[f"{v}_T_scene_vio"]
    return SequenceTruth(joints, vio, cams, {v: int(g[f"{v}_sync_frame"]) for v in views}, valid)
