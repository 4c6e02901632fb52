"""Mesh clean-up, simplification, statistics and PLY round trips on hand-built meshes."""

from __future__ import annotations



import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io.mesh_file import as_stored
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.mesh import (
    clean_mesh, face_components, mesh_stats, merge_duplicate_vertices, read_mesh_ply, simplify_mesh, write_mesh_ply,
)


def grid(n: int, size: float = 1.0, origin=(0.0, 0.0, 0.0)):
    """An n x n-cell square of side ``size`` in the plane z = origin z: (n+1)^2 vertices, 2n^2 faces."""
    x, y = np.meshgrid(np.linspace(0, size, n + 1), np.linspace(0, size, n + 1), indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]) + origin
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    f = np.concatenate([np.column_stack([a, a + n + 1, a + 1]), np.column_stack([a + 1, a + n + 1, a + n + 2])])
    return v, f


def test_clean_removes_a_floater_and_a_small_piece_and_their_vertices():
    v0, f0 = grid(40, 2.0)  # 3200 faces: the scene
    v1, f1 = grid(2, 0.05, (1.0, 1.0, 1.0))  # 8 faces, 5 cm: a floater
    v2, f2 = grid(6, 0.5, (3.0, 0.0, 0.0))  # 72 faces, 0.5 m: a small but real-sized piece
    v = np.concatenate([v0, v1, v2])
    f = np.concatenate([f0, f1 + len(v0), f2 + len(v0) + len(v1)])
    c = np.tile([0.2, 0.4, 0.6], (len(v), 1))
    c[: len(v0)] = [0.9, 0.1, 0.1]
    # 72 faces is above the absolute minimum (50) but below 5 % of the largest (160).
    cfg = SceneConfig(min_component_fraction=0.05, min_component_triangles=50, floater_max_extent_m=0.1,
                      structure_min_extent_m=0.0)
    vc, fc, cc = clean_mesh(v, f, c, cfg)
    assert len(fc) == len(f0) and len(vc) == len(v0)
    np.testing.assert_allclose(cc, [[0.9, 0.1, 0.1]] * len(vc))
    assert vc[:, 2].max() == 0.0
    # With a looser fraction the 0.5 m piece stays and only the 5 cm floater goes.
    vc, fc, _ = clean_mesh(v, f, c, SceneConfig(min_component_fraction=0.01, min_component_triangles=0))
    assert len(fc) == len(f0) + len(f2)
    # With the structure rule (default: 0.5 m) the piece is real structure and stays however small
    # it is next to the largest component; the floater still goes.
    vc, fc, _ = clean_mesh(v, f, c, SceneConfig(min_component_fraction=0.05, min_component_triangles=50))
    assert len(fc) == len(f0) + len(f2)


def test_duplicated_vertices_do_not_split_components():
    v, f = grid(4)
    # Split every face onto its own copy of its vertices (as meshes joined block by block can be).
    v_split = v[f.reshape(-1)]
    f_split = np.arange(len(v_split)).reshape(-1, 3)
    assert face_components(v_split, f_split)[1] == len(f)
    vm, fm, _ = merge_duplicate_vertices(v_split, f_split)
    assert len(vm) == len(v) and face_components(vm, fm)[1] == 1


def test_simplify_reduces_faces_and_keeps_the_surface():
    v, f = grid(100, 2.0)  # 2 cm cells
    c = np.tile([0.5, 0.5, 0.5], (len(v), 1))
    vs, fs, cs = simplify_mesh(v, f, c, voxel_m=0.1)
    assert len(fs) < len(f) / 10 and len(fs) > 0
    assert np.abs(vs[:, 2]).max() < 1e-9
    assert mesh_stats(vs, fs)["area_m2"] == pytest.approx(4.0, rel=0.1)
    assert cs.shape == vs.shape


def test_mesh_stats_known_answers():
    v, f = grid(3, 2.0, (1.0, -1.0, 0.5))
    s = mesh_stats(v, f)
    assert s["vertices"] == 16 and s["faces"] == 18
    assert s["area_m2"] == pytest.approx(4.0)
    np.testing.assert_allclose(s["bounds"], [[1.0, -1.0, 0.5], [3.0, 1.0, 0.5]])


def test_ply_round_trip_is_atomic(tmp_path):
    v, f = grid(5, 1.0)
    rng = np.random.default_rng(0)
    c = rng.random((len(v), 3))
    path = write_mesh_ply(tmp_path / "out" / "mesh.ply", v, f, c)
    assert [p.name for p in path.parent.iterdir()] == ["mesh.ply"]  # no temporary left behind
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian")
    v2, f2, c2 = read_mesh_ply(path)
    np.testing.assert_allclose(v2, v, atol=1e-12)
    np.testing.assert_array_equal(f2, f)
    np.testing.assert_allclose(c2, np.round(c * 255) / 255, atol=1 / 255 + 1e-9)  # stored as uint8
    v3, f3, c3 = read_mesh_ply(write_mesh_ply(tmp_path / "plain.ply", v, f))
    assert len(c3) == 0 and len(f3) == len(f)
    # What the file gives back, without the file (Stage I's floor and simplify steps use it): the
    # same arrays exactly, colours out of range and on half steps included.
    c[:4] = [[-0.1, 1.2, 0.5 / 255], [1.5 / 255, 2.5 / 255, 254.5 / 255], [0, 1, 0.5], [0.2, 0.4, 0.6]]
    for got, want in zip(as_stored(v, f, c), read_mesh_ply(write_mesh_ply(tmp_path / "c.ply", v, f, c))):
        np.testing.assert_array_equal(got, want)
    for got, want in zip(as_stored(v, f), (v3, f3, c3)):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(InputError, match="missing.ply: mesh file not found"):
        read_mesh_ply(tmp_path / "missing.ply")


