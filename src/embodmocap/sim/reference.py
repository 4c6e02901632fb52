"""Reference clips resampled at the control rate, with the body states the tracking task compares.

A clip is one fitted sequence: its qpos (:func:`embodmocap.sim.model.reference_qpos`) is resampled
at ``control_hz`` (linear for positions and hinge angles, slerp for the root quaternion), and MuJoCo
forward kinematics gives every body's world position, orientation and (by finite differences)
linear and angular velocity. Past its end a clip holds its last frame at rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from embodmocap.geometry.heightmap import HeightMap
from embodmocap.geometry.rotations import matrix_to_rotvec, quat_to_matrix, wxyz_to_xyzw, xyzw_to_wxyz


@dataclass(frozen=True)
class Clip:
    """One reference clip at the control rate (N samples, B = 24 bodies).

    Attributes:
        name: ``<session folder name>/<sequence>``.
        xml: MJCF of the performer in the clip's scene (no keyframes).
        heightmap: the scene's support height map.
        qpos: (N, 76), qvel: (N, 75) reference state.
        xpos: (N, B, 3) body positions, xquat: (N, B, 4) orientations (wxyz), vel: (N, B, 3)
            linear and angvel: (N, B, 3) angular velocities, world frame.
        dt: seconds between samples.
    """

    name: str
    xml: str
    heightmap: HeightMap
    qpos: NDArray
    qvel: NDArray
    xpos: NDArray
    xquat: NDArray
    vel: NDArray
    angvel: NDArray
    dt: float

    def __len__(self) -> int:
        return len(self.qpos)


def resample_qpos(qpos: NDArray, fps: float, hz: float) -> NDArray[np.float64]:
    """(N, NQ) qpos at ``hz`` from (T, NQ) at ``fps``: linear, root quaternion by slerp."""
    q = np.asarray(qpos, dtype=np.float64)
    T = len(q)
    if T == 1:
        return q.copy()
    t_src = np.arange(T) / fps
    n = int(np.floor(t_src[-1] * hz + 1e-9)) + 1
    t = np.arange(n) / hz
    out = np.empty((n, q.shape[1]))
    for c in list(range(3)) + list(range(7, q.shape[1])):
        out[:, c] = np.interp(t, t_src, q[:, c])
    rot = Rotation.from_quat(wxyz_to_xyzw(q[:, 3:7]))
    out[:, 3:7] = xyzw_to_wxyz(Slerp(t_src, rot)(t).as_quat())
    return out


def make_clip(name: str, xml: str, heightmap: HeightMap, qpos: NDArray, fps: float, hz: float) -> Clip:
    """Build a :class:`Clip` (runs MuJoCo forward kinematics on every sample)."""
    from embodmocap.sim.deps import mujoco as _mujoco

    mujoco = _mujoco()  # one clear line naming the extra when missing
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    q = resample_qpos(qpos, fps, hz)
    N, dt = len(q), 1.0 / hz
    nb = m.nbody - 1
    xpos, xquat = np.zeros((N, nb, 3)), np.zeros((N, nb, 4))
    for k in range(N):
        d.qpos[:] = q[k]
        mujoco.mj_kinematics(m, d)
        xpos[k], xquat[k] = d.xpos[1:], d.xquat[1:]
    qvel = np.zeros((N, m.nv))
    vel, angvel = np.zeros_like(xpos), np.zeros_like(xpos)
    if N > 1:
        for k in range(N - 1):
            mujoco.mj_differentiatePos(m, qvel[k], dt, q[k], q[k + 1])
        qvel[-1] = qvel[-2]
        vel[:-1] = np.diff(xpos, axis=0) / dt
        vel[-1] = vel[-2]
        R = quat_to_matrix(wxyz_to_xyzw(xquat))
        dR = R[1:] @ np.swapaxes(R[:-1], -1, -2)  # world-frame increments
        angvel[:-1] = matrix_to_rotvec(dR) / dt
        angvel[-1] = angvel[-2]
    return Clip(name, xml, heightmap, q, qvel, xpos, xquat, vel, angvel, dt)
