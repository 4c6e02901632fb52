"""`sim check` measures how deep a body is on the full-resolution scene mesh, not on the
simplified one. Stage I's vertex clustering (5 cm cells) moves the surface by up to a cell: it
fills concave corners, rounds convex ones, and gives a lone vertex of the scan's noise sticking out
of the floor (outdoor seed 3 has one 4 cm up, 5 cm from a standing ankle) a cell of its own, which
its neighbours' 5 cm faces spread into a tent over the foot: the true standing motion read 3.4 cm
inside the scene. Known geometry: the studio's room (seed 101), its box on the floor, meshed as a
scan meshes it at full resolution, and the studio's true standing pose placed against the box."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from embodmocap.body.model import load_body_model
from embodmocap.scene.mesh import simplify_mesh
from embodmocap.sim.check import detail_signed_distance, plausibility
from embodmocap.sim.config import SimCheckConfig
from embodmocap.sim.session import SimSequence, body_vertices

CELL_M = 0.05  # Stage I's simplification cell (SceneConfig.simplify_voxel_m)
GAP_M = 0.003  # the body point's true distance to the box side


def _grid(x0, x1, y0, y1, z, step, keep=None):
    """An up-facing grid of ``step`` squares over [x0, x1] x [y0, y1] at height z (vertices, faces);
    ``keep(cx, cy)`` selects squares by their centres."""
    xs, ys = np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    v = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])
    i, j = np.meshgrid(np.arange(len(xs) - 1), np.arange(len(ys) - 1), indexing="ij")
    a = (i * len(ys) + j).ravel()
    b, c, d = a + len(ys), a + len(ys) + 1, a + 1
    f = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    if keep is not None:
        cen = v[f].mean(axis=1)
        f = f[keep(cen[:, 0], cen[:, 1])]
    return v, f


def _corner_case(phase_m: float = 0.005):
    """The box of seed 101's room (axis-aligned there) with the floor around it, both as a scan
    meshes them at full resolution (1 cm triangles; no bottom, no floor under the box), that mesh
    simplified by Stage I's clustering, and a standing frame of the studio's true motion placed
    with its lowest point facing the box's +x side ``GAP_M`` in front of it."""
    import trimesh

    from embodmocap.synth.motion import MotionScriptConfig, script_motion
    from embodmocap.synth.scene import build_scene

    body = load_body_model(None)
    built = build_scene("indoor", np.random.default_rng([101, 1]), "standard")
    box = built.spec.furniture["box"]
    c, s = abs(np.cos(box.yaw)), abs(np.sin(box.yaw))
    assert min(c, s) < 1e-9  # axis-aligned: its sides on the grid lines
    half = (box.size[:2] if c > s else box.size[1::-1]) / 2
    lo_b, hi_b = box.centre_xy - half, box.centre_xy + half
    h = box.top_z
    # Full resolution: the floor (1 cm squares) round the box's footprint, the box's sides and top.
    # The floor's corner (the clustering grid's origin) puts the box's +x side 5 mm into a cell.
    x0 = hi_b[0] - phase_m - CELL_M * np.ceil((hi_b[0] - lo_b[0]) / CELL_M + 2)  # below the box: the grid origin
    fv, ff = _grid(x0, x0 + 1.2, lo_b[1] - 0.4, lo_b[1] - 0.4 + 1.2, 0.0, 0.01,
                   lambda x, y: ~((x > lo_b[0]) & (x < hi_b[0]) & (y > lo_b[1]) & (y < hi_b[1])))
    bx = trimesh.creation.box(bounds=np.array([[*lo_b, 0.0], [*hi_b, h]]))
    bn = np.asarray(bx.face_normals)
    bv, bf = trimesh.remesh.subdivide_to_size(np.asarray(bx.vertices), np.asarray(bx.faces)[bn[:, 2] > -0.5], 0.01)
    v, f = np.concatenate([fv, bv]), np.concatenate([ff, bf + len(fv)])
    sv, sf, _ = simplify_mesh(v, f, voxel_m=CELL_M)

    betas = np.zeros(body.num_betas)
    betas[:4] = np.random.default_rng([101, 2]).normal(0.0, [0.8, 0.6, 0.5, 0.5])
    sc = script_motion(built.spec, body, betas, 1.0, 30.0, np.random.default_rng([101, 3]),
                       MotionScriptConfig(interactions=()))
    p = sc.params
    p = dataclasses.replace(p, global_orient=p.global_orient[:1], body_pose=p.body_pose[:1], transl=p.transl[:1])
    bv0 = body_vertices(body, p)[0]
    low = bv0[bv0[:, 2] < h - 0.02]
    k = int(np.argmin(low[:, 0]))  # the body's point farthest toward -x, below the box top
    y_mid = (lo_b[1] + hi_b[1]) / 2
    shift = np.array([hi_b[0] + GAP_M - low[k, 0], y_mid - low[k, 1], 0.0])
    p = dataclasses.replace(p, transl=np.asarray(p.transl) + shift)
    point = low[k] + shift
    sq = SimSequence(Path("."), "corner", p, np.arange(1), body, sv, sf, detail_vertices=v, detail_faces=f)
    return sq, point, hi_b[0]