def _down_share(v, f):
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    a = np.linalg.norm(n, axis=1)  # 2 x area
    return a[n[:, 2] < 0].sum() / a.sum()  # share of the area facing down


def _floor_with_a_pocket(seed=0):
    """A 2 m TSDF-like floor (2 cm cells, 3 mm noise) facing up, with a thin pocket under 1 m^2 of
    it: a sheet 5 mm below facing down (the pocket's roof) and one 10 mm below facing up."""
    rng = np.random.default_rng(seed)
    v0, f0 = grid(100, 2.0)
    v1, f1 = grid(50, 1.0, (0.5, 0.5, -0.005))
    v2, f2 = grid(50, 1.0, (0.5, 0.5, -0.010))
    f1 = f1[:, [0, 2, 1]]  # the roof faces down, into the pocket
    v = np.concatenate([v0, v1, v2])
    f = np.concatenate([f0, f1 + len(v0), f2 + len(v0) + len(v1)])
    v = v + rng.normal(0.0, 0.003, v.shape) * [0.3, 0.3, 1.0]
    return v, f


def test_simplify_keeps_a_floor_facing_up_over_a_thin_pocket():
    # Clustering collapses the three sheets into the same cells; the kept faces must face up like
    # the surface they stand for (the product once kept either winding at random).
    v, f = _floor_with_a_pocket()
    down_in = _down_share(v, f)
    assert 0.1 < down_in < 0.25  # the input: the pocket's roof
    vs, fs, _ = simplify_mesh(v, f, voxel_m=0.05)
    assert len(fs) < len(f) / 5
    assert _down_share(vs, fs) < 0.005
    assert mesh_stats(vs, fs)["area_m2"] == pytest.approx(4.0, rel=0.1)
    # A plain floor with its faces wound the other way stays wound that way (the vote follows the
    # input, it does not force +z).
    vd, fd = grid(100, 2.0)
    vs, fs, _ = simplify_mesh(vd, fd[:, [0, 2, 1]], voxel_m=0.05)
    assert _down_share(vs, fs) > 0.995


def test_simplify_outvotes_single_turned_over_faces():
    # A TSDF's noise turns single faces over here and there (~1 % of a scanned floor); the faces
    # around the cells outvote them, so the light mesh has fewer, not more, than its input.
    rng = np.random.default_rng(1)
    v, f = grid(100, 2.0)
    flip = rng.random(len(f)) < 0.05
    f[flip] = f[flip][:, [0, 2, 1]]
    vs, fs, _ = simplify_mesh(v, f, voxel_m=0.05)
    assert _down_share(v, f) > 0.04
    assert _down_share(vs, fs) < 0.002


def test_fast_helpers_give_numpys_arrays_bit_for_bit():
    # The clean-up and the simplification use sort-free / bincount versions of np.unique(axis=0),
    # np.add.at and np.minimum.at; the mesh files must not change, so the arrays must be identical.
    from embodmocap.scene.mesh import _component_bounds, _sum_at, _unique_rows, face_components

    rng = np.random.default_rng(3)
    rows = rng.integers(0, 7, size=(5000, 3))
    for r in (rows, rows * 10**7):  # a small box (one int64 key) and one too large for a key
        got, want = _unique_rows(r), np.unique(r, axis=0, return_inverse=True, return_counts=True)
        assert all(np.array_equal(a, b.reshape(a.shape)) for a, b in zip(got, want))
    idx = rng.integers(0, 50, size=20000)
    vals = rng.normal(size=(20000, 3)) * 10.0 ** rng.integers(-8, 8, size=(20000, 1))
    want = np.zeros((50, 3))
    np.add.at(want, idx, vals)
    assert np.array_equal(_sum_at(idx, vals, 50), want)
    # Three separate grids (three components) with noisy vertices and unused vertices in between.
    parts, off = [], 0
    vs_all, fs_all = [], []
    for k in range(3):
        v, f = grid(10 + 5 * k, 1.0 + k)
        v = v + rng.normal(scale=0.01, size=v.shape) + [3.0 * k, 0.0, k]
        vs_all += [v, rng.normal(size=(4, 3)) * 100]
        fs_all.append(f + off)
        off += len(v) + 4
    v, f = np.concatenate(vs_all), np.concatenate(fs_all)
    comp, n = face_components(v, f)
    assert n == 3
    lo, hi = _component_bounds(v, f, comp, n)
    for k in range(n):
        corners = v[f[comp == k]].reshape(-1, 3)
        assert np.array_equal(lo[k], corners.min(axis=0)) and np.array_equal(hi[k], corners.max(axis=0))
