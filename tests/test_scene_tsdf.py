"""TSDF fusion against exactly rendered geometry, Open3D against the NumPy reference, depth
filtering, and a small synthetic capture end to end (key frames -> depth -> fusion -> metrics)."""

from __future__ import annotations



from pathlib import Path

import cv2
import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.evaluate.mesh_metrics import mesh_accuracy, mesh_completeness, surface_distances, visible_surface_samples
from embodmocap.geometry.transforms import make_T
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.depth import filter_depth, fusion_frames, keyframe_depth
from embodmocap.scene.tsdf import NumpyTSDF, fuse_open3d
from embodmocap.types import Intrinsics

K_RGB = Intrinsics(120.0, 120.0, 79.5, 59.5, 160, 120)
K_D = K_RGB.scaled(80, 60)


@pytest.fixture(scope="module")
def rendered():
    """An indoor studio scene rendered exactly (no sensor noise) from 24 handheld poses."""
    from embodmocap.synth.render import Renderer
    from embodmocap.synth.scene import build_scene
    from embodmocap.synth.trajectory import scene_walk

    built = build_scene("indoor", np.random.default_rng(5))
    T = scene_walk(built.spec, 12.0, 30.0, np.random.default_rng(6))[::15]
    r = Renderer(built)
    frames = []
    for Ti in T:
        out = r.render(K_RGB, Ti, depth_intrinsics=K_D)
        rgb = cv2.resize(out.rgb, (K_D.width, K_D.height), interpolation=cv2.INTER_AREA)
        depth = np.where(out.depth_lr_m <= 3.5, out.depth_lr_m, 0).astype(np.float32)
        frames.append((rgb, depth, K_D, Ti))
    return built, frames


def test_open3d_fusion_of_exact_depth_is_accurate_and_complete(rendered):
    built, frames = rendered
    v, f, c = fuse_open3d(iter(frames), voxel_m=0.02, sdf_trunc_m=0.08, depth_trunc_m=3.5)
    assert len(f) > 1000 and c.shape == v.shape and 0 <= c.min() and c.max() <= 1
    acc = mesh_accuracy(v, f, built.vertices, built.faces, n_samples=50_000)
    seen = visible_surface_samples(built.vertices, built.faces, np.stack([fr[3] for fr in frames]), K_D, 3.5, 50_000)
    comp = mesh_completeness(v, f, seen, 0.05)
    assert acc < 0.01, acc
    assert comp > 0.95, comp


def test_open3d_fusion_is_the_same_on_any_number_of_threads(rendered):
    """One OpenMP thread (Stage I's default: no spinning on a busy machine) and one per core give
    the same mesh, array for array."""
    _, frames = rendered
    one = fuse_open3d(iter(frames), 0.04, 0.12, 3.5, threads=1)
    every = fuse_open3d(iter(frames), 0.04, 0.12, 3.5, threads=0)
    assert len(one[1]) > 1000
    for a, b in zip(one, every):
        np.testing.assert_array_equal(a, b)


def test_numpy_reference_matches_geometry_and_open3d(rendered):
    built, frames = rendered
    lo, hi = built.vertices.min(0), built.vertices.max(0)
    ref = NumpyTSDF(lo, hi, voxel_m=0.04, sdf_trunc_m=0.12, depth_trunc_m=3.5)
    assert ref.integrate_frames(frames) == len(frames)
    pts = ref.surface_points()
    assert len(pts) > 1000
    d_gt = surface_distances(pts, built.vertices, built.faces)
    assert d_gt.mean() < 0.01, d_gt.mean()
    v, f, _ = ref.extract_mesh()
    assert mesh_accuracy(v, f, built.vertices, built.faces, n_samples=20_000) < 0.012
    # Against Open3D at the same voxel size: the two surfaces agree within a voxel.
    v3, f3, _ = fuse_open3d(iter(frames), voxel_m=0.04, sdf_trunc_m=0.12, depth_trunc_m=3.5)
    d = surface_distances(pts, v3, f3)
    assert np.median(d) < 0.01 and np.percentile(d, 90) < 0.04, (np.median(d), np.percentile(d, 90))


