"""The robot motion's files (``sequences/<seq>/robot/<robot>/``), written atomically.

==================  =========================================================================
file                contents
==================  =========================================================================
``qpos.npz``        ``root_pos`` (T, 3) m, ``root_quat_wxyz`` (T, 4), ``joint_pos`` (T, J) rad,
                    ``joint_names`` (J,), ``fps`` (), ``frames`` (T,), ``scale`` (), ``robot`` (),
                    ``contacts`` (T, 2) bool (human left/right foot contact), ``version`` ()
``motion.csv``      BeyondMimic / mjlab ``csv_to_npz`` input: no header, one line per frame,
                    ``x, y, z, qx, qy, qz, qw, joint_1 .. joint_J`` (root position m, root
                    quaternion x y z w, joints in the robot's actuated order, rad)
``motion.npz``      what ``csv_to_npz`` writes from that CSV: ``fps`` (1,), ``joint_pos`` /
                    ``joint_vel`` (N, J), ``body_pos_w`` (N, B, 3), ``body_quat_w`` (N, B, 4 wxyz),
                    ``body_lin_vel_w`` / ``body_ang_vel_w`` (N, B, 3); resampled to
                    ``tracking_fps``; bodies in MuJoCo (depth-first) order
``motion_gmr.pkl``  GMR-style pickle: ``fps``, ``root_pos`` (T, 3), ``root_rot`` (T, 4, x y z w),
                    ``dof_pos`` (T, J), ``local_body_pos`` (T, B, 3, in the root frame),
                    ``link_body_list`` (B names)
``scene.obj``       the scene mesh (Z up, metres)
``scene.xml``       MJCF: the robot, the scene's height map as a height field (collision) and the
                    scene mesh inline (visual only), keyframe ``start`` = the motion's first frame
==================  =========================================================================
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from embodmocap.geometry.heightmap import HeightMap
from embodmocap.geometry.rotations import quat_conj, quat_mul, quat_to_matrix, quat_to_rotvec, wxyz_to_xyzw, xyzw_to_wxyz
from embodmocap.io.atomic import write_bytes, write_npz, write_text
from embodmocap.io.mesh_file import obj_text
from embodmocap.io.npz_file import load_npz
from embodmocap.robot.model import RobotModel, mujoco_module

#: Version of ``qpos.npz`` and ``robot_report.json``.
ROBOT_FILES_VERSION = 1


# ------------------------------------------------------------------------------------ qpos


def write_qpos(path: str | Path, robot: RobotModel, qpos: NDArray, fps: float, *, frames: NDArray | None = None,
               scale: float = 1.0, contacts: NDArray | None = None) -> Path:
    """Write ``qpos.npz`` (module table) from full MuJoCo qpos (T, nq)."""
    pos, quat, joints = robot.split(qpos)
    T = len(pos)
    write_npz(path, version=np.int64(ROBOT_FILES_VERSION), robot=np.array(robot.cfg.name), root_pos=pos,
              root_quat_wxyz=quat, joint_pos=joints, joint_names=np.array(robot.joint_names), fps=np.float64(fps),
              frames=np.arange(T) if frames is None else np.asarray(frames), scale=np.float64(scale),
              contacts=np.zeros((T, 2), bool) if contacts is None else np.asarray(contacts, bool))
    return Path(path)


def read_qpos(path: str | Path) -> dict:
    """Read ``qpos.npz``: a dict of its arrays (``fps`` and ``scale`` as floats)."""
    z = load_npz(path, what="robot motion", fix="run `embodmocap robot retarget` again",
                 required=("root_pos", "root_quat_wxyz", "joint_pos", "joint_names", "fps"), versions=(ROBOT_FILES_VERSION,))
    out = dict(z)
    out["fps"] = float(z["fps"])
    out["scale"] = float(z.get("scale", 1.0))
    out["joint_names"] = [str(n) for n in z["joint_names"]]
    return out


# ------------------------------------------------------------------------------------ CSV


def csv_rows(robot: RobotModel, qpos: NDArray) -> NDArray[np.float64]:
    """(T, 7 + J) rows of the BeyondMimic CSV: root xyz, root quaternion x y z w, joints in CSV order."""
    pos, quat, joints = robot.split(qpos)
    order = [robot.joint_names.index(j) for j in robot.csv_joints]
    return np.concatenate([pos, wxyz_to_xyzw(quat), joints[:, order]], axis=1)


def write_motion_csv(path: str | Path, robot: RobotModel, qpos: NDArray) -> Path:
    """Write the BeyondMimic/mjlab motion CSV (no header; ``np.loadtxt(..., delimiter=",")`` reads it)."""
    buf = io.StringIO()
    np.savetxt(buf, csv_rows(robot, qpos), delimiter=",", fmt="%.9g")
    write_text(path, buf.getvalue())
    return Path(path)


def csv_columns(robot: RobotModel) -> list[str]:
    """The names of the CSV's columns (documentation; the file itself has no header)."""
    return ["x", "y", "z", "qx", "qy", "qz", "qw", *robot.csv_joints]


