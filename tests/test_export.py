"""Exports: every format read back by an independent reader and checked against the body model."""

from __future__ import annotations

import csv
import pickle

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.joints import SMPL_JOINT_NAMES
from embodmocap.body.model import BodyModel, load_body_model
from embodmocap.errors import InputError
from embodmocap.export import (
    HeightMap, egocentric_heightmap, export_sequence, read_amass, read_heightmap, read_mimickit_motion,
    scene_heightmap, write_amass, write_bvh, write_glb, write_joints_csv, write_mimickit,
)
from embodmocap.export.mimickit import HUMANOID_TO_SMPL, R_HUMANOID_SMPL
from embodmocap.io.layout import SessionLayout
from embodmocap.types import SmplParams

# Z-up world -> Y-up world: (x, y, z) -> (x, z, -y), written out independently of the package.
R_YUP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
FPS = 30.0


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return load_body_model(None)


@pytest.fixture(scope="module")
def params() -> SmplParams:
    """8 frames of a varied pose: random joint rotations, turning root, moving translation."""
    rng = np.random.default_rng(7)
    T = 8
    betas = np.zeros(10)
    betas[:4] = rng.normal(0, 0.8, 4)
    go = Rotation.from_euler("xz", np.stack([np.full(T, np.pi / 2), np.linspace(0, 2.5, T)], 1)).as_rotvec()
    body_pose = rng.normal(0, 0.35, (T, 69))
    transl = np.stack([np.linspace(0, 1.2, T), np.linspace(2, 1.5, T), 0.9 + 0.05 * np.sin(np.arange(T))], 1)
    return SmplParams(betas=betas, global_orient=go, body_pose=body_pose, transl=transl, fps=FPS, gender="neutral")


def _forward(model: BodyModel, p: SmplParams):
    out = model.forward(p.betas, p.global_orient, p.body_pose, p.transl, dtype=torch.float64)
    return out.vertices.numpy(), out.joints.numpy()


def _box_scene():
    """A 4 m x 3 m floor (z=0) at x in [0, 4], y in [0, 3] and a 1 x 1 x 0.5 m box at x, y in [1, 2]."""
    floor_v = np.array([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], float)
    floor_f = np.array([[0, 1, 2], [0, 2, 3]])
    corners = np.array([[x, y, z] for z in (0, 0.5) for y in (1, 2) for x in (1, 2)], float)
    box_f = np.array([[4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4], [2, 3, 7], [2, 7, 6],
                      [0, 2, 6], [0, 6, 4], [1, 3, 7], [1, 7, 5]])
    return np.concatenate([floor_v, corners]), np.concatenate([floor_f, box_f + 4])


# ------------------------------------------------------------------------------------ AMASS


def test_amass_round_trip(tmp_path, params):
    frames = np.arange(10, 18)
    path = write_amass(tmp_path / "m.npz", params, frames=frames)
    with np.load(path) as z:
        assert z["poses"].shape == (8, 72) and str(z["gender"]) == "neutral"
        assert float(z["mocap_framerate"]) == FPS
    back, back_frames = read_amass(path)
    np.testing.assert_array_equal(back.poses, params.poses)
    np.testing.assert_array_equal(back.transl, params.transl)
    np.testing.assert_array_equal(back.betas, params.betas)
    np.testing.assert_array_equal(back_frames, frames)
    assert back.fps == FPS and back.gender == "neutral"


def test_amass_smplh_layout_keeps_the_body_and_zeroes_the_hands(tmp_path, params):
    path = write_amass(tmp_path / "h.npz", params, hands=True)
    with np.load(path) as z:
        poses = z["poses"]
    assert poses.shape == (8, 156)
    np.testing.assert_array_equal(poses[:, :66], params.poses[:, :66])
    assert not poses[:, 66:].any()
    back, _ = read_amass(path)
    np.testing.assert_array_equal(back.poses[:, :66], params.poses[:, :66])
    assert not back.poses[:, 66:].any()


def test_amass_bad_file_names_the_file(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((3, 70)), trans=np.zeros((3, 3)), betas=np.zeros(10))
    with pytest.raises(InputError, match="bad.npz.*72 or 156"):
        read_amass(bad)


# ------------------------------------------------------------------------------------ BVH