def test_tilted_plane_is_fused_flat():
    """Analytic depth of the plane z = 0 seen from 1.5 m by a camera pitched 30 degrees."""
    K = Intrinsics(160.0, 160.0, 79.5, 59.5, 160, 120)
    a = np.radians(30.0)
    # Camera looking down (+z_cam = -z_world), then pitched towards +y.
    R_down = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float)
    R_pitch = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ts = [make_T(R_down @ R_pitch, [x, 0.0, 1.5]) for x in (-0.2, 0.0, 0.2)]
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1)
    frames = []
    for T in Ts:
        dz = rays @ T[:3, :3].T  # world direction per unit camera depth
        depth = np.where(dz[..., 2] < -1e-3, -T[2, 3] / dz[..., 2], 0).astype(np.float32)
        depth[depth > 2.5] = 0  # keep away from very grazing rays
        frames.append((np.full((K.height, K.width, 3), 128, np.uint8), depth, K, T))
    v, f, _ = fuse_open3d(iter(frames), 0.02, 0.06, 2.5)
    # Flat to a small fraction of the 2 cm voxel (nearest-pixel projection costs ~1 mm).
    assert np.median(np.abs(v[:, 2])) < 0.002 and np.abs(v[:, 2]).max() < 0.004
    ref = NumpyTSDF([-3, -1, -0.3], [3, 5, 0.3], 0.02, 0.06, 2.5)
    ref.integrate_frames(frames)
    pts = ref.surface_points()
    assert len(pts) > 500
    assert np.median(np.abs(pts[:, 2])) < 0.002 and np.abs(pts[:, 2]).max() < 0.004


def test_filter_depth_known_answers():
    d = np.array([[0.5, 3.0, 4.0], [np.nan, -1.0, 2.0]], np.float32)
    conf = np.array([[2, 1, 2], [2, 2, 0]], np.uint8)
    out = filter_depth(d, conf, min_confidence=1, trunc_m=3.5)
    np.testing.assert_array_equal(out, [[0.5, 3.0, 0.0], [0.0, 0.0, 0.0]])
    assert np.isnan(d[1, 0])  # input untouched
    np.testing.assert_array_equal(filter_depth(d, None, 1, 3.5)[1], [0.0, 0.0, 2.0])


# ------------------------------------------------------------------------------------------------
# A small synthetic capture, end to end


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    out = tmp_path_factory.mktemp("scene_synth") / "s"
    synthesize(SynthConfig(seed=3, seconds=0.5, scene_seconds=6.0, width=160, height=120,
                           depth_width=128, depth_height=96), out)
    return out


def test_capture_key_frames_fuse_into_an_accurate_mesh(session):
    from embodmocap.io.captures import open_capture
    from embodmocap.io.layout import SessionLayout
    from embodmocap.scene.keyframes import choose_keyframes
    from embodmocap.scene.mesh import clean_mesh
    import trimesh

    lay = SessionLayout(session)
    cap = open_capture(lay.scene_capture("scene0"))
    gt = np.load(lay.ground_truth.scene_device("scene0"))
    gt_mesh = trimesh.load(lay.ground_truth.scene_mesh("scene0"), process=False)
    cfg = SceneConfig(voxel_m_indoor=0.02, min_keyframes=8)
    sel = choose_keyframes(cap, cfg, indoor=True)
    assert len(sel) >= 8 and len(sel.dropped_blurry) >= 1
    depth, K = keyframe_depth(cap, int(sel.frame_ids[0]), cfg, True)
    assert K == cap.depth_intrinsics and depth.shape == (96, 128) and depth.max() <= cfg.depth_trunc_m(True)
    # Geometry check with the true scene-frame poses (the capture's own poses live in a drifting
    # VIO world).
    T_true = gt["T_scene_cam"][sel.frame_ids]
    v, f, c = fuse_open3d(fusion_frames(cap, sel.frame_ids, T_true, cfg, True),
                          cfg.voxel_m(True), cfg.sdf_trunc_m(True), cfg.depth_trunc_m(True))
    v, f, c = clean_mesh(v, f, c, cfg)
    acc = mesh_accuracy(v, f, gt_mesh.vertices, gt_mesh.faces, n_samples=50_000)
    seen = visible_surface_samples(gt_mesh.vertices, gt_mesh.faces, T_true, K, 3.5, 50_000)
    comp = mesh_completeness(v, f, seen)
    assert acc < 0.015, acc
    assert comp > 0.9, comp


