"""The performer's MuJoCo model (embodmocap.sim.model / scene / session) against the body model and
the scene mesh it is built from."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

mujoco = pytest.importorskip("mujoco")

from embodmocap.export.mimickit import HUMANOID_TO_SMPL, R_HUMANOID_SMPL  # noqa: E402
from embodmocap.sim.model import BODY_NAMES, hinge_ranges, performer_mjcf, reference_qpos  # noqa: E402
from embodmocap.sim.scene import heightfield_mjcf, support_heightmap  # noqa: E402
from embodmocap.sim.session import export_mjcf, load_sequence  # noqa: E402
from embodmocap.types import SmplParams  # noqa: E402
from sim_session import furniture, sim_session  # noqa: E402,F401


def _fk(m, d, qpos):
    """(T, 24, 3) MuJoCo body positions of each qpos, in the humanoid's body order."""
    out = []
    for q in qpos:
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        out.append(d.xpos[1:1 + len(BODY_NAMES)].copy())
    return np.array(out)


def test_export_loads_steps_and_fk_equals_smpl_joints(sim_session):
    out = export_mjcf(sim_session)
    sq = load_sequence(sim_session)
    m = mujoco.MjModel.from_xml_path(str(out / f"{sq.name}.xml"))
    d = mujoco.MjData(m)
    assert m.nkey == len(sq.params) and m.nu == 69 and m.nq == 76
    # The reference keyframes: MuJoCo FK = the body model's joints for the fitted shape.
    J = sq.body_model.from_params(sq.params, dtype=torch.float64).joints.numpy()
    fk = _fk(m, d, m.key_qpos)
    assert np.abs(fk - J[:, HUMANOID_TO_SMPL]).max() < 1e-3
    # Rest pose standing upright (identity root quaternion = SMPL's canonical frame turned Z up).
    q = np.zeros(m.nq)
    q[3] = 1.0
    rest = sq.rest_joints
    want = (rest - rest[0]) @ R_HUMANOID_SMPL.T
    assert np.abs(_fk(m, d, q[None])[0] - want[HUMANOID_TO_SMPL]).max() < 1e-3
    mujoco.mj_resetDataKeyframe(m, d, 0)
    for _ in range(50):
        mujoco.mj_step(m, d)
    assert np.isfinite(d.qpos).all() and d.time > 0.2


def test_fk_over_random_poses_and_shapes(sim_session):
    bm = load_sequence(sim_session).body_model
    rng = np.random.default_rng(3)
    lo, hi = hinge_ranges().T
    for _ in range(3):
        betas = rng.normal(size=bm.num_betas)
        m = mujoco.MjModel.from_xml_string(performer_mjcf(bm, betas))
        d = mujoco.MjData(m)
        T = 16
        poses = np.zeros((T, 24, 3))
        eul = rng.uniform(lo, hi, size=(T, 69))
        poses[:, HUMANOID_TO_SMPL[1:]] = Rotation.from_euler("XYZ", eul.reshape(-1, 3)).as_rotvec().reshape(T, 23, 3)
        poses[:, 0] = Rotation.random(T, random_state=rng.integers(1 << 30)).as_rotvec()
        p = SmplParams(betas, poses[:, 0], poses[:, 1:].reshape(T, 69), rng.normal(size=(T, 3)), fps=30)
        J = bm.from_params(p, dtype=torch.float64).joints.numpy()
        assert np.abs(_fk(m, d, reference_qpos(p, bm.rest_joints(betas))) - J[:, HUMANOID_TO_SMPL]).max() < 1e-3


