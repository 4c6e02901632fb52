"""The performer as a MuJoCo model: geometry, masses, joints and actuators from the fitted body.

**Bodies** follow the SMPL humanoid of the MimicKit export (:data:`SMPL_HUMANOID_BODIES`, depth
first, root ``Pelvis``), body frames **x forward, y left, z up** at rest, each body's origin at its
SMPL joint for the fitted betas (``local_pos_m`` of :func:`humanoid_skeleton`), so MuJoCo's forward
kinematics gives SMPL's joints exactly.

**Joints**: a free joint ``root`` on the pelvis, and three hinges per other body named
``<body>_x``, ``<body>_y``, ``<body>_z`` about SMPL's joint axes x (left), y (up), z (forward),
i.e. humanoid axes (0 1 0), (0 0 1), (1 0 0), applied in that order: a body's local rotation is
``Rx(a) Ry(b) Rz(c)`` in SMPL axes, so the hinge angles are the intrinsic XYZ Euler angles of the
SMPL joint rotation. Their ranges are Stage IV's anatomical ranges
(:data:`embodmocap.motion.terms.ANATOMICAL_RANGES`, stated there per axis-angle component; used
as Euler limits here, equal for small rotations and a fair bound for large ones).

**Geometry**: each body's part of the fitted mesh (area-uniform samples of the rest-pose surface
whose interpolated skinning weight is largest on its SMPL joint) is fitted by a capsule along its
principal axis (radius: a percentile of the distances from the axis, length: the 1st-99th
percentile extent), or by its bounding box for the feet (so the sole is the mesh's sole).
Geoms collide with the scene only, never with each other. Each body's mass is the volume of its
part of the fitted mesh (:func:`part_volumes`) at the body density; MuJoCo derives the inertia from
the geom's shape with that mass.

**Actuators**: one position (PD) actuator per hinge, ``kp`` 1000 N m/rad on legs and spine, 300
on the arms, neck and head, ``kv = 0.1 s * kp``, torque limited to 800 N m (arms 200)
(:class:`HumanoidConfig`).

qpos layout: ``[root xyz (3) | root quaternion wxyz (4) | 69 hinge angles]``, hinges in body order
then x, y, z.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.body.humanoid import (
    HUMANOID_TO_SMPL, R_HUMANOID_SMPL, SMPL_HUMANOID_BODIES, humanoid_skeleton, mimickit_frames,
)
from embodmocap.geometry.rotations import matrix_to_rotvec, quat_to_matrix, rotvec_to_quat, wxyz_to_xyzw, xyzw_to_wxyz
from embodmocap.motion.terms import ANATOMICAL_RANGES
from embodmocap.sim.config import HumanoidConfig
from embodmocap.types import SmplParams

BODY_NAMES: tuple[str, ...] = tuple(n for n, _ in SMPL_HUMANOID_BODIES)
#: Hinge axes in the humanoid body frame for SMPL's x, y, z (the columns of R_HUMANOID_SMPL).
HINGE_AXES: NDArray[np.float64] = R_HUMANOID_SMPL.T.copy()
#: Bodies on the arm chains, neck and head (the lighter gains).
ARM_BODIES: frozenset[str] = frozenset(
    {"Neck", "Head"} | {f"{s}_{p}" for s in "LR" for p in ("Thorax", "Shoulder", "Elbow", "Wrist", "Hand")})
NQ = 7 + 3 * (len(BODY_NAMES) - 1)
NV = 6 + 3 * (len(BODY_NAMES) - 1)


def hinge_names() -> list[str]:
    """The 69 hinge (and actuator) names in qpos order."""
    return [f"{b}_{a}" for b in BODY_NAMES[1:] for a in "xyz"]


def hinge_ranges() -> NDArray[np.float64]:
    """(69, 2) hinge limits, radians, in qpos order (Stage IV's anatomical ranges)."""
    r = np.asarray(ANATOMICAL_RANGES, dtype=np.float64)  # (23, 3, 2) for SMPL joints 1..23
    return r[HUMANOID_TO_SMPL[1:] - 1].reshape(69, 2)


def rest_vertices(body_model, betas: NDArray) -> NDArray[np.float64]:
    """(V, 3) vertices of the shaped rest pose (zero pose, zero transl), SMPL's canonical frame."""
    import torch

    out = body_model.forward(np.asarray(betas)[None], np.zeros((1, 3)), np.zeros((1, 69)), dtype=torch.float64)
    return out.vertices[0].numpy()


def surface_samples(body_model, betas: NDArray, n: int = 60_000, seed: int = 0) -> tuple[NDArray, NDArray]:
    """Area-uniform points on the shaped rest mesh and the SMPL joint that owns each.

    Returns ``(points (n, 3), owner (n,))``, SMPL's canonical frame. A point's owner is the
    largest of the skinning weights interpolated at it, so a long triangle spanning a limb (a
    coarse mesh has no vertices along a straight segment) gives its middle to the limb's joint.
    """
    V = rest_vertices(body_model, betas)
    F = np.asarray(body_model.faces, dtype=np.int64)
    W = np.asarray(body_model.lbs_weights)
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(F), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    bary = np.stack([1 - u - v, u, v], axis=1)  # (n, 3)
    pts = np.einsum("nk,nkc->nc", bary, tri[f])
    owner = np.einsum("nk,nkj->nj", bary, W[F[f]]).argmax(axis=1)
    return pts, owner


def part_volumes(body_model, betas: NDArray, cell_m: float = 0.01) -> NDArray[np.float64]:
    """(24,) volume of the shaped rest body around each SMPL joint, m^3.

    The closed mesh's volume (divergence theorem) is shared out by the points of a ``cell_m`` grid
    inside the mesh (ray-parity occupancy), each given to the owner of its nearest surface sample
    (:func:`surface_samples`): the parts sum to the mesh's volume exactly.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    V = rest_vertices(body_model, betas)
    F = np.asarray(body_model.faces, dtype=np.int64)
    total = float(np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0)
    lo, hi = V.min(axis=0), V.max(axis=0)
    axes = [np.arange(lo[k] + cell_m / 2, hi[k], cell_m) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    inside = scene.compute_occupancy(o3d.core.Tensor(grid.astype(np.float32))).numpy() > 0.5
    pts, owner = surface_samples(body_model, betas)
    _, idx = cKDTree(pts).query(grid[inside])
    counts = np.bincount(owner[idx], minlength=24).astype(np.float64)
    return abs(total) * counts / max(counts.sum(), 1.0)


def body_geoms(body_model, betas: NDArray, cfg: HumanoidConfig = HumanoidConfig()) -> list[dict]:
    """Collision geometry of each humanoid body in its own frame (humanoid axes, origin at its joint).

    Fitted to area-uniform samples of the shaped rest mesh owned by the body's joint
    (:func:`surface_samples`). Returns one dict per body in :data:`BODY_NAMES` order: ``{"type":
    "capsule", "fromto": (6,), "radius": r}`` or ``{"type": "box", "pos": (3,), "half": (3,)}``
    (metres).
    """
    pts, owner = surface_samples(body_model, betas)
    J = body_model.rest_joints(betas)
    out = []
    for name, j in SMPL_HUMANOID_BODIES:
        P = (pts[owner == j] - J[j]) @ R_HUMANOID_SMPL.T
        if len(P) < 8:  # a body with (almost) no surface of its own: a small sphere at the joint
            out.append({"type": "capsule", "fromto": np.zeros(6), "radius": 0.02})
            continue
        if name in cfg.box_bodies:
            lo, hi = P.min(axis=0), P.max(axis=0)
            out.append({"type": "box", "pos": (lo + hi) / 2, "half": np.maximum((hi - lo) / 2, 0.005)})
            continue
        c = P.mean(axis=0)
        _, _, vt = np.linalg.svd(P - c, full_matrices=False)
        d = vt[0]
        t = (P - c) @ d
        radial = np.linalg.norm((P - c) - t[:, None] * d, axis=1)
        r = max(float(np.percentile(radial, cfg.capsule_radius_percentile)), 0.01)
        lo, hi = np.percentile(t, [1.0, 99.0])
        half = max((hi - lo) / 2 - r, 0.0)
        mid = c + d * (lo + hi) / 2
        out.append({"type": "capsule", "fromto": np.concatenate([mid - half * d, mid + half * d]), "radius": r})
    return out


def _f(a) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.atleast_1d(a))


def humanoid_xml(body_model, betas: NDArray, cfg: HumanoidConfig = HumanoidConfig()) -> tuple[str, str]:
    """The performer's ``<body>`` tree and its ``<actuator>`` block (MJCF text, two strings)."""
    rest = body_model.rest_joints(betas)
    skel = humanoid_skeleton(rest, body_model.parents)
    parents = skel["parents"]
    local = np.asarray(skel["local_pos_m"])
    geoms = body_geoms(body_model, betas, cfg)
    # Masses from the mesh's own volume per part (the capsules only approximate the shape).
    masses = cfg.density_kg_m3 * np.clip(part_volumes(body_model, betas)[HUMANOID_TO_SMPL], 1e-5, None)
    ranges = hinge_ranges().reshape(23, 3, 2)
    children: dict[int, list[int]] = {i: [] for i in range(len(BODY_NAMES))}
    for i, p in enumerate(parents[1:], start=1):
        children[p].append(i)

    def geom(i: int) -> str:
        g = geoms[i]
        if g["type"] == "box":
            return (f'<geom name="{BODY_NAMES[i]}_geom" type="box" pos="{_f(g["pos"])}" size="{_f(g["half"])}" '
                    f'mass="{masses[i]:.6g}"/>')
        return (f'<geom name="{BODY_NAMES[i]}_geom" type="capsule" fromto="{_f(g["fromto"])}" size="{g["radius"]:.6g}" '
                f'mass="{masses[i]:.6g}"/>')

    def body(i: int, indent: str) -> list[str]:
        name = BODY_NAMES[i]
        pos = rest[0] if i == 0 else local[i]
        lines = [f'{indent}<body name="{name}" pos="{_f(pos if i else np.zeros(3))}">']
        if i == 0:
            lines.append(f'{indent}  <freejoint name="root"/>')
        else:
            for k, ax in enumerate("xyz"):
                lo, hi = ranges[i - 1, k]
                lines.append(f'{indent}  <joint name="{name}_{ax}" type="hinge" axis="{_f(HINGE_AXES[k])}" range="{lo:.6g} {hi:.6g}"/>')
        lines.append(f"{indent}  {geom(i)}")
        for c in children[i]:
            lines += body(c, indent + "  ")
        lines.append(f"{indent}</body>")
        return lines

    tree = "\n".join(body(0, "    "))
    acts = []
    for name in hinge_names():
        arm = name.rsplit("_", 1)[0] in ARM_BODIES
        kp = cfg.kp_arm_nm_rad if arm else cfg.kp_nm_rad
        tmax = cfg.max_torque_nm / 4 if arm else cfg.max_torque_nm
        acts.append(f'    <position name="{name}" joint="{name}" kp="{kp:.6g}" kv="{cfg.kd_ratio_s * kp:.6g}" '
                    f'inheritrange="1" forcerange="{-tmax:.6g} {tmax:.6g}"/>')
    return tree, "\n".join(acts)


def performer_mjcf(body_model, betas: NDArray, cfg: HumanoidConfig = HumanoidConfig(), *, scene_assets: str = "",
                   scene_geoms: str = "", keyframes: NDArray | None = None, key_times: NDArray | None = None,
                   root_pos: NDArray | None = None, model_name: str = "embodmocap_performer") -> str:
    """A complete MJCF document: options, the performer, optional scene assets/geoms and keyframes.

    Args:
        keyframes: (K, NQ) qpos per key (see :func:`reference_qpos`); each key also holds the PD
            targets that keep that pose (``ctrl`` = its hinge angles, clipped to the ranges).
        key_times: (K,) seconds of the keys.
    """
    tree, acts = humanoid_xml(body_model, betas, cfg)
    parts = [
        f'<mujoco model="{model_name}">',
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{cfg.timestep_s:.8g}" integrator="implicitfast"/>',
        '  <size memory="64M"/>',
        "  <default>",
        f'    <joint damping="{cfg.joint_damping:.6g}" armature="{cfg.armature:.6g}" limited="true"/>',
        f'    <geom density="{cfg.density_kg_m3:.6g}" contype="1" conaffinity="0" condim="3" '
        f'friction="{cfg.friction:.6g} 0.005 0.0001" rgba="0.8 0.6 0.5 1"/>',
        "  </default>",
        '  <visual><global offwidth="640" offheight="480"/></visual>',
        "  <asset>",
        '    <texture name="grid" type="2d" builtin="checker" rgb1="0.45 0.45 0.45" rgb2="0.55 0.55 0.55" width="64" height="64"/>',
        '    <material name="scene" texture="grid" texrepeat="20 20" rgba="0.8 0.8 0.8 1"/>',
        scene_assets,
        "  </asset>",
        "  <worldbody>",
        '    <light name="sun" pos="0 0 6" dir="0 0 -1" directional="true"/>',
        scene_geoms,
        tree,
        "  </worldbody>",
        "  <actuator>",
        acts,
        "  </actuator>",
    ]
    if keyframes is not None:
        lo, hi = hinge_ranges().T
        kt = np.arange(len(keyframes)) if key_times is None else np.asarray(key_times)
        parts.append("  <keyframe>")
        for k, (q, t) in enumerate(zip(np.asarray(keyframes), kt)):
            parts.append(f'    <key name="f{k:05d}" time="{t:.6g}" qpos="{_f(q)}" ctrl="{_f(np.clip(q[7:], lo, hi))}"/>')
        parts.append("  </keyframe>")
    parts.append("</mujoco>")
    return "\n".join(p for p in parts if p) + "\n"


def reference_qpos(params: SmplParams, rest_joints: NDArray) -> NDArray[np.float64]:
    """(T, NQ) qpos reproducing ``params`` (world, Z up): pelvis position, pelvis quaternion (wxyz,
    humanoid axes) and the hinges' XYZ Euler angles of each SMPL joint rotation, unwrapped in time."""
    T = len(params)
    frames = mimickit_frames(params, rest_joints)  # root pos | root exp-map | ... (humanoid axes)
    quat = xyzw_to_wxyz(rotvec_to_quat(frames[:, 3:6]))  # w >= 0
    poses = np.asarray(params.poses).reshape(T, 24, 3)[:, HUMANOID_TO_SMPL[1:]]
    eul = Rotation.from_rotvec(poses.reshape(-1, 3)).as_euler("XYZ").reshape(T, 69)
    eul = np.unwrap(eul, axis=0) if T > 1 else eul
    return np.concatenate([frames[:, :3], quat, eul], axis=1)


def params_from_qpos(qpos: NDArray, betas: NDArray, rest_joints: NDArray, fps: float) -> SmplParams:
    """Inverse of :func:`reference_qpos`: SMPL parameters (world, Z up) of (T, NQ) qpos."""
    q = np.asarray(qpos, dtype=np.float64)
    T = len(q)
    C = R_HUMANOID_SMPL
    R_root = quat_to_matrix(wxyz_to_xyzw(q[:, 3:7])) @ C
    local = Rotation.from_euler("XYZ", q[:, 7:].reshape(-1, 3)).as_rotvec().reshape(T, 23, 3)
    poses = np.zeros((T, 24, 3))
    poses[:, HUMANOID_TO_SMPL[1:]] = local
    poses[:, 0] = matrix_to_rotvec(R_root)
    transl = q[:, :3] - np.asarray(rest_joints)[0]
    return SmplParams(np.asarray(betas), poses[:, 0], poses[:, 1:].reshape(T, 69), transl, fps=fps)
