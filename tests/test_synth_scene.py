"""The synthetic scene: furniture, closed outward-facing boxes, free walk area, laser spot, PLY."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from embodmocap.synth.scene import box_mesh, build_scene, scene_mesh_trimesh, write_scene_ply
from embodmocap.synth.texture import albedo


def test_box_mesh_is_closed_with_outward_normals():
    rng = np.random.default_rng(0)
    centres = rng.uniform(-2, 2, (5, 3))
    sizes = rng.uniform(0.1, 2.0, (5, 3))
    yaws = rng.uniform(-np.pi, np.pi, 5)
    v, f = box_mesh(centres, sizes, yaws)
    assert v.shape == (40, 3) and f.shape == (60, 3) and f.dtype == np.int32
    for b in range(5):
        m = trimesh.Trimesh(v[8 * b:8 * b + 8], f[12 * b:12 * b + 12] - 8 * b, process=False)
        assert m.is_watertight and m.is_winding_consistent
        assert m.volume == pytest.approx(np.prod(sizes[b]), rel=1e-9)  # > 0: normals point out
        # Every face normal points away from the box centre.
        assert np.all(np.einsum("ij,ij->i", m.face_normals, m.triangles_center - centres[b]) > 0)


@pytest.mark.parametrize("preset", ["indoor", "outdoor"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scene_has_furniture_and_free_walk_area(preset, seed):
    built = build_scene(preset, np.random.default_rng(seed))
    spec = built.spec
    names = set(spec.furniture)
    assert {"chair", "table", "box"} <= names and len(names & {"sofa", "bed"}) == 1
    lo, hi = spec.floor_min_xy, spec.floor_max_xy
    size = hi - lo
    if preset == "indoor":
        assert 4.5 <= size[0] <= 7.0 and 4.0 <= size[1] <= 6.0 and 2.6 <= spec.wall_height <= 3.0
    else:
        assert np.all((size >= 8.0) & (size <= 12.0))
    assert 0.40 <= spec.furniture["chair"].top_z <= 0.5
    assert 0.7 <= spec.furniture["table"].top_z <= 0.8
    assert 0.2 <= spec.furniture["box"].top_z <= 0.3 and np.all(spec.furniture["box"].size[:2] >= 0.45)

    # Footprints (yaw is a multiple of 90 degrees) inside the floor, pairwise disjoint, and clear of
    # the walk area.
    rects = []
    for f in spec.furniture.values():
        assert np.isclose(np.mod(f.yaw, np.pi / 2), 0) or np.isclose(np.mod(f.yaw, np.pi / 2), np.pi / 2)
        ext = f.size[:2] if np.isclose(abs(np.cos(f.yaw)), 1) else f.size[1::-1]
        rects.append((f.centre_xy - ext / 2, f.centre_xy + ext / 2))
        # Its front faces into the room: the front point is nearer the centre than the piece.
        assert np.linalg.norm(f.front_point(0.5)[:2] - (lo + hi) / 2) < np.linalg.norm(f.centre_xy - (lo + hi) / 2)
    wlo, whi = spec.walk_area_min_xy, spec.walk_area_max_xy
    assert np.all(whi - wlo >= 1.8)
    for i, (a0, a1) in enumerate(rects):
        assert np.all(a0 >= lo - 1e-9) and np.all(a1 <= hi + 1e-9)
        assert not (np.all(a0 < whi) and np.all(wlo < a1)), "furniture in the walk area"
        for b0, b1 in rects[i + 1:]:
            assert not (np.all(a0 < b1) and np.all(b0 < a1)), "furniture overlaps"

    # The laser dot lies on a wall plane, at 1.2-1.6 m, its normal pointing into the room.
    dot, n = spec.laser_dot, spec.laser_normal
    assert 1.2 <= dot[2] <= 1.6 and np.isclose(np.linalg.norm(n), 1.0)
    on_wall = np.isclose(dot[:2], lo) | np.isclose(dot[:2], hi)
    assert on_wall.sum() == 1
    assert np.dot((lo + hi) / 2 - dot[:2], n[:2]) > 0

    # The mesh: every box closed and outward, materials valid.
    mesh = scene_mesh_trimesh(built)
    assert len(built.face_material) == len(built.faces) and built.face_material.max() < len(built.materials)
    vols = [trimesh.Trimesh(built.vertices[8 * b:8 * b + 8], built.faces[12 * b:12 * b + 12] - 8 * b, process=False).volume
            for b in range(len(built.faces) // 12)]
    assert min(vols) > 0
    assert mesh.bounds[0][2] == pytest.approx(-0.2)


def test_scene_is_deterministic_and_seed_dependent():
    a = build_scene("indoor", np.random.default_rng(5))
    b = build_scene("indoor", np.random.default_rng(5))
    c = build_scene("indoor", np.random.default_rng(6))
    assert np.array_equal(a.vertices, b.vertices) and a.materials == b.materials
    assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)


def test_write_scene_ply_round_trip(tmp_path):
    built = build_scene("outdoor", np.random.default_rng(0))
    path = write_scene_ply(built, tmp_path / "gt" / "scene.ply")
    m = trimesh.load(path, process=False)
    assert np.allclose(m.vertices, built.vertices, atol=1e-5)
    assert np.array_equal(m.faces, built.faces)
    assert [p.name for p in path.parent.iterdir()] == ["scene.ply"]  # no temp file left


def test_albedo_is_a_deterministic_solid_texture():
    built = build_scene("indoor", np.random.default_rng(0))
    rng = np.random.default_rng(1)
    p = rng.uniform(-3, 3, (50_000, 3))
    m = rng.integers(0, len(built.materials), 50_000)
    a = albedo(p, m, built.materials)
    assert a.shape == (50_000, 3) and a.dtype == np.float32
    assert a.min() >= 0 and a.max() <= 1
    # Same point, same colour, regardless of the order or batch it is evaluated in.
    perm = rng.permutation(50_000)
    assert np.array_equal(albedo(p[perm], m[perm], built.materials), a[perm])
    # Textured, not flat: strong variation within one material over a small patch.
    wall = built.material_id("wall")
    patch = np.column_stack([np.full(4000, 1.0), rng.uniform(0, 0.5, 4000), rng.uniform(1, 1.5, 4000)])
    lum = albedo(patch, np.full(4000, wall), built.materials).mean(1)
    assert lum.std() > 0.05


def test_room_presets_have_their_sizes_and_standard_is_unchanged():
    std = build_scene("indoor", np.random.default_rng(4))
    again = build_scene("indoor", np.random.default_rng(4), "standard")
    np.testing.assert_array_equal(std.vertices, again.vertices)
    large = build_scene("indoor", np.random.default_rng(4), "large").spec
    np.testing.assert_allclose(large.floor_max_xy - large.floor_min_xy, [8.0, 6.0], atol=0.16)
    assert build_scene("indoor", np.random.default_rng(4), "high_ceiling").spec.wall_height >= 4.0
    with pytest.raises(ValueError):
        build_scene("outdoor", np.random.default_rng(4), "large")


def test_repetitive_walls_repeat_and_plain_walls_are_flat():
    from embodmocap.synth.texture import LATTICE_ROTATION, albedo

    rep = build_scene("indoor", np.random.default_rng(2), "repetitive")
    mats = rep.materials
    wall = rep.material_id("wall")
    m = mats[wall]
    assert m.period == 2
    rng = np.random.default_rng(0)
    p = rng.uniform(-2, 2, (500, 3))
    # One period along a lattice axis (cell size x period), expressed in the scene frame.
    shift = LATTICE_ROTATION @ np.array([m.cell_m[0] * m.period, 0.0, 0.0])
    ids = np.full(len(p), wall)
    a, b = albedo(p, ids, mats), albedo(p + shift, ids, mats)
    assert np.mean(np.all(np.abs(a - b) < 1e-4, axis=1)) > 0.97  # (float rounding at cell borders)
    std = build_scene("indoor", np.random.default_rng(2))
    c = albedo(p, np.full(len(p), std.material_id("wall")), std.materials)
    d = albedo(p + shift, np.full(len(p), std.material_id("wall")), std.materials)
    assert np.mean(np.all(np.abs(c - d) < 1e-4, axis=1)) < 0.2
    plain = build_scene("indoor", np.random.default_rng(2), "low_texture")
    e = albedo(p, np.full(len(p), plain.material_id("wall")), plain.materials)
    assert e.std(axis=0).max() < 0.3 * c.std(axis=0).max()


def test_relight_is_identity_at_unit_gain_and_saturates():
    from embodmocap.synth.texture import relight

    img = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    np.testing.assert_allclose(relight(img, 1.0, np.ones(3)).astype(int), img.astype(int), atol=1)
    bright = relight(img, 3.0, np.ones(3))
    assert np.all(bright >= img) and bright.max() == 255
    warm = relight(np.full((1, 1, 3), 128, np.uint8), 1.0, [1.2, 1.0, 0.8])[0, 0]
    assert warm[0] > 128 > warm[2] and abs(int(warm[1]) - 128) <= 1
    f = relight(np.full((2, 2, 3), 0.5, np.float32), 0.5, np.ones(3))
    assert f.dtype == np.float32 and np.all(f < 0.5)