def test_no_valid_depth_is_an_input_error_naming_the_capture(session):
    from embodmocap.io.captures import open_capture
    from embodmocap.io.layout import SessionLayout

    cap = open_capture(SessionLayout(session).scene_capture("scene0"))
    ids = np.arange(3)
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    with pytest.raises(InputError, match=r"scene0.*no valid depth in 3 key frames: every confident pixel is farther"):
        list(fusion_frames(cap, ids, T, SceneConfig(depth_trunc_m_indoor=0.01), True))


def test_confidence_weights_are_exact_shares_of_the_frames():
    from embodmocap.scene.depth import weigh_by_confidence

    depth = np.full((2, 3), 2.0, np.float32)
    conf = np.array([[0, 1, 2], [2, 1, 0]])
    w = np.array([0.25, 0.5, 1.0])
    kept = np.stack([weigh_by_confidence(depth, conf, w, n) > 0 for n in range(40)])  # (40, 2, 3)
    share = kept.mean(axis=0)
    np.testing.assert_allclose(share, [[0.25, 0.5, 1.0], [1.0, 0.5, 0.25]])
    # Evenly spread: a weight-0.25 pixel is fused once in every 4 consecutive frames.
    assert all(kept[i:i + 4, 0, 0].sum() == 1 for i in range(0, 36))
    assert np.array_equal(weigh_by_confidence(depth, conf, np.ones(3), 7), depth)


def test_range_weight_is_the_inverse_square_share_beyond_the_range():
    """``depth_weight_range_m``: a pixel beyond the range is fused in ``(range / depth)^2`` of the
    frames (times its confidence weight); nearer pixels and invalid ones are unchanged; off (0)
    is the confidence weighting alone."""
    from embodmocap.scene.depth import weigh_by_confidence

    depth = np.array([[1.0, 2.0, 4.0, 0.0], [1.0, 2.0, 4.0, 5.0]], np.float32)
    conf = np.array([[2, 2, 2, 2], [0, 0, 0, 1]])
    w = np.array([0.25, 0.5, 1.0])
    kept = np.stack([weigh_by_confidence(depth, conf, w, n, range_m=2.0) > 0 for n in range(400)])
    expect = np.array([[1.0, 1.0, 0.25, 0.0], [0.25, 0.25, 0.0625, 0.5 * 0.16]])
    np.testing.assert_allclose(kept.mean(axis=0), expect, atol=1 / 400)
    # No confidence map: the range alone.
    alone = np.stack([weigh_by_confidence(depth, None, w, n, range_m=2.0) > 0 for n in range(400)]).mean(axis=0)
    np.testing.assert_allclose(alone[0], [1.0, 1.0, 0.25, 0.0], atol=1 / 400)
    np.testing.assert_array_equal(weigh_by_confidence(depth, None, w, 3), depth)
    np.testing.assert_array_equal(weigh_by_confidence(depth, conf, w, 5, range_m=0.0),
                                  weigh_by_confidence(depth, conf, w, 5))


def test_prefetch_keeps_order_and_raises_where_the_reader_failed():
    from embodmocap.scene.depth import prefetch

    assert list(prefetch(iter(range(50)), 3)) == list(range(50))

    def reader():
        yield 1
        yield 2
        raise InputError("capture", "broken frame", "fix it")

    got = []
    with pytest.raises(InputError, match="broken frame"):
        for x in prefetch(reader()):
            got.append(x)
    assert got == [1, 2]