def _mesh_height(v, f, xy, top=10.0):
    """Highest mesh surface below ``top`` at points ``xy`` (N, 2): the reference, by ray casting."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    keep = v[f, 2].min(axis=1) < top
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f[keep].astype(np.uint32)))
    rays = np.concatenate([xy, np.full((len(xy), 1), top), np.tile([0, 0, -1.0], (len(xy), 1))], axis=1)
    t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    return top - t


@pytest.fixture(scope="module")
def room(sim_session):
    """The whole studio room as a heightfield under a 2 m cap, and a performer model in it."""
    sq = load_sequence(sim_session)
    hm = support_heightmap(sq.scene_vertices, sq.scene_faces, 2.0, cell_m=0.05)
    asset, geom = heightfield_mjcf(hm)
    xml = performer_mjcf(sq.body_model, sq.params.betas, scene_assets=asset, scene_geoms=geom)
    return sq, hm, mujoco.MjModel.from_xml_string(xml)


def test_heightfield_matches_the_mesh_within_one_cell(room):
    sq, hm, m = room
    d = mujoco.MjData(m)
    d.qpos[:3] = 100.0  # the performer out of the rays' way
    mujoco.mj_forward(m, d)
    rng = np.random.default_rng(0)
    lo = hm.origin + 0.3
    hi = hm.origin + np.array(hm.heights.shape[::-1]) * hm.cell_m - 0.3
    xy = rng.uniform(lo, hi, size=(400, 2))
    geomgroup = np.zeros(6, np.uint8)
    geomid = np.zeros(1, np.int32)
    h_mj = []
    for p in xy:  # MuJoCo's own ray against the heightfield (bodies excluded)
        dist = mujoco.mj_ray(m, d, np.array([p[0], p[1], 5.0]), np.array([0, 0, -1.0]), None, 1, 1, geomid)
        h_mj.append(5.0 - dist)
    h_mj = np.array(h_mj)
    # The mesh's heights within one cell around each point bound the heightfield's value there.
    g = np.linspace(-1.0, 1.0, 9)
    offs = np.array([[dx, dy] for dx in g for dy in g]) * hm.cell_m
    near = _mesh_height(sq.scene_vertices, sq.scene_faces, (xy[:, None] + offs).reshape(-1, 2), top=2.0).reshape(len(xy), -1)
    near = np.where(np.isfinite(near), near, 2.0)  # inside a wall: the cap
    assert np.all(h_mj >= near.min(axis=1) - 2e-3) and np.all(h_mj <= near.max(axis=1) + 2e-3)
    # Away from edges (all neighbours at one height) it is the mesh's height.
    flat = np.ptp(near, axis=1) < 1e-3
    assert flat.mean() > 0.5 and np.abs(h_mj[flat] - near[flat, len(offs) // 2]).max() < 2e-3


def _lowest(m, d, geoms):
    """Lowest point (z) of capsule and box geoms, from their MuJoCo poses and sizes."""
    z = []
    for g in geoms:
        R = d.geom_xmat[g].reshape(3, 3)
        p = d.geom_xpos[g]
        s = m.geom_size[g]
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
            z.append(min(p[2] + R[2, 2] * s[1], p[2] - R[2, 2] * s[1]) - s[0])
        else:
            corners = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * s
            z.append((p + corners @ R.T)[:, 2].min())
    return min(z)


def _drop(m, pose: dict, root_xy, surface_z, yaw=0.0, pitch=0.0, seconds=2.0, gap=0.05):
    """Drop the performer holding ``pose`` (hinge name -> angle) from ``gap`` above ``surface_z``
    (its lowest point) and let it settle; returns MjData."""
    d = mujoco.MjData(m)
    d.qpos[:2] = root_xy
    d.qpos[3:7] = Rotation.from_euler("ZY", [yaw, pitch]).as_quat()[[3, 0, 1, 2]]
    for name, a in pose.items():
        d.qpos[m.jnt_qposadr[m.joint(name).id]] = a
        d.ctrl[m.actuator(name).id] = a
    mujoco.mj_kinematics(m, d)
    d.qpos[2] += surface_z + gap - _lowest(m, d, [g for g in range(m.ngeom) if m.geom_bodyid[g] > 0])
    while d.time < seconds:
        mujoco.mj_step(m, d)
    return d


SIT = {"L_Hip_x": -1.5, "R_Hip_x": -1.5, "L_Knee_x": 0.6, "R_Knee_x": 0.6}


def test_a_dropped_body_rests_on_the_floor_and_on_the_seats(room, sim_session):
    sq, hm, m = room
    body_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] > 0]
    seat_geoms = [m.geom(f"{b}_geom").id for b in ("Pelvis", "L_Hip", "R_Hip")]
    # Lying on its back on the floor (z = 0 in the studio), in the free middle of the room.
    centre = hm.origin + np.array(hm.heights.shape[::-1]) * hm.cell_m / 2
    d = _drop(m, {}, centre, 0.0, pitch=-np.pi / 2)
    assert abs(_lowest(m, d, body_geoms) - 0.0) < 0.01 and np.abs(d.qvel[:3]).max() < 0.05
    # Sitting on the sofa / bed and on the chair: the buttocks and thighs rest on the seat at its
    # height (their contacts with the scene are at the seat's top, penetrating < 1 cm), at rest.
    scene_geom = m.geom("scene").id
    seats = 0
    for name, piece in furniture(sim_session).items():
        if name not in ("chair", "sofa", "bed"):
            continue
        yaw = piece["yaw"]  # furniture faces its local +x (the back is at -x)
        fwd = np.array([np.cos(yaw), np.sin(yaw)])
        d = _drop(m, SIT, np.asarray(piece["centre_xy"]) + 0.05 * fwd, piece["top_z"], yaw=yaw)
        on_seat = [c for c in d.contact[:d.ncon] if scene_geom in (c.geom1, c.geom2)
                   and ({c.geom1, c.geom2} & set(seat_geoms))]
        assert on_seat, name
        for c in on_seat:
            assert abs(c.pos[2] - piece["top_z"]) < 0.01 and -c.dist < 0.01, name
        assert np.abs(d.qvel[:3]).max() < 0.05, name
        seats += 1
    assert seats >= 2


def test_cli_export_mjcf(sim_session, tmp_path):
    from embodmocap.cli import main

    out = tmp_path / "bundle"
    assert main(["export", str(sim_session), "--to", "mjcf", "--out", str(out)]) == 0
    m = mujoco.MjModel.from_xml_path(str(out / "seq0.xml"))
    ref = np.load(out / "seq0_reference.npz")
    assert np.allclose(m.key_qpos, ref["qpos"], atol=1e-5) and m.nhfield == 1


def test_mass_is_the_mesh_volume_at_body_density_and_capsules_hug_the_mesh(sim_session):
    from embodmocap.sim.model import body_geoms, rest_vertices, surface_samples

    bm = load_sequence(sim_session).body_model
    betas = np.zeros(bm.num_betas)
    V, F = rest_vertices(bm, betas), np.asarray(bm.faces)
    volume = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6  # closed mesh
    m = mujoco.MjModel.from_xml_string(performer_mjcf(bm, betas))
    assert m.body_subtreemass[1] == pytest.approx(1000.0 * volume, rel=1e-3)
    # The limbs' and head's surface lies within 2 cm of its capsule's surface (mostly); the flat,
    # wide trunk pieces are rounder capsules: their median distance is still under 2.5 cm.
    pts, owner = surface_samples(bm, betas, n=20_000, seed=1)
    J = bm.rest_joints(betas)
    for (name, j), g in zip([(n, j) for n, j in zip(BODY_NAMES, HUMANOID_TO_SMPL)], body_geoms(bm, betas)):
        P = (pts[owner == j] - J[j]) @ R_HUMANOID_SMPL.T
        if g["type"] != "capsule" or len(P) < 50:
            continue
        a, b = g["fromto"][:3], g["fromto"][3:]
        ab = b - a
        t = np.clip(((P - a) @ ab) / max(ab @ ab, 1e-12), 0, 1)
        dist = np.abs(np.linalg.norm(P - (a + t[:, None] * ab), axis=1) - g["radius"])
        assert np.median(dist) < 0.025, name
        if name not in ("Pelvis", "Torso", "Spine", "Chest", "Neck"):
            assert np.mean(dist < 0.02) > 0.8, name


def test_a_body_dropped_on_a_bed_lies_on_its_top(tmp_path):
    import dataclasses

    from stage4_session import SYNTH, make_stage4_session

    root = tmp_path / "bed"
    make_stage4_session(root, dataclasses.replace(SYNTH, seed=1))  # studio seed 1 furnishes a bed
    bed = furniture(root)["bed"]
    sq = load_sequence(root)
    hm = support_heightmap(sq.scene_vertices, sq.scene_faces, 2.0, cell_m=0.05)
    asset, geom = heightfield_mjcf(hm)
    m = mujoco.MjModel.from_xml_string(performer_mjcf(sq.body_model, sq.params.betas, scene_assets=asset, scene_geoms=geom))
    body_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] > 0]
    # On its back along the bed's length (the bed's local y), in the middle of the mattress.
    d = _drop(m, {}, np.asarray(bed["centre_xy"]), bed["top_z"], yaw=bed["yaw"] + np.pi / 2, pitch=-np.pi / 2)
    assert abs(_lowest(m, d, body_geoms) - bed["top_z"]) < 0.01 and np.abs(d.qvel[:3]).max() < 0.05
    # Sitting on its edge, facing out of the bed (its local +x side).
    fwd = np.array([np.cos(bed["yaw"]), np.sin(bed["yaw"])])
    xy = np.asarray(bed["centre_xy"]) + fwd * (bed["size"][0] / 2 - 0.2)
    d = _drop(m, SIT, xy, bed["top_z"], yaw=bed["yaw"])
    seat_geoms = {m.geom(f"{b}_geom").id for b in ("Pelvis", "L_Hip", "R_Hip")}
    on_bed = [c for c in d.contact[:d.ncon] if m.geom("scene").id in (c.geom1, c.geom2) and {c.geom1, c.geom2} & seat_geoms]
    assert on_bed and all(abs(c.pos[2] - bed["top_z"]) < 0.01 for c in on_bed)


def _l_block(depth=0.6, width=0.8, seat=0.45, back=0.2, height=0.9):
    """A closed L-shaped seat with a backrest (one concave solid, as a scanned sofa would be):
    profile in x (front +x) and z, extruded along y. Returns (vertices, faces) outward."""
    x0, x1, xb = -depth / 2, depth / 2, -depth / 2 + back
    prof = np.array([[x0, 0], [x1, 0], [x1, seat], [xb, seat], [xb, height], [x0, height]])
    n = len(prof)
    v = np.concatenate([np.column_stack([prof[:, 0], np.full(n, y), prof[:, 1]]) for y in (-width / 2, width / 2)])
    cap = [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]]  # a fan from the L's outer corner
    f = [[a, c, b] for a, b, c in cap] + [[a + n, b + n, c + n] for a, b, c in cap]
    for i in range(n):
        j = (i + 1) % n
        f += [[i, j, j + n], [i, j + n, i + n]]
    import trimesh

    m = trimesh.Trimesh(v, np.array(f), process=False)
    trimesh.repair.fix_normals(m)
    assert m.is_watertight and m.volume > 0
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_coacd_pieces_hold_a_body_on_a_concave_seat_and_are_cached(sim_session, tmp_path):
    """`--scene-collision coacd`: a concave L-shaped seat (coacd splits it) and the floor; a body
    dropped sitting on the seat rests on its top within 1 cm, one lying on the floor at 0; the
    pieces are cached by mesh hash (a rerun reads them, another mesh gets its own file)."""
    from embodmocap.sim.scene import cached_convex_pieces, pieces_mjcf

    sq = load_sequence(sim_session)
    seat_v, seat_f = _l_block()
    import trimesh

    floor = trimesh.creation.box(extents=(6, 6, 0.1))
    floor.apply_translation([0, 0, -0.05])
    v = np.concatenate([seat_v + [1.0, 0, 0], floor.vertices])
    f = np.concatenate([seat_f, floor.faces + len(seat_v)])
    cache = tmp_path / "cache"
    pieces = cached_convex_pieces(v, f, cache, threshold=0.03)
    assert len(pieces) >= 3  # the floor + at least two for the L
    files = list(cache.glob("coacd_*.npz"))
    assert len(files) == 1
    again = cached_convex_pieces(v, f, cache, threshold=0.03)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(pieces, again))
    cached_convex_pieces(v + [0, 0, 0.01], f, cache, threshold=0.03)
    assert len(list(cache.glob("coacd_*.npz"))) == 2
    asset, geom = pieces_mjcf(pieces)
    m = mujoco.MjModel.from_xml_string(performer_mjcf(sq.body_model, sq.params.betas, scene_assets=asset, scene_geoms=geom))
    body_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] > 0]
    scene_geoms = {g for g in range(m.ngeom) if m.geom_bodyid[g] == 0}
    seat_geoms = [m.geom(f"{b}_geom").id for b in ("Pelvis", "L_Hip", "R_Hip")]
    d = _drop(m, SIT, np.array([1.05, 0.0]), 0.45)
    on_seat = [c for c in d.contact[:d.ncon] if {c.geom1, c.geom2} & scene_geoms and {c.geom1, c.geom2} & set(seat_geoms)]
    assert on_seat
    for c in on_seat:
        assert abs(c.pos[2] - 0.45) < 0.01 and -c.dist < 0.01
    assert np.abs(d.qvel[:3]).max() < 0.05
    d = _drop(m, {}, np.array([-1.5, 0.0]), 0.0, pitch=-np.pi / 2)
    assert abs(_lowest(m, d, body_geoms)) < 0.01 and np.abs(d.qvel[:3]).max() < 0.05


def test_export_mjcf_scene_collision_coacd_and_both(sim_session, tmp_path):
    """`export --to mjcf --scene-collision coacd|both` loads and steps (pieces cached in the
    sequence's sim/ folder); the studio room as convex pieces (its boxes are convex: each its own
    hull, no coacd run) holds a body sitting on its seats at their height."""
    from embodmocap.cli import main
    from embodmocap.sim.scene import convex_pieces, pieces_mjcf

    for mode, n_hfield in (("coacd", 0), ("both", 1)):
        out = tmp_path / mode
        assert main(["export", str(sim_session), "--to", "mjcf", "--out", str(out), "--scene-collision", mode]) == 0
        m = mujoco.MjModel.from_xml_path(str(out / "seq0.xml"))
        assert m.nhfield == n_hfield and m.nmesh >= 1  # the floor under the motion at least
        mujoco.mj_step(m, mujoco.MjData(m))
    assert list((sim_session / "sequences" / "seq0" / "sim").glob("coacd_*.npz"))
    sq = load_sequence(sim_session)
    pieces = convex_pieces(sq.scene_vertices, sq.scene_faces)
    asset, geom = pieces_mjcf(pieces)
    m = mujoco.MjModel.from_xml_string(performer_mjcf(sq.body_model, sq.params.betas, scene_assets=asset, scene_geoms=geom))
    scene_geoms = {g for g in range(m.ngeom) if m.geom_bodyid[g] == 0}
    seat_geoms = [m.geom(f"{b}_geom").id for b in ("Pelvis", "L_Hip", "R_Hip")]
    seats = 0
    for name, piece in furniture(sim_session).items():
        if name not in ("chair", "sofa", "bed"):
            continue
        fwd = np.array([np.cos(piece["yaw"]), np.sin(piece["yaw"])])
        d = _drop(m, SIT, np.asarray(piece["centre_xy"]) + 0.05 * fwd, piece["top_z"], yaw=piece["yaw"])
        on_seat = [c for c in d.contact[:d.ncon] if {c.geom1, c.geom2} & scene_geoms and {c.geom1, c.geom2} & set(seat_geoms)]
        assert on_seat, name
        for c in on_seat:
            assert abs(c.pos[2] - piece["top_z"]) < 0.01 and -c.dist < 0.01, name
        assert np.abs(d.qvel[:3]).max() < 0.05, name
        seats += 1
    assert seats >= 2