def _bvh_fk(path):
    """Joint positions (T, J, 3) and names by forward kinematics on what the `bvh` package parses."""
    from bvh import Bvh

    with open(path) as f:
        mocap = Bvh(f.read())
    names = mocap.get_joints_names()
    T = mocap.nframes
    world_R = {}
    world_p = {}
    for name in names:  # depth-first: parents come first
        channels = mocap.joint_channels(name)
        rot_ch = [c for c in channels if c.endswith("rotation")]
        order = "".join(c[0] for c in rot_ch)
        angles = np.array(mocap.frames_joint_channels(name, rot_ch))
        local = Rotation.from_euler(order.upper(), angles, degrees=True).as_matrix()
        offset = np.array(mocap.joint_offset(name))
        parent = mocap.joint_parent(name)
        if parent is None:
            pos = np.array(mocap.frames_joint_channels(name, ["Xposition", "Yposition", "Zposition"])) + offset
            world_R[name], world_p[name] = local, pos
        else:
            pR, pp = world_R[parent.name], world_p[parent.name]
            world_p[name] = pp + pR @ offset
            world_R[name] = pR @ local
    return names, np.stack([world_p[n] for n in names], axis=1), mocap


@pytest.mark.parametrize("units, scale", [("cm", 100.0), ("m", 1.0)])
def test_bvh_parsed_by_independent_library_matches_smpl_joints(tmp_path, model, params, units, scale):
    path = write_bvh(tmp_path / "m.bvh", params, model, units=units)
    names, pos, mocap = _bvh_fk(path)
    assert sorted(names) == sorted(SMPL_JOINT_NAMES) and mocap.nframes == len(params)
    assert mocap.frame_time == pytest.approx(1 / FPS, abs=1e-8)
    _, joints = _forward(model, params)
    expected = joints[:, [SMPL_JOINT_NAMES.index(n) for n in names]] @ R_YUP.T
    err_m = np.abs(pos / scale - expected).max()
    assert err_m < 1e-3, err_m
    # Bone lengths are the fitted ones: the rest offsets equal the rest-joint differences.
    rest = model.rest_joints(params.betas)
    np.testing.assert_allclose(np.array(mocap.joint_offset("left_knee")) / scale, rest[4] - rest[1], atol=1e-6)


# ------------------------------------------------------------------------------------ glTF