# ------------------------------------------------------------------------------------ tracking npz


def resample(pos: NDArray, quat_wxyz: NDArray, joints: NDArray, fps_in: float, fps_out: float):
    """Resample a motion the way mjlab's ``csv_to_npz`` does.

    Output times are ``0, 1/fps_out, ...`` strictly below the input's duration ``(T - 1) / fps_in``;
    each lies between two input frames at a blend found from its phase; positions and joints are
    interpolated linearly, the root quaternion spherically. A single frame stays a single frame.
    Returns ``(pos (N, 3), quat (N, 4) wxyz, joints (N, J))``."""
    T = len(pos)
    if T < 2:
        return pos.copy(), quat_wxyz.copy(), joints.copy()
    duration = (T - 1) * (1.0 / fps_in)  # csv_to_npz's own expression (same frame count)
    times = np.arange(0.0, duration, 1.0 / fps_out)
    phase = times / duration
    i0 = np.floor(phase * (T - 1)).astype(np.int64)
    i1 = np.minimum(i0 + 1, T - 1)
    w = phase * (T - 1) - i0
    lerp = lambda a: a[i0] * (1 - w[:, None]) + a[i1] * w[:, None]  # noqa: E731
    slerp = Slerp(np.arange(T, dtype=np.float64), Rotation.from_quat(wxyz_to_xyzw(quat_wxyz)))
    q = xyzw_to_wxyz(slerp(np.clip(i0 + w, 0, T - 1)).as_quat())
    # keep the hemisphere of the input (csv_to_npz's slerp keeps the sign of its first quaternion)
    q *= np.where(np.sum(q * quat_wxyz[i0], axis=-1, keepdims=True) < 0, -1.0, 1.0)
    return lerp(pos), q, lerp(joints)


def so3_derivative(quat_wxyz: NDArray, dt: float) -> NDArray[np.float64]:
    """(N, 3) world angular velocity of a quaternion sequence: central differences
    ``axis_angle(q[t+1] q[t-1]^-1) / (2 dt)``, the ends repeating their neighbours (as ``csv_to_npz``)."""
    q = wxyz_to_xyzw(np.asarray(quat_wxyz, np.float64))
    if len(q) < 3:
        return np.zeros((len(q), 3))
    # quat_to_rotvec takes the shorter turn, whatever the product's sign
    omega = quat_to_rotvec(quat_mul(q[2:], quat_conj(q[:-2]))) / (2.0 * dt)
    return np.concatenate([omega[:1], omega, omega[-1:]])


def tracking_arrays(robot: RobotModel, qpos: NDArray, fps: float, fps_out: float) -> dict[str, NDArray]:
    """The arrays of mjlab's tracking npz for a motion (module table)."""
    pos, quat, joints = robot.split(qpos)
    pos, quat, joints = resample(pos, quat, joints, fps, fps_out)
    dt = 1.0 / fps_out
    grad = (lambda a: np.gradient(a, dt, axis=0)) if len(pos) > 1 else np.zeros_like  # noqa: E731
    lin, jvel = grad(pos), grad(joints)
    omega_w = so3_derivative(quat, dt)
    # MuJoCo's free joint: linear velocity in the world frame, angular velocity in the body frame.
    R = quat_to_matrix(wxyz_to_xyzw(quat))
    qv = np.zeros((len(pos), robot.model.nv))
    a = robot.root_dof
    qv[:, a:a + 3] = lin
    qv[:, a + 3:a + 6] = np.einsum("tba,tb->ta", R, omega_w)
    qv[:, robot.joint_dof] = jvel
    full = robot.qpos(pos, quat, joints)
    body_pos, body_quat = robot.forward(full)
    body_lin, body_ang = robot.body_velocities(full, qv)
    return {"fps": np.array([fps_out]), "joint_pos": joints, "joint_vel": jvel, "body_pos_w": body_pos,
            "body_quat_w": body_quat, "body_lin_vel_w": body_lin, "body_ang_vel_w": body_ang}


