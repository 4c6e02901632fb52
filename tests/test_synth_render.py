"""The ray-casting renderer (exact depth, person mask, laser dot, SIFT-friendly texture) and the
LiDAR simulation."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.geometry.transforms import apply_T, invert_T, look_at_R, make_T
from embodmocap.synth import lidar, trajectory
from embodmocap.geometry.raycast import camera_ray_dirs, raycasting_scene
from embodmocap.synth.render import Renderer, RenderConfig, _cast
from embodmocap.synth.scene import box_mesh, build_scene, scene_mesh_trimesh
from embodmocap.types import Intrinsics

K = Intrinsics(483.0, 483.0, 319.5, 239.5, 640, 480)
K_LR = K.scaled(256, 192)


@pytest.fixture(scope="module")
def indoor():
    built = build_scene("indoor", np.random.default_rng(11))
    return built, Renderer(built)


@pytest.fixture(scope="module")
def outdoor():
    built = build_scene("outdoor", np.random.default_rng(12))
    return built, Renderer(built)


def _pose(R_cols, centre) -> np.ndarray:
    return make_T(np.column_stack(R_cols).astype(float), np.asarray(centre, float))


def _walk_poses(spec, n=4, seed=0):
    T = trajectory.scene_walk(spec, 20.0, 30.0, np.random.default_rng(seed))
    return T[np.linspace(0, len(T) - 1, n).astype(int)]


def _backproject(depth, K_, T):
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    pc = np.column_stack([(u - K_.cx) / K_.fx * z, (v - K_.cy) / K_.fy * z, z])
    return apply_T(T, pc)


def test_plane_at_known_distance_gives_exact_depth(indoor):
    built, r = indoor
    spec = built.spec
    c = np.array([*(spec.walk_area_min_xy + spec.walk_area_max_xy) / 2, 1.4])
    up = r.render(K, _pose([[1, 0, 0], [0, 1, 0], [0, 0, 1]], c), depth_intrinsics=K_LR)
    assert np.allclose(up.depth_m, spec.wall_height - 1.4, atol=1e-5)
    assert np.allclose(up.depth_lr_m, spec.wall_height - 1.4, atol=1e-5)
    down = r.render(K, _pose([[1, 0, 0], [0, -1, 0], [0, 0, -1]], c))
    assert np.allclose(down.depth_m, 1.4, atol=1e-5)
    assert not down.person_mask.any()


@pytest.mark.parametrize("which", ["indoor", "outdoor"])
def test_depth_matches_the_scene_mesh(which, request):
    built, r = request.getfixturevalue(which)
    mesh = scene_mesh_trimesh(built)
    whole = raycasting_scene(built.vertices, built.faces)
    rng = np.random.default_rng(0)
    for T in _walk_poses(built.spec, n=3):
        out = r.render(K, T, depth_intrinsics=K_LR)
        for depth, K_ in ((out.depth_m, K), (out.depth_lr_m, K_LR)):
            # Same answer as casting every ray against the whole static mesh (the fast path is exact).
            dirs = T[:3, :3].astype(np.float32) @ camera_ray_dirs(K_)
            ref = _cast(whole, T[:3, 3], dirs)["t_hit"].reshape(depth.shape)
            ref = np.where(np.isfinite(ref), ref, 0)
            assert np.mean(np.abs(depth - ref) < 1e-4) > 0.999
            # Back-projected pixels lie on the mesh (within 1 mm).
            pts = _backproject(depth, K_, T)
            pts = pts[rng.choice(len(pts), min(1500, len(pts)), replace=False)]
            _, dist, _ = mesh.nearest.on_surface(pts)
            assert np.percentile(dist, 99.5) < 1e-3
        assert out.rgb.shape == (480, 640, 3) and out.rgb.dtype == np.uint8


def test_person_mask_is_where_depth_comes_from_the_body(indoor):
    built, r = indoor
    spec = built.spec
    c = np.array([*(spec.walk_area_min_xy + spec.walk_area_max_xy) / 2, 1.0])
    T = _pose([[0, -1, 0], [0, 0, -1], [1, 0, 0]], c)  # looking along +x
    # A "body": a 0.5 x 0.6 x 1.2 m box 2 m in front, its near face parallel to the image plane.
    v, f = box_mesh(np.array([[c[0] + 2.25, c[1], 1.0]]), np.array([[0.5, 0.6, 1.2]]))
    empty = r.render(K, T, depth_intrinsics=K_LR)
    full = r.render(K, T, (v, f), depth_intrinsics=K_LR)
    mask = full.person_mask
    assert mask.sum() > 1000
    assert np.array_equal(mask, full.depth_m < empty.depth_m - 1e-6)
    assert np.array_equal(full.person_mask_lr, full.depth_lr_m < empty.depth_lr_m - 1e-6)
    assert np.allclose(full.depth_m[mask], 2.0, atol=1e-5)
    assert np.array_equal(full.depth_m[~mask], empty.depth_m[~mask])
    # The mask is the projected rectangle of the near face: u = fx * y / 2 + cx ...
    ys, xs = np.nonzero(mask)
    assert xs.min() == pytest.approx(K.cx - 0.3 / 2 * K.fx, abs=1.0)
    assert ys.max() == pytest.approx(K.cy + 0.6 / 2 * K.fy, abs=1.0)
    # The body looks different from the background.
    assert np.abs(full.rgb[mask].mean(0) - empty.rgb[mask].mean(0)).max() > 20


def _red(rgb):
    return (rgb[..., 0] >= 240) & (rgb[..., 1] <= 70) & (rgb[..., 2] <= 70)


@pytest.mark.parametrize("distance", [2.0, 4.5])
def test_laser_dot_visible_when_on_at_its_projection(indoor, distance):
    built, r = indoor
    spec = built.spec
    n = spec.laser_normal
    c = spec.laser_dot + n * distance + np.array([0, 0, 0.1])
    R = look_at_R(c[None], spec.laser_dot[None])[0]
    T = make_T(R, c)
    on = r.render(K, T, laser_on=True)
    off = r.render(K, T, laser_on=False)
    red = _red(on.rgb)
    assert red.sum() >= 9 and not _red(off.rgb).any()
    pc = apply_T(invert_T(T), spec.laser_dot[None])[0]
    uv = pc[:2] / pc[2] * [K.fx, K.fy] + [K.cx, K.cy]
    ys, xs = np.nonzero(red)
    assert np.hypot(xs.mean() - uv[0], ys.mean() - uv[1]) < 1.0
    assert np.hypot(xs - uv[0], ys - uv[1]).max() < 8


def test_laser_dot_hidden_behind_the_body(indoor):
    built, r = indoor
    spec = built.spec
    c = spec.laser_dot + spec.laser_normal * 3.0
    T = make_T(look_at_R(c[None], spec.laser_dot[None])[0], c)
    v, f = box_mesh((spec.laser_dot + spec.laser_normal * 1.0)[None], np.full((1, 3), 0.4))
    out = r.render(K, T, (v, f), laser_on=True)
    assert not _red(out.rgb).any()


def test_sift_finds_keypoints_and_geometrically_correct_matches(indoor):
    cv2 = pytest.importorskip("cv2")
    built, r = indoor
    T_all = trajectory.scene_walk(built.spec, 20.0, 30.0, np.random.default_rng(3))
    sift = cv2.SIFT_create()
    ok_rates = []
    for i in (30, 300):
        Ta, Tb = T_all[i], T_all[i + 8]
        a, b = r.render(K, Ta), r.render(K, Tb)
        ka, da = sift.detectAndCompute(cv2.cvtColor(a.rgb, cv2.COLOR_RGB2GRAY), None)
        kb, db = sift.detectAndCompute(cv2.cvtColor(b.rgb, cv2.COLOR_RGB2GRAY), None)
        assert len(ka) >= 300 and len(kb) >= 300
        pairs = cv2.BFMatcher().knnMatch(da, db, k=2)
        good = [m for m, n2 in pairs if m.distance < 0.75 * n2.distance]
        assert len(good) >= 50
        pa = np.array([ka[m.queryIdx].pt for m in good])
        pb = np.array([kb[m.trainIdx].pt for m in good])
        # True correspondence: back-project with the rendered depth, project into view b.
        z = a.depth_m[np.rint(pa[:, 1]).astype(int), np.rint(pa[:, 0]).astype(int)].astype(np.float64)
        pc = np.column_stack([(pa[:, 0] - K.cx) / K.fx * z, (pa[:, 1] - K.cy) / K.fy * z, z])
        qb = apply_T(invert_T(Tb) @ Ta, pc)
        proj = qb[:, :2] / qb[:, 2:] * [K.fx, K.fy] + [K.cx, K.cy]
        ok_rates.append(np.mean(np.linalg.norm(proj - pb, axis=1) < 2.0))
    assert min(ok_rates) > 0.7, ok_rates


def test_rendering_is_deterministic(outdoor):
    built, _ = outdoor
    T = _walk_poses(built.spec, n=1)[0]
    a = Renderer(built).render(K, T, laser_on=True, depth_intrinsics=K_LR)
    b = Renderer(built).render(K, T, laser_on=True, depth_intrinsics=K_LR)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth_lr_m, b.depth_lr_m)
    c = Renderer(built, RenderConfig(seed=1)).render(K, T)
    assert not np.array_equal(a.rgb, c.rgb)  # different sensor noise
    assert np.abs(a.rgb.astype(int) - c.rgb.astype(int)).mean() < 6


# ------------------------------------------------------------------------------------------------
# LiDAR


def test_lidar_noise_matches_the_config():
    cfg = lidar.LidarConfig()
    rng = np.random.default_rng(0)
    for d, factor in ((1.0, 1.0), (2.5, 1.0), (4.0, cfg.medium_noise_factor)):
        depth = np.full((192, 256), d, np.float32)
        mm, conf = lidar.simulate_lidar(depth, rng, cfg)
        assert mm.dtype == np.uint16 and conf.dtype == np.uint8
        valid = mm > 0
        assert 0.005 < 1 - valid.mean() < 0.05  # holes: a few percent
        err = mm[valid] / 1000.0 - d
        expected = (cfg.sigma_base_m + cfg.sigma_rel * d) * factor
        assert abs(err.mean()) < 0.1 * expected
        assert err.std() == pytest.approx(expected, rel=0.05)
        assert np.all(conf[valid] == (2 if d < cfg.medium_range_m else 1)) and np.all(conf[~valid] == 0)


def test_lidar_range_edges_and_determinism():
    cfg = lidar.LidarConfig(hole_fraction=0.0)
    depth = np.full((192, 256), 2.0, np.float32)
    depth[:, 128:] = 3.0  # a depth edge
    depth[:20] = 6.0  # beyond range
    depth[-10:] = 0.0  # no return
    mm, conf = lidar.simulate_lidar(depth, np.random.default_rng(1), cfg)
    assert np.all(mm[:20] == 0) and np.all(mm[-10:] == 0) and np.all(conf[:20] == 0)
    assert np.all(conf[30:150, 127:129] == 0)  # both sides of the edge
    assert np.all(conf[30:150, 10:120] == 2)
    mm2, conf2 = lidar.simulate_lidar(depth, np.random.default_rng(1), cfg)
    assert np.array_equal(mm, mm2) and np.array_equal(conf, conf2)
    # Low-confidence pixels are noisier, as on the real sensor.
    big = np.full((400, 400), 2.0, np.float32)
    big[::4] = 2.6  # stripes: every pixel next to a stripe is an edge pixel
    mm, conf = lidar.simulate_lidar(big, np.random.default_rng(2), cfg)
    err = mm / 1000.0 - big
    assert (conf == 0).sum() > 1000 and (conf == 2).sum() > 1000
    assert err[conf == 0].std() > 2 * err[conf == 2].std()


def test_body_reaching_behind_the_camera_is_still_masked_exactly(indoor):
    built, r = indoor
    spec = built.spec
    c = np.array([*(spec.walk_area_min_xy + spec.walk_area_max_xy) / 2, 1.2])
    T = _pose([[0, -1, 0], [0, 0, -1], [1, 0, 0]], c)  # looking along +x; camera right = -y
    # A long box beside the camera, from 1 m behind it to 1.5 m in front.
    v, f = box_mesh(np.array([[c[0] + 0.25, c[1] - 0.4, 1.2]]), np.array([[2.5, 0.3, 0.6]]))
    empty = r.render(K, T, depth_intrinsics=K_LR)
    full = r.render(K, T, (v, f), depth_intrinsics=K_LR)
    assert full.person_mask.sum() > 5000
    assert np.array_equal(full.person_mask, full.depth_m < empty.depth_m - 1e-6)
    assert np.array_equal(full.person_mask_lr, full.depth_lr_m < empty.depth_lr_m - 1e-6)