def _accessor(gltf, blob, index):
    """Decode one accessor of a pygltflib document (tightly packed views, as the writer makes)."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    start = view.byteOffset + (acc.byteOffset or 0)
    data = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=start)
    return data.reshape(acc.count, width) if width > 1 else data


def test_glb_reads_back_and_skins_like_smpl_without_pose_correctives(tmp_path, model, params):
    import pygltflib

    scene_v, scene_f = _box_scene()
    frames = np.arange(100, 108)
    path = write_glb(tmp_path / "m.glb", params, model, (scene_v, scene_f, np.full((len(scene_v), 3), 0.5)), frames=frames)
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()

    by_name = {m.name: m for m in g.meshes}
    scene_prim = by_name["scene"].primitives[0]
    assert g.accessors[scene_prim.attributes.POSITION].count == len(scene_v)
    np.testing.assert_allclose(_accessor(g, blob, scene_prim.attributes.POSITION), scene_v @ R_YUP.T, atol=1e-6)

    skin = g.skins[0]
    assert len(skin.joints) == 24
    assert [g.nodes[j].name for j in skin.joints] == list(SMPL_JOINT_NAMES)
    anim = g.animations[0]
    times = _accessor(g, blob, anim.samplers[0].input)
    assert len(times) == len(params)
    assert times[-1] == pytest.approx((len(params) - 1) / FPS, abs=1e-6)
    assert all(s.interpolation == "LINEAR" for s in anim.samplers)

    # Our own LBS from the read-back accessors: node FK -> skin matrices -> 4 weights per vertex.
    node_joint = {n: k for k, n in enumerate(skin.joints)}
    T = len(params)
    local_R = np.tile(np.eye(3), (T, 24, 1, 1))
    local_t = np.tile(np.array([g.nodes[n].translation for n in skin.joints], float)[None], (T, 1, 1))
    for ch in anim.channels:
        out = _accessor(g, blob, anim.samplers[ch.sampler].output).astype(np.float64)
        k = node_joint[ch.target.node]
        if ch.target.path == "rotation":
            local_R[:, k] = Rotation.from_quat(out).as_matrix()
        else:
            local_t[:, k] = out
    parent = {c: p for p in skin.joints for c in (g.nodes[p].children or [])}
    world = np.zeros((T, 24, 4, 4))
    for n in skin.joints:  # SMPL order lists parents before children
        k = node_joint[n]
        M = np.tile(np.eye(4), (T, 1, 1))
        M[:, :3, :3], M[:, :3, 3] = local_R[:, k], local_t[:, k]
        world[:, k] = world[:, node_joint[parent[n]]] @ M if n in parent else M
    ibm = _accessor(g, blob, skin.inverseBindMatrices).reshape(24, 4, 4).transpose(0, 2, 1)
    skin_M = world @ ibm
    body_prim = by_name["body"].primitives[0]
    rest_v = _accessor(g, blob, body_prim.attributes.POSITION).astype(np.float64)
    jidx = _accessor(g, blob, body_prim.attributes.JOINTS_0).astype(np.int64)
    w = _accessor(g, blob, body_prim.attributes.WEIGHTS_0).astype(np.float64)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)
    M_v = np.einsum("vk,tvkij->tvij", w, skin_M[:, jidx])
    skinned = np.einsum("tvij,vj->tvi", M_v[..., :3, :3], rest_v) + M_v[..., :3, 3]

    # Reference: SMPL with pose blend shapes off, and the same 4-influence weights.
    arrays = model.arrays
    arrays["posedirs"] = np.zeros_like(arrays["posedirs"])
    weights4 = np.zeros_like(arrays["weights"])
    np.add.at(weights4, (np.arange(len(w))[:, None], jidx), w)  # zero-weight slots point at joint 0
    arrays["weights"] = weights4
    plain = BodyModel(arrays)
    ref_v, _ = _forward(plain, params)
    err = np.abs(skinned - ref_v @ R_YUP.T).max()
    assert err < 1e-4, err
    # Against the full model the only differences are pose correctives and dropped small weights.
    full_v, _ = _forward(model, params)
    assert np.abs(skinned - full_v @ R_YUP.T).max() < 0.1


# ------------------------------------------------------------------------------------ MimicKit


def test_mimickit_motion_reads_back_and_its_fk_gives_smpl_joints(tmp_path, model, params):
    scene = _box_scene()
    out = write_mimickit(tmp_path / "mk", params, model, scene, name="seq0", loop_mode="wrap")
    with open(out / "seq0.pkl", "rb") as f:
        doc = pickle.load(f)
    assert set(doc) == {"loop_mode", "fps", "frames"} and doc["loop_mode"] == 1 and doc["fps"] == FPS
    fps, loop, frames = read_mimickit_motion(out / "seq0.pkl")
    assert frames.shape == (len(params), 75)

    _, joints = _forward(model, params)
    np.testing.assert_allclose(frames[:, :3], joints[:, 0], atol=1e-9)  # root = pelvis
    C = R_HUMANOID_SMPL
    R_go = Rotation.from_rotvec(np.array(params.global_orient)).as_matrix()
    np.testing.assert_allclose(Rotation.from_rotvec(frames[:, 3:6]).as_matrix(), R_go @ C.T, atol=1e-9)

    # FK the way MimicKit does it, with the offsets of the skeleton sidecar.
    import json

    skel = json.loads((out / "seq0_skeleton.json").read_text())
    parents, offsets = skel["parents"], np.array(skel["local_pos_m"])
    rots = Rotation.from_rotvec(frames[:, 3:].reshape(-1, 3)).as_matrix().reshape(len(params), 24, 3, 3)
    world_R, world_p = [rots[:, 0]], [frames[:, :3]]
    for b in range(1, 24):
        pR, pp = world_R[parents[b]], world_p[parents[b]]
        world_p.append(pp + pR @ offsets[b])
        world_R.append(pR @ rots[:, b])
    np.testing.assert_allclose(np.stack(world_p, 1), joints[:, HUMANOID_TO_SMPL], atol=1e-6)
    # The humanoid's body frame is z up, x forward: at rest the head is above the pelvis.
    assert offsets[skel["body_names"].index("Neck")][2] > 0

    obj_lines = (out / "scene.obj").read_text().splitlines()
    v = np.array([[float(x) for x in ln.split()[1:]] for ln in obj_lines if ln.startswith("v ")])
    f = np.array([[int(x) for x in ln.split()[1:]] for ln in obj_lines if ln.startswith("f ")]) - 1
    np.testing.assert_allclose(v, scene[0], atol=1e-6)
    np.testing.assert_array_equal(f, scene[1])
    hm = read_heightmap(out / "scene_heightmap.npz")
    assert hm.heights.dtype == np.float32 and hm.cell_m == 0.05


def test_heightmap_of_a_box_scene_and_the_egocentric_grid():
    v, f = _box_scene()
    hm = scene_heightmap(v, f, cell_m=0.1, margin_m=0.3)
    centres_x = hm.origin[0] + (np.arange(hm.heights.shape[1]) + 0.5) * hm.cell_m
    centres_y = hm.origin[1] + (np.arange(hm.heights.shape[0]) + 0.5) * hm.cell_m
    X, Y = np.meshgrid(centres_x, centres_y)
    in_box = (X > 1.05) & (X < 1.95) & (Y > 1.05) & (Y < 1.95)
    on_floor = (X > 0.05) & (X < 3.95) & (Y > 0.05) & (Y < 2.95) & ~((X > 0.95) & (X < 2.05) & (Y > 0.95) & (Y < 2.05))
    outside = (X < -0.05) | (X > 4.05) | (Y < -0.05) | (Y > 3.05)
    np.testing.assert_allclose(hm.heights[in_box], 0.5, atol=1e-6)
    np.testing.assert_allclose(hm.heights[on_floor], 0.0, atol=1e-6)
    assert np.isnan(hm.heights[outside]).all() and outside.any()

    # Standing at (2.5, 1.5) facing -X: the box is straight ahead 0.5..1.5 m away.
    grid = egocentric_heightmap(hm, np.array([2.5, 1.5]), np.pi, size=11, spacing=0.2)
    assert grid.shape == (11, 11)
    ahead = grid[:, 5]  # the row of points straight ahead / behind
    np.testing.assert_allclose(ahead[[8, 9, 10]], 0.5, atol=1e-6)  # 0.6, 0.8, 1.0 m ahead: box
    np.testing.assert_allclose(ahead[[0, 5]], 0.0, atol=1e-6)  # 1.0 m behind, under the root: floor
    # Facing +Y instead, -X is on the left: the box is 0.6..1.0 m to the left, floor to the right.
    side = egocentric_heightmap(hm, np.array([2.5, 1.5]), np.pi / 2, size=11, spacing=0.2)[5]
    np.testing.assert_allclose(side[[8, 9, 10]], 0.5, atol=1e-6)
    np.testing.assert_allclose(side[[0, 1, 2]], 0.0, atol=1e-6)
    # Batched roots; off the map -> fill.
    batch = egocentric_heightmap(hm, np.array([[2.5, 1.5], [50.0, 50.0]]), np.array([np.pi, 0.0]), fill=-1.0)
    np.testing.assert_array_equal(batch[0], grid)
    assert (batch[1] == -1.0).all()


def test_mimickit_heightmap_is_the_support_under_a_ceiling_not_the_ceiling(tmp_path, model, params):
    """Indoors the highest surface of every cell is the ceiling: the bundle's height map must show
    the floor and the box the performer moves among instead (a flat 2.6 m map was written before)."""
    from embodmocap.export import write_mimickit

    v, f = _box_scene()
    ceiling_v = np.array([[0, 0, 2.6], [4, 0, 2.6], [4, 3, 2.6], [0, 3, 2.6]], float)
    v2 = np.concatenate([v, ceiling_v])
    f2 = np.concatenate([f, np.array([[0, 2, 1], [0, 3, 2]]) + len(v)])
    out = write_mimickit(tmp_path / "mk", params, model, (v2, f2), name="seq0")
    hm = read_heightmap(out / "scene_heightmap.npz")
    centres_x = hm.origin[0] + (np.arange(hm.heights.shape[1]) + 0.5) * hm.cell_m
    centres_y = hm.origin[1] + (np.arange(hm.heights.shape[0]) + 0.5) * hm.cell_m
    X, Y = np.meshgrid(centres_x, centres_y)
    in_box = (X > 1.05) & (X < 1.95) & (Y > 1.05) & (Y < 1.95)
    on_floor = (X > 0.05) & (X < 3.95) & (Y > 0.05) & (Y < 2.95) & ~((X > 0.95) & (X < 2.05) & (Y > 0.95) & (Y < 2.05))
    np.testing.assert_allclose(hm.heights[in_box], 0.5, atol=1e-6)
    np.testing.assert_allclose(hm.heights[on_floor], 0.0, atol=1e-6)


def test_heightmap_round_trip(tmp_path):
    from embodmocap.export import write_heightmap

    hm = HeightMap(heights=np.array([[0.0, np.nan], [1.5, 2.0]]), origin=np.array([-1.0, 2.0]), cell_m=0.25)
    back = read_heightmap(write_heightmap(tmp_path / "h.npz", hm))
    np.testing.assert_array_equal(back.heights, hm.heights)
    np.testing.assert_array_equal(back.origin, hm.origin)
    assert back.cell_m == 0.25


# ------------------------------------------------------------------------------------ CSV


def test_csv_reads_back_with_the_csv_module(tmp_path, model, params):
    _, joints = _forward(model, params)
    frames = np.arange(5, 13)
    path = write_joints_csv(tmp_path / "j.csv", joints, FPS, frames)
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    assert header[:5] == ["frame", "time_s", "pelvis_x", "pelvis_y", "pelvis_z"]
    assert header[-1] == "right_hand_z" and len(header) == 2 + 72
    table = np.array(body, dtype=np.float64)
    np.testing.assert_array_equal(table[:, 0], frames)
    np.testing.assert_allclose(table[:, 1], frames / FPS, atol=1e-6)
    np.testing.assert_allclose(table[:, 2:].reshape(-1, 24, 3), joints, atol=1e-6)


# ------------------------------------------------------------------------------------ session


@pytest.fixture()
def session(tmp_path, model, params):
    """A tiny fake session: manifest, body model, scene mesh and Stage IV motion files."""
    from embodmocap.body.testmodel import write_test_model
    from embodmocap.io.atomic import write_npz
    from embodmocap.io.manifest import SceneEntry, SequenceEntry, SessionManifest, ViewEntry, write_manifest
    from embodmocap.io.mesh_file import write_mesh_ply

    root = tmp_path / "session"
    lay = SessionLayout(root)
    for folder in ("captures/room", "captures/seq0/v1", "captures/seq0/v2"):
        (root / folder).mkdir(parents=True)
    write_test_model(lay.body_model)
    manifest = SessionManifest(
        root=root, body_model=lay.body_model,
        scenes={"room": SceneEntry(name="room", capture=root / "captures/room")},
        sequences={"seq0": SequenceEntry(name="seq0", scene="room", views={
            v: ViewEntry(capture=root / f"captures/seq0/{v}") for v in ("v1", "v2")})},
    )
    write_manifest(manifest)
    v, f = _box_scene()
    write_mesh_ply(lay.scene("room").mesh_raw, v, f)
    _, joints = _forward(model, params)
    seq = lay.sequence("seq0")
    write_npz(seq.smpl_world, poses=params.poses, trans=params.transl, betas=params.betas, gender=np.array("neutral"),
              mocap_framerate=np.array(FPS), frames=np.arange(len(params), dtype=np.int64), version=np.array(1))
    write_npz(seq.joints_world, joints=joints, coco17=np.zeros((len(params), 17, 3)), version=np.array(1))
    return root


def test_export_sequence_writes_every_format(session, model, params):
    lay = SessionLayout(session)
    outs = {to: export_sequence(session, "seq0", to) for to in ("amass", "bvh", "glb", "mimickit", "csv")}
    for to, out in outs.items():
        assert out.parent == lay.sequence("seq0").exports_dir and out.exists(), to
    back, _ = read_amass(outs["amass"])
    np.testing.assert_allclose(back.poses, params.poses)
    _, pos, _ = _bvh_fk(outs["bvh"])
    assert pos.shape == (len(params), 24, 3)
    assert (outs["mimickit"] / "seq0.pkl").is_file() and (outs["mimickit"] / "scene_heightmap.npz").is_file()
    with open(outs["csv"], newline="") as f:
        assert len(list(csv.reader(f))) == len(params) + 1
    # A second run replaces the outputs in place (atomic), leaving no temporary files.
    export_sequence(session, "seq0", "mimickit")
    assert sorted(p.name for p in lay.sequence("seq0").exports_dir.iterdir()) == sorted(o.name for o in outs.values())


def test_export_without_a_fit_says_which_command_to_run(session):
    SessionLayout(session).sequence("seq0").smpl_world.unlink()
    with pytest.raises(InputError, match=r"smpl_world\.npz.*embodmocap motion .* --seq seq0"):
        export_sequence(session, "seq0", "bvh")
    with pytest.raises(InputError, match="unknown export format"):
        export_sequence(session, "seq0", "fbx")