def write_tracking_npz(path: str | Path, robot: RobotModel, qpos: NDArray, fps: float, fps_out: float) -> Path:
    """Write the tracking npz (what ``csv_to_npz`` writes for our CSV)."""
    arrays = tracking_arrays(robot, qpos, fps, fps_out)
    write_npz(path, **arrays, body_names=np.array(robot.body_names), joint_names=np.array(robot.joint_names))
    return Path(path)


# ------------------------------------------------------------------------------------ GMR pkl


def write_gmr_pkl(path: str | Path, robot: RobotModel, qpos: NDArray, fps: float) -> Path:
    """Write the GMR-style pickle (module table); plain numpy arrays and Python scalars."""
    pos, quat, joints = robot.split(qpos)
    body_pos, _ = robot.forward(qpos)
    R = quat_to_matrix(wxyz_to_xyzw(quat))
    local = np.einsum("tba,tnb->tna", R, body_pos - pos[:, None])
    doc = {"fps": float(fps), "root_pos": pos, "root_rot": wxyz_to_xyzw(quat), "dof_pos": joints,
           "local_body_pos": local, "link_body_list": list(robot.body_names)}
    write_bytes(path, pickle.dumps(doc, protocol=4))
    return Path(path)


# ------------------------------------------------------------------------------------ scene


def scene_mjcf(robot: RobotModel, hm: HeightMap | None, mesh: tuple | None, qpos0: NDArray) -> str:
    """MJCF text: the robot (meshes from its own folder, absolute path), the height map as a
    height field (collision), the scene mesh inline (visual only) and keyframe ``start``."""
    mj = mujoco_module()
    spec = mj.MjSpec.from_file(str(robot.mjcf))
    spec.meshdir = str((robot.mjcf.parent / (spec.meshdir or ".")).resolve())
    spec.modelname = f"embodmocap_{robot.cfg.name}_scene"
    if hm is not None:
        h = np.asarray(hm.heights, np.float64)
        floor = float(np.nanmin(h)) if np.isfinite(h).any() else 0.0
        h = np.where(np.isfinite(h), h, floor)
        top = max(float(h.max()) - floor, 1e-3)
        H, W = h.shape
        rx, ry = max(W - 1, 1) * hm.cell_m / 2, max(H - 1, 1) * hm.cell_m / 2
        spec.add_hfield(name="scene_heightmap", size=[rx, ry, top, 0.1], nrow=H, ncol=W,
                        userdata=((h - floor) / top).ravel().tolist())
        spec.worldbody.add_geom(name="scene_ground", type=mj.mjtGeom.mjGEOM_HFIELD, hfieldname="scene_heightmap",
                                pos=[hm.origin[0] + hm.cell_m / 2 + rx, hm.origin[1] + hm.cell_m / 2 + ry, floor],
                                rgba=[0.5, 0.5, 0.5, 0.3], group=3)
    if mesh is not None:
        v, f = np.asarray(mesh[0], np.float64), np.asarray(mesh[1], np.int64)
        spec.add_mesh(name="scene_mesh", uservert=v.ravel().tolist(), userface=f.ravel().tolist(),
                      inertia=mj.mjtMeshInertia.mjMESH_INERTIA_SHELL)
        spec.worldbody.add_geom(name="scene_visual", type=mj.mjtGeom.mjGEOM_MESH, meshname="scene_mesh",
                                contype=0, conaffinity=0, density=0, group=2, rgba=[0.8, 0.8, 0.75, 1])
    spec.add_key(name="start", qpos=np.asarray(qpos0, np.float64).tolist())
    spec.compile()
    return spec.to_xml()


def write_scene(out_dir: Path, robot: RobotModel, hm: HeightMap | None, mesh: tuple | None, qpos0: NDArray) -> list[Path]:
    """Write ``scene.obj`` (when there is a mesh) and ``scene.xml`` into ``out_dir``; returns the paths."""
    paths = []
    if mesh is not None:
        write_text(out_dir / "scene.obj", obj_text(mesh[0], mesh[1]))
        paths.append(out_dir / "scene.obj")
    write_text(out_dir / "scene.xml", scene_mjcf(robot, hm, mesh, qpos0))
    paths.append(out_dir / "scene.xml")
    return paths

