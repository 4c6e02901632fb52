"""The viewer's robot layer: a retargeted robot (``sequences/<seq>/robot/<robot>/qpos.npz``) drawn
with its own visual meshes, one scene node per mesh geom, moved every frame.

Needs the ``robot`` extra (mujoco) and the robot's MJCF; the robot's config is read back from the
robot folder's stage manifest (so a robot given by ``--robot-config`` shows without it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.layout import SessionLayout
from embodmocap.io.stage_files import read_stage_record


def find_robot(session: Path, seq: str, robot: str) -> Path | None:
    """The robot folder to show: ``robot`` by name, the first one with a ``qpos.npz`` for
    ``"auto"``, None for ``"none"`` or when there is none."""
    root = SessionLayout(session).sequence(seq).robots_dir
    if robot == "none" or not root.is_dir():
        return None
    if robot != "auto":
        d = root / robot
        if not (d / "qpos.npz").is_file():
            raise InputError(d / "qpos.npz", f"no retargeted motion of robot {robot!r}",
                             f"run `embodmocap robot retarget {session} --seq {seq} --robot {robot}` first")
        return d
    found = sorted(p.parent for p in root.glob("*/qpos.npz"))
    return found[0] if found else None


@dataclass
class RobotFrames:
    """Per-frame poses of a robot's visual mesh geoms.

    Attributes:
        name: the robot's name.
        meshes: one ``(vertices (V, 3) mesh frame, faces (F, 3))`` per visual mesh geom.
        pos: (T, G, 3) world position of each geom per motion row.
        wxyz: (T, G, 4) world orientation of each geom per motion row.
    """

    name: str
    meshes: list[tuple[NDArray[np.float32], NDArray[np.uint32]]]
    pos: NDArray[np.float64]
    wxyz: NDArray[np.float64]

    @classmethod
    def load(cls, folder: Path) -> "RobotFrames":
        from embodmocap.robot.config import robot_config_from_record
        from embodmocap.robot.files import read_qpos
        from embodmocap.robot.g1 import BUILTIN_ROBOTS
        from embodmocap.robot.model import RobotModel, mujoco_module

        mj = mujoco_module()
        manifest = folder / "manifest.json"
        rec = read_stage_record(manifest).config.get("robot") if manifest.is_file() else None
        cfg = robot_config_from_record(rec) if rec else BUILTIN_ROBOTS.get(folder.name)
        if cfg is None:
            raise InputError(manifest, "cannot tell which robot this is", "run `embodmocap robot retarget` again")
        rm = RobotModel.load(cfg)
        q = read_qpos(folder / "qpos.npz")
        qpos = rm.qpos(q["root_pos"], q["root_quat_wxyz"], q["joint_pos"])
        m = rm.model
        geoms = [g for g in range(m.ngeom) if int(m.geom_type[g]) == int(mj.mjtGeom.mjGEOM_MESH)
                 and m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0]
        meshes = []
        for g in geoms:
            k = int(m.geom_dataid[g])
            v0, nv = int(m.mesh_vertadr[k]), int(m.mesh_vertnum[k])
            f0, nf = int(m.mesh_faceadr[k]), int(m.mesh_facenum[k])
            meshes.append((np.array(m.mesh_vert[v0:v0 + nv], np.float32), np.array(m.mesh_face[f0:f0 + nf], np.uint32)))
        data = mj.MjData(m)
        T, G = len(qpos), len(geoms)
        pos, wxyz = np.empty((T, G, 3)), np.empty((T, G, 4))
        quat = np.empty(4)
        for t in range(T):
            data.qpos[:] = qpos[t]
            mj.mj_kinematics(m, data)
            pos[t] = data.geom_xpos[geoms]
            for i, g in enumerate(geoms):
                mj.mju_mat2Quat(quat, data.geom_xmat[g])
                wxyz[t, i] = quat
        return cls(cfg.name, meshes, pos, wxyz)
