"""A robot's MuJoCo model as the retargeting sees it: names, limits, forward kinematics, soles.

Needs the ``robot`` extra (mujoco); the built-in G1 ships in ``robot/assets``; ``mjlab:`` MJCF
paths need an installed mjlab. The body
order everywhere is MuJoCo's body order without the world body, which is the MJCF's depth-first
order (what mjlab's ``body_pos_w`` uses). Quaternions are w x y z unless a name says ``xyzw``.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError, MissingExtraError, require
from embodmocap.robot.config import ASSETS_PREFIX, MJLAB_PREFIX, RobotConfig


def mujoco_module():
    """The ``mujoco`` module, or one clear line naming the ``robot`` extra."""
    return require("mujoco", "robot")


def resolve_mjcf(cfg: RobotConfig) -> Path:
    """The MJCF file of ``cfg`` on this machine (``embodmocap:`` paths in this package's robot
    assets, ``mjlab:`` paths in an installed mjlab)."""
    if cfg.mjcf.startswith(ASSETS_PREFIX):
        path = Path(__file__).parent / "assets" / cfg.mjcf[len(ASSETS_PREFIX):]
    elif cfg.mjcf.startswith(MJLAB_PREFIX):
        spec = importlib.util.find_spec("mjlab")
        if spec is None or spec.origin is None:
            raise MissingExtraError("mjlab (for an `mjlab:` MJCF path; the built-in G1 needs none)", "robot")
        path = Path(spec.origin).parent / cfg.mjcf[len(MJLAB_PREFIX):]
    else:
        path = Path(cfg.mjcf)
    if not path.is_file():
        raise InputError(path, f"MJCF of robot {cfg.name!r} not found", "fix `mjcf` in the robot config")
    return path


@dataclass
class RobotModel:
    """A loaded robot: ``model`` (mujoco.MjModel), ``data`` (a scratch mujoco.MjData) and ``cfg``."""

    cfg: RobotConfig
    model: object
    data: object
    mjcf: Path

    @classmethod
    def load(cls, cfg: RobotConfig) -> "RobotModel":
        mj = mujoco_module()
        path = resolve_mjcf(cfg)
        try:
            model = mj.MjModel.from_xml_path(str(path))
        except ValueError as err:
            raise InputError(path, f"MuJoCo cannot load the MJCF ({str(err).splitlines()[0]})", "fix the MJCF") from err
        rm = cls(cfg, model, mj.MjData(model), path)
        rm._check()
        return rm

    def _check(self) -> None:
        mj = mujoco_module()
        names = set(self.body_names)
        for b in [self.cfg.root_body, *self.cfg.feet, *self.cfg.hands, *(lk.body for lk in self.cfg.links)]:
            if b not in names:
                raise InputError(self.mjcf, f"robot config {self.cfg.name!r} names body {b!r}, which the MJCF lacks",
                                 "fix the body name in the robot config")
        root = mj.mj_name2id(self.model, mj.mjtObj.mjOBJ_BODY, self.cfg.root_body)
        adr = self.model.body_jntadr[root]
        if adr < 0 or int(self.model.jnt_type[adr]) != int(mj.mjtJoint.mjJNT_FREE):
            raise InputError(self.mjcf, f"root body {self.cfg.root_body!r} has no free joint", "give the root body a <freejoint/>")
        for a, b in self.cfg.avoid_collisions:
            for x in (a, b):
                if x not in names:
                    raise InputError(self.mjcf, f"avoid_collisions names body {x!r}, which the MJCF lacks", "fix avoid_collisions")
        for j in self.cfg.csv_joint_order:
            if j not in self.joint_names:
                raise InputError(self.mjcf, f"csv_joint_order names {j!r}, not a hinge joint of the MJCF", "fix csv_joint_order")

    # ---------------------------------------------------------------- names and indices

    @cached_property
    def body_names(self) -> tuple[str, ...]:
        """Every body but the world, MuJoCo (depth-first) order."""
        mj = mujoco_module()
        return tuple(mj.mj_id2name(self.model, mj.mjtObj.mjOBJ_BODY, i) for i in range(1, self.model.nbody))

    @cached_property
    def hinge_ids(self) -> NDArray[np.int64]:
        """Joint ids of the hinge and slide joints (the robot's joints), MJCF order."""
        mj = mujoco_module()
        t = np.asarray(self.model.jnt_type)
        return np.flatnonzero((t == int(mj.mjtJoint.mjJNT_HINGE)) | (t == int(mj.mjtJoint.mjJNT_SLIDE)))

    @cached_property
    def joint_names(self) -> tuple[str, ...]:
        mj = mujoco_module()
        return tuple(mj.mj_id2name(self.model, mj.mjtObj.mjOBJ_JOINT, int(i)) for i in self.hinge_ids)

    @cached_property
    def joint_qpos(self) -> NDArray[np.int64]:
        """qpos address of each joint of :attr:`joint_names`."""
        return np.asarray(self.model.jnt_qposadr)[self.hinge_ids]

    @cached_property
    def joint_dof(self) -> NDArray[np.int64]:
        """qvel address of each joint of :attr:`joint_names`."""
        return np.asarray(self.model.jnt_dofadr)[self.hinge_ids]

    @cached_property
    def root_qpos(self) -> int:
        mj = mujoco_module()
        root = mj.mj_name2id(self.model, mj.mjtObj.mjOBJ_BODY, self.cfg.root_body)
        return int(self.model.jnt_qposadr[self.model.body_jntadr[root]])

    @cached_property
    def root_dof(self) -> int:
        mj = mujoco_module()
        root = mj.mj_name2id(self.model, mj.mjtObj.mjOBJ_BODY, self.cfg.root_body)
        return int(self.model.jnt_dofadr[self.model.body_jntadr[root]])

    @cached_property
    def joint_range(self) -> NDArray[np.float64]:
        """(J, 2) joint ranges; (-inf, inf) for unlimited joints."""
        r = np.array(self.model.jnt_range)[self.hinge_ids].astype(np.float64)
        lim = np.asarray(self.model.jnt_limited)[self.hinge_ids].astype(bool)
        r[~lim] = (-np.inf, np.inf)
        return r

    @cached_property
    def velocity_limit(self) -> NDArray[np.float64]:
        """(J,) speed limits from the config, rad/s (inf where none)."""
        return np.array([self.cfg.joint_velocity_limit(j) or np.inf for j in self.joint_names])

    @cached_property
    def csv_joints(self) -> tuple[str, ...]:
        """Joint order of the motion CSV."""
        return self.cfg.csv_joint_order or self.joint_names

    def body_id(self, name: str) -> int:
        """MuJoCo body id (1-based: 0 is the world)."""
        return self.body_names.index(name) + 1

    # ---------------------------------------------------------------- state

    def qpos(self, root_pos: NDArray, root_quat_wxyz: NDArray, joint_pos: NDArray) -> NDArray[np.float64]:
        """(T, nq) full qpos from root position (T, 3), root quaternion (T, 4) and joints (T, J)."""
        root_pos = np.asarray(root_pos, np.float64)
        q = np.tile(np.asarray(self.model.qpos0, np.float64), (len(root_pos), 1))
        q[:, self.root_qpos:self.root_qpos + 3] = root_pos
        q[:, self.root_qpos + 3:self.root_qpos + 7] = root_quat_wxyz
        q[:, self.joint_qpos] = joint_pos
        return q

    def split(self, qpos: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Root position (T, 3), root quaternion wxyz (T, 4), joints (T, J) of qpos (T, nq)."""
        q = np.asarray(qpos, np.float64)
        a = self.root_qpos
        return q[:, a:a + 3].copy(), q[:, a + 3:a + 7].copy(), q[:, self.joint_qpos].copy()

    def forward(self, qpos: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Body positions (T, B, 3) and quaternions wxyz (T, B, 4), world, for qpos (T, nq)."""
        mj = mujoco_module()
        q = np.atleast_2d(np.asarray(qpos, np.float64))
        pos = np.empty((len(q), self.model.nbody - 1, 3))
        quat = np.empty((len(q), self.model.nbody - 1, 4))
        for t in range(len(q)):
            self.data.qpos[:] = q[t]
            mj.mj_kinematics(self.model, self.data)
            pos[t] = self.data.xpos[1:]
            quat[t] = self.data.xquat[1:]
        return pos, quat

    def body_velocities(self, qpos: NDArray, qvel: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Linear (T, B, 3) and angular (T, B, 3) world velocities of each body's frame origin.

        ``qvel`` is MuJoCo's: the free joint's linear part in the world frame, its angular part in
        the root body's frame."""
        mj = mujoco_module()
        q = np.atleast_2d(np.asarray(qpos, np.float64))
        v = np.atleast_2d(np.asarray(qvel, np.float64))
        B = self.model.nbody - 1
        lin, ang = np.empty((len(q), B, 3)), np.empty((len(q), B, 3))
        res = np.zeros(6)
        for t in range(len(q)):
            self.data.qpos[:] = q[t]
            self.data.qvel[:] = v[t]
            mj.mj_kinematics(self.model, self.data)
            mj.mj_comPos(self.model, self.data)
            mj.mj_comVel(self.model, self.data)
            for b in range(1, B + 1):
                mj.mj_objectVelocity(self.model, self.data, mj.mjtObj.mjOBJ_XBODY, b, res, 0)  # XBODY: the frame origin
                ang[t, b - 1] = res[:3]
                lin[t, b - 1] = res[3:]
        return lin, ang

    def collision_geoms(self, body: str) -> list[int]:
        """Ids of a body's collision geoms (contype or conaffinity set)."""
        m = self.model
        g = np.flatnonzero(np.asarray(m.geom_bodyid) == self.body_id(body))
        return [int(i) for i in g if m.geom_contype[i] or m.geom_conaffinity[i]]

    # ---------------------------------------------------------------- soles

    def contact_points(self, body: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Points of a body's collision geoms in the body frame and their radii: ``(P (N, 3), r (N,))``.

        The lowest point of the body is min over points of ``z - r`` (capsule and cylinder: both
        end centres with the radius; sphere: centre; box: its 8 corners with radius 0). A body
        without collision geoms gives its origin."""
        mj = mujoco_module()
        m = self.model
        b = self.body_id(body)
        pts, rad = [], []
        for g in np.flatnonzero(np.asarray(m.geom_bodyid) == b):
            if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0:
                continue  # visual only
            R = np.empty(9)
            mj.mju_quat2Mat(R, m.geom_quat[g])
            R = R.reshape(3, 3)
            c, s, t = m.geom_pos[g], m.geom_size[g], int(m.geom_type[g])
            G = mj.mjtGeom
            if t in (int(G.mjGEOM_CAPSULE), int(G.mjGEOM_CYLINDER)):
                for sign in (-1.0, 1.0):
                    pts.append(c + R[:, 2] * sign * s[1])
                    rad.append(s[0])
            elif t == int(G.mjGEOM_SPHERE):
                pts.append(c.copy())
                rad.append(s[0])
            elif t == int(G.mjGEOM_BOX):
                for corner in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T:
                    pts.append(c + R @ (corner * s))
                    rad.append(0.0)
            else:  # a mesh or ellipsoid: its bounding sphere
                pts.append(c.copy())
                rad.append(float(m.geom_rbound[g]))
        if not pts:
            return np.zeros((1, 3)), np.zeros(1)
        return np.array(pts, np.float64), np.array(rad, np.float64)