@pytest.fixture(scope="module")
def corner():
    return _corner_case()


def test_a_foot_against_a_box_on_the_floor_does_not_penetrate_it(corner):
    sq, point, face_x = corner
    assert point[2] < 0.035 and abs(point[0] - face_x - GAP_M) < 1e-6  # low on the box's side
    s = plausibility(sq, residual=False)["summary"]
    assert s["penetration_max_cm"] < 0.05
    assert s["contact_fraction"]["left_foot"] + s["contact_fraction"]["right_foot"] >= 1.0


def test_a_lone_vertex_of_the_scan_beside_a_foot_is_not_a_tent_over_it(corner):
    # One floor vertex of the full mesh 7 cm up (the scan's noise), at a corner of the clustering
    # grid (where its neighbours fall in four cells, so its faces survive the clustering), 1 cm
    # beside the foot's widest point (3 cm up). The full mesh's spike is 1 cm wide: the foot is
    # outside it. The simplified mesh's tent over it (5 cm faces) swallows the foot's side.
    sq, _, _ = corner
    v = sq.detail_vertices.copy()
    B = body_vertices(sq.body_model, sq.params)[0]
    foot = B[B[:, 2] < 0.06]
    tip = foot[np.argmax(foot[:, 1])]  # the foot's widest point toward +y (away from the box)
    o = v.min(axis=0)
    spike_xy = o[:2] + np.round((tip[:2] + [0.0, 0.03] - o[:2]) / CELL_M) * CELL_M
    floor = np.flatnonzero(v[:, 2] == 0.0)
    j = floor[np.argmin(np.linalg.norm(v[floor, :2] - spike_xy, axis=1))]
    assert np.allclose(v[j, :2], spike_xy, atol=1e-9)
    v[j, 2] = 0.07
    p = sq.params
    moved = dataclasses.replace(p, transl=np.asarray(p.transl) + [0.0, spike_xy[1] - 0.01 - tip[1], 0.0])
    sv, sf, _ = simplify_mesh(v, sq.detail_faces, voxel_m=CELL_M)
    spiked = dataclasses.replace(sq.with_params(moved), scene_vertices=sv, scene_faces=sf, detail_vertices=v)
    s = plausibility(spiked, residual=False)["summary"]
    assert s["penetration_max_cm"] < 0.05, s["penetration_max_cm"]
    # The simplified mesh alone (the check before) reads the tent as solid.
    off = plausibility(spiked, SimCheckConfig(full_resolution_depth=False), residual=False)["summary"]
    assert off["penetration_max_cm"] > 0.4, off["penetration_max_cm"]


@pytest.mark.parametrize("into_m", [0.01, 0.03])
def test_a_foot_pushed_into_the_box_penetrates_by_the_depth(corner, into_m):
    sq, point, face_x = corner
    p = sq.params
    pushed = sq.with_params(dataclasses.replace(p, transl=np.asarray(p.transl) - [GAP_M + into_m, 0.0, 0.0]))
    pen = plausibility(pushed, residual=False)["summary"]["penetration_max_cm"]
    assert abs(pen - 100 * into_m) < 0.2, pen


def test_detail_signed_distance_against_a_reference():
    # A unit-square floor at z = 0 in 1 cm triangles, one of them turned over (a scan's noise);
    # points above, below and beside it.
    v, f = _grid(0.0, 1.0, 0.0, 1.0, 0.0, 0.01)
    f = f.copy()
    f[7] = f[7][[0, 2, 1]]
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.2, 1.2, 400), rng.uniform(-0.2, 1.2, 400), rng.uniform(-0.1, 0.1, 400)])
    got = detail_signed_distance(v, f, pts, np.full(len(pts), 0.15))
    # Reference: distance to the square; inside (negative) where the way out of it points mostly
    # down (straight below the square, or below its rim by more than 30 degrees).
    q = np.column_stack([pts[:, 0].clip(0, 1), pts[:, 1].clip(0, 1), np.zeros(len(pts))])
    d = np.linalg.norm(pts - q, axis=1)
    ref = np.where(pts[:, 2] < -0.5 * d, -d, d)
    ref[d > 0.15] = np.nan  # nothing within reach
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    ok = ~np.isnan(ref)
    np.testing.assert_allclose(got[ok], ref[ok], atol=1e-5)
