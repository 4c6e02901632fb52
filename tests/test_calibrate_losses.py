"""Stage III refinement losses: gradients against finite differences, known answers, builders."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodmocap.calibrate import losses as L
from embodmocap.geometry.transforms import invert_T, make_T, rot_x, rot_z

K = np.array([[400.0, 0.0, 159.5], [0.0, 400.0, 119.5], [0.0, 0.0, 1.0]])


def cameras(n=6, seed=0):
    rng = np.random.default_rng(seed)
    R = rot_z(rng.uniform(-np.pi, np.pi, n)) @ rot_x(np.full(n, -np.pi / 2))  # looking horizontally
    return make_T(R, rng.uniform([-1, -1, 1], [1, 1, 2], (n, 3)))


def params(yaw, t):
    y = torch.tensor(float(yaw), dtype=torch.float64, requires_grad=True)
    return y, torch.tensor(np.asarray(t, dtype=np.float64), requires_grad=True)


def world_offset(yaw, t, pivot):
    """The world-side 4x4 equivalent of the pivoted offset."""
    return make_T(rot_z(yaw), L.world_side_translation(yaw, np.asarray(t), pivot))


@pytest.mark.parametrize("kind", L.ROBUST_KINDS)
def test_irls_weight_is_the_kernel_derivative(kind):
    s = torch.linspace(0.0, 0.05, 41, dtype=torch.float64)[1:].requires_grad_(True)
    scale = 0.07
    (g,) = torch.autograd.grad(L.robust_rho(s, kind, scale).sum(), s)
    torch.testing.assert_close(g * scale**2, L.irls_weight(s.detach(), kind, scale))
    # near zero every kernel is the plain squared error over scale^2
    small = torch.tensor([1e-8], dtype=torch.float64)
    assert float(L.robust_rho(small, kind, scale)) == pytest.approx(1e-8 / scale**2, rel=1e-5)


def test_offset_matches_world_side_transform():
    T = cameras()
    cams = L.Cameras.from_T(T)
    yaw, t = 0.3, np.array([0.1, -0.2, 0.05])
    p_cam = np.random.default_rng(1).normal(0, 1, (len(T), 3)) + [0, 0, 3]
    frames = torch.arange(len(T))
    got = L.cam_to_world(torch.tensor(yaw, dtype=torch.float64), torch.tensor(t), cams, frames, torch.tensor(p_cam))
    D = world_offset(yaw, t, cams.pivot.numpy())
    want = np.einsum("nij,nj->ni", (D @ T)[:, :3, :3], p_cam) + (D @ T)[:, :3, 3]
    np.testing.assert_allclose(got.numpy(), want, atol=1e-12)


def test_track_residual_known_answer_and_gradient():
    Ta, Tb = cameras(seed=0), cameras(seed=1)
    rng = np.random.default_rng(2)
    pw = rng.normal(0, 0.3, (len(Ta), 3)) + [0, 0, 1]
    frames = np.arange(len(Ta))
    pa = np.einsum("nji,nj->ni", Ta[:, :3, :3], pw - Ta[:, :3, 3])
    pb = np.einsum("nji,nj->ni", Tb[:, :3, :3], pw - Tb[:, :3, 3])
    pairs = L.make_track_pairs(("a", "b"), frames, pa, pb, rng.uniform(0.5, 1, len(pa)))
    ca, cb = L.Cameras.from_T(Ta), L.Cameras.from_T(Tb)
    zero = params(0.0, [0, 0, 0])
    r = L.track_residuals(zero, zero, ca, cb, pairs)
    np.testing.assert_allclose(r.detach().numpy(), 0, atol=1e-12)
    # a pure translation of view a shows up as exactly that residual everywhere
    r = L.track_residuals(params(0.0, [0.1, 0.0, -0.02]), zero, ca, cb, pairs)
    np.testing.assert_allclose(r.detach().numpy(), np.tile([0.1, 0.0, -0.02], (len(pa), 1)), atol=1e-12)
    for kind in L.ROBUST_KINDS:
        f = lambda ya, ta, yb, tb: L.track_loss((ya, ta), (yb, tb), ca, cb, pairs, kind, 0.05)[0]  # noqa: E731
        assert torch.autograd.gradcheck(f, (*params(0.02, [0.03, -0.04, 0.01]), *params(-0.01, [0.0, 0.05, 0.02])))


def room():
    # a closed box as a mesh: 8 vertices, 12 triangles
    lo, hi = np.array([-2.0, -2.0, 0.0]), np.array([2.0, 2.5, 2.5])
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads])
    return v, f, lo, hi


def test_scene_points_lie_on_the_mesh():
    v, f, lo, hi = room()
    sp = L.ScenePoints.from_mesh(v, f, n_points=5000, seed=0)
    p, n = sp.points.numpy(), sp.normals.numpy()
    on_face = np.minimum(np.abs(p - lo), np.abs(p - hi)).min(axis=1)
    assert on_face.max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    # each normal is the axis of the face the point is on
    axis = np.argmin(np.minimum(np.abs(p - lo), np.abs(p - hi)), axis=1)
    assert np.all(np.abs(n[np.arange(len(n)), axis]) > 0.999)


def test_chamfer_point_to_plane_known_answer_and_gradient():
    v, f, lo, hi = room()
    scene = L.ScenePoints.from_mesh(v, f, n_points=20000, seed=0)
    T = cameras(n=4)
    rng = np.random.default_rng(3)
    # points on the floor and the x = 2 wall, in camera coordinates
    pw = np.concatenate([
        np.c_[rng.uniform(-1.5, 1.5, (50, 2)), np.zeros(50)],
        np.c_[np.full(50, 2.0), rng.uniform(-1.5, 1.5, 50), rng.uniform(0.5, 2.0, 50)],
    ])
    frames = rng.integers(0, len(T), len(pw))
    pc = np.einsum("nji,nj->ni", T[frames, :3, :3], pw - T[frames, :3, 3])
    cloud = L.BackgroundCloud(torch.as_tensor(frames), torch.as_tensor(pc))
    cams = L.Cameras.from_T(T)
    loss, diag = L.chamfer_loss(params(0, [0, 0, 0]), cams, cloud, scene)
    assert loss.item() < 1e-20 and diag["n"] == 100
    # lifting by 2 cm: floor points are 2 cm off their plane, wall points slide along theirs
    lift = params(0.0, [0.0, 0.0, 0.02])
    nbr = L.nearest_scene(scene, L.chamfer_world_points(lift, cams, cloud))
    r = L.chamfer_residuals(lift, cams, cloud, scene, nbr).detach().numpy()
    np.testing.assert_allclose(np.abs(r[:50]), 0.02, atol=1e-9)
    np.testing.assert_allclose(r[50:], 0.0, atol=1e-9)
    p0 = params(0.01, [0.01, -0.02, 0.015])
    nbr = L.nearest_scene(scene, L.chamfer_world_points(p0, cams, cloud))
    for kind in L.ROBUST_KINDS:
        fn = lambda y, t: L.chamfer_loss((y, t), cams, cloud, scene, nbr, kind, 0.01)[0]  # noqa: E731
        assert torch.autograd.gradcheck(fn, p0)


def test_reprojection_matches_explicit_projection_and_gradient():
    T = cameras(n=5)
    cams = L.Cameras.from_T(T)
    rng = np.random.default_rng(4)
    frames = np.repeat(np.arange(len(T)), 10)
    # points 2-4 m in front of each camera
    pc = np.c_[rng.uniform(-1, 1, (len(frames), 2)), rng.uniform(2, 4, len(frames))]
    xyz = np.einsum("nij,nj->ni", T[frames, :3, :3], pc) + T[frames, :3, 3]
    xy = (pc[:, :2] / pc[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2]
    m = L.Matches2D3D.from_arrays(frames, xy, xyz)
    Kt = torch.as_tensor(K)
    np.testing.assert_allclose(L.reproj_residuals(params(0, [0, 0, 0]), cams, Kt, m).detach().numpy(), 0, atol=1e-9)
    # against projecting with the explicitly offset cameras
    yaw, t = 0.05, np.array([0.05, -0.03, 0.02])
    D = world_offset(yaw, t, cams.pivot.numpy())
    Tc = invert_T(D @ T)[frames]
    q = np.einsum("nij,nj->ni", Tc[:, :3, :3], xyz) + Tc[:, :3, 3]
    want = xy - ((q[:, :2] / q[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2])
    got = L.reproj_residuals(params(yaw, t), cams, Kt, m).detach().numpy()
    np.testing.assert_allclose(got, want, atol=1e-9)
    for kind in L.ROBUST_KINDS:
        fn = lambda y, tt: L.reproj_loss((y, tt), cams, Kt, m, kind, 2.0)[0]  # noqa: E731
        assert torch.autograd.gradcheck(fn, params(0.01, [0.02, 0.01, -0.01]))


def test_keypoint_correspondences_filter_by_confidence_and_joint():
    rng = np.random.default_rng(5)
    ka, kb = rng.uniform(0, 300, (4, 17, 3)), rng.uniform(0, 300, (4, 17, 3))
    ka[..., 2], kb[..., 2] = 0.9, 0.8
    ka[1, 7, 2] = 0.3  # one low-confidence left elbow
    c = L.KeypointCorrespondences(ka, kb).correspondences()
    assert len(c.frames) == 4 * 12 - 1
    assert np.all(c.weight == 0.8)
    first = (c.frames == 0)
    np.testing.assert_array_equal(c.xy_a[first], ka[0, 5:, :2])
    np.testing.assert_allclose(c.behind_surface_m[first], L.JOINT_DEPTH_BEHIND_SURFACE_M[5:])


def test_sample_depth_rescales_pixels_and_skips_holes():
    # depth grid at half resolution: each depth pixel's value encodes its column
    h, w = 60, 80
    d = np.tile(np.arange(w, dtype=np.float64) * 0.01 + 1.0, (h, 1))
    d[10, 20] = 0.0  # a hole: the median of the neighbourhood covers it
    xy = np.array([[40.5, 20.5], [1.0, 1.0], [500.0, 20.0]])  # the last is outside
    got = L.sample_depth(lambda t: d, np.zeros(3, dtype=np.int64), xy, (160, 120))
    assert got[0] == pytest.approx(1.20)
    assert got[1] == pytest.approx(1.00, abs=0.011)
    assert got[2] == 0.0


def test_track_pairs_from_depth_reach_the_joint_centre():
    # a flat "body" at 2 m in both cameras; the joint lies 5 cm behind it along each ray
    Kd = K.copy()
    depth = lambda t: np.full((240, 320), 2.0)  # noqa: E731
    corr = L.Correspondences(
        frames=np.array([0, 3]), xy_a=np.array([[159.5, 119.5], [200.0, 100.0]]),
        xy_b=np.array([[159.5, 119.5], [10.0, 10.0]]), weight=np.array([1.0, 0.7]),
        behind_surface_m=np.array([0.05, 0.0]),
    )
    pairs = L.track_pairs_from_depth(corr, ("a", "b"), (depth, depth), (Kd, Kd), ((320, 240), (320, 240)))
    np.testing.assert_allclose(pairs.p_a[0].numpy(), [0, 0, 2.05])
    ray = np.array([(200 - 159.5) / 400, (100 - 119.5) / 400, 1.0])
    np.testing.assert_allclose(pairs.p_a[1].numpy(), 2.0 * ray)
    assert pairs.weight.tolist() == [1.0, 0.7]
    far = L.track_pairs_from_depth(corr, ("a", "b"), (depth, depth), (Kd, Kd), ((320, 240),) * 2, max_depth_m=1.5)
    assert len(far) == 0


def test_background_cloud_removes_the_person():
    h, w = 120, 160
    d = np.full((h, w), 3.0)
    d[40:80, 60:100] = 1.0  # the person
    mask = np.zeros((240, 320), dtype=bool)
    mask[80:160, 120:200] = True  # the same region at RGB resolution
    Kd = K * [[0.5], [0.5], [1]]
    cloud = L.background_cloud(lambda t: d, lambda t: mask, np.array([0, 2]), Kd, points_per_frame=3000, seed=0)
    assert len(cloud) == 6000
    np.testing.assert_allclose(cloud.p_cam[:, 2].numpy(), 3.0)
    assert set(cloud.frames.tolist()) == {0, 2}
    without = L.background_cloud(lambda t: d, None, np.array([0]), Kd, points_per_frame=h * w)
    assert np.isclose(without.p_cam[:, 2].numpy(), 1.0).sum() == 40 * 40
