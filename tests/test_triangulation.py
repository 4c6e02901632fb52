"""Multi-view triangulation against synthetic cameras with known 3D points."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.geometry.transforms import invert_T, look_at_T, make_T, rot_z
from embodmocap.geometry.triangulation import (
    Triangulation,
    TriangulationConfig,
    fill_gaps,
    projection_matrices,
    triangulate,
    triangulate_loop,
)

K = np.array([[900.0, 0.0, 360.0], [0.0, 900.0, 480.0], [0.0, 0.0, 1.0]])
NO_REJECT = TriangulationConfig(reject_px=np.inf, max_gap_frames=0)


def ring_cameras(V, T=None, radius=4.0, offset=(0.0, 0.0, 0.0)):
    """V cameras on a ring around ``offset`` + (0, 0, 1); (V, 4, 4), or (T, V, 4, 4) if T is
    given: then the ring turns and the cameras bob over time (hand-held)."""
    offset = np.asarray(offset)
    target = offset + [0.0, 0.0, 1.0]
    ang = np.linspace(0, 2 * np.pi, V, endpoint=False) + 0.3
    if T is None:
        centres = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.full(V, 1.6)], -1) + offset
        return look_at_T(centres, target)
    t = np.arange(T)[:, None]
    a = ang[None] + 0.01 * t
    centres = np.stack([radius * np.cos(a), radius * np.sin(a), 1.6 + 0.2 * np.sin(0.1 * t + ang)], -1) + offset
    return look_at_T(centres, np.broadcast_to(target, centres.shape) + 0.1 * np.sin(0.05 * t)[..., None])


def project(P, X):
    """P (V, 3, 4) or (T, V, 3, 4), X (T, J, 3) -> (T, V, J, 2) pixels."""
    P = P if P.ndim == 4 else P[None]
    h = np.einsum("tvij,tkj->tvki", P[..., :3], X) + P[:, :, None, :, 3]
    return h[..., :2] / h[..., 2:]


def body_points(rng, T, J, offset=(0.0, 0.0, 0.0)):
    """(T, J, 3) points in a 1 m box around ``offset`` + (0, 0, 1)."""
    return rng.uniform(-0.5, 0.5, size=(T, J, 3)) + np.asarray(offset) + [0.0, 0.0, 1.0]


def expected_sq_error(P, X, sigma, conf=None):
    """First-order mean squared 3D error of the (weighted) DLT, per point: (T, J).

    P (V, 3, 4); X (T, J, 3); sigma (V,) pixel noise std of each view; conf (V,) the DLT row
    scales (None: 1). A DLT row's residual is the pixel error times the depth, so the estimate is
    a least-squares fit of pixels with weights w = (conf * depth)^2; its covariance is the sandwich
    A^-1 B A^-1 with A = sum w J^T J and B = sum w^2 sigma^2 J^T J (J: projection Jacobian).
    """
    conf = np.ones(len(P)) if conf is None else np.asarray(conf)
    h = np.einsum("vij,tkj->tkvi", P[..., :3], X) + P[:, :, 3]  # (T, J, V, 3)
    # d(u, v)/dX = (P_row[:3] * h2 - P2[:3] * h_row) / h2^2 for rows 0 and 1
    depth = h[..., 2, None, None]
    jac = (P[None, None, :, :2, :3] * depth - P[None, None, :, 2, None, :3] * h[..., :2, None]) / depth**2
    w = (conf * h[..., 2]) ** 2  # (T, J, V)
    A = np.einsum("tkvri,tkvrj,tkv->tkij", jac, jac, w)
    B = np.einsum("tkvri,tkvrj,tkv->tkij", jac, jac, w**2 * np.asarray(sigma) ** 2)
    Ai = np.linalg.inv(A)
    return np.trace(Ai @ B @ Ai, axis1=-2, axis2=-1)


# ---------------------------------------------------------------------------------------------


def test_projection_matrices_match_camera_transform():
    rng = np.random.default_rng(1)
    T_wc = ring_cameras(3, T=5)  # (5, 3, 4, 4)
    Ks = np.stack([K, K * [[1.1], [1.1], [1.0]], K * [[0.9], [0.9], [1.0]]])
    P = projection_matrices(Ks, T_wc)
    assert P.shape == (5, 3, 3, 4)
    X = rng.normal(size=3) + [0, 0, 1]
    p_cam = np.einsum("tvij,j->tvi", invert_T(T_wc)[..., :3, :3], X) + invert_T(T_wc)[..., :3, 3]
    uv_ref = np.einsum("vij,tvj->tvi", Ks, p_cam)
    uv_ref = uv_ref[..., :2] / uv_ref[..., 2:]
    h = P @ np.append(X, 1.0)
    np.testing.assert_allclose(h[..., :2] / h[..., 2:], uv_ref, atol=1e-9)
    assert projection_matrices(K, T_wc[0]).shape == (3, 3, 4)


@pytest.mark.parametrize("V", [2, 3, 4])
@pytest.mark.parametrize("moving", [False, True])
def test_exact_recovery_noise_free(V, moving):
    rng = np.random.default_rng(V)
    T, J = 40, 17
    # far from the origin on purpose: the solver must stay exact there too
    offset = (60.0, -25.0, 3.0)
    P = projection_matrices(K, ring_cameras(V, T if moving else None, offset=offset))
    X = body_points(rng, T, J, offset)
    xy = project(P, X)
    conf = rng.uniform(0.5, 1.0, size=(T, V, J))
    res = triangulate(P, xy, conf)
    assert isinstance(res, Triangulation)
    np.testing.assert_allclose(res.points, X, atol=1e-8)
    assert res.used.all() and not res.filled.any() and res.long_gaps == []
    assert np.nanmax(res.reproj_err_px) < 1e-6
    np.testing.assert_allclose(res.conf, conf.sum(axis=1) / V)


def test_noise_error_at_expected_level_and_weighting_beats_unweighted():
    rng = np.random.default_rng(7)
    T, J, V = 400, 17, 3
    P = projection_matrices(K, ring_cameras(V))
    X = body_points(rng, T, J)
    clean = project(P, X)

    # equal noise, equal confidence: mean squared error matches the Cramer-Rao level
    sigma = np.array([1.0, 1.0, 1.0])
    xy = clean + rng.normal(size=clean.shape) * sigma[None, :, None, None]
    res = triangulate(P, xy, np.ones((T, V, J)), NO_REJECT)
    mse = np.mean(np.sum((res.points - X) ** 2, axis=-1))
    expected = np.mean(expected_sq_error(P, X, sigma))
    assert 0.85 < mse / expected < 1.15, (mse, expected)

    # one view much noisier and less confident: weighting by confidence helps, by the amount the
    # first-order analysis predicts for each estimator
    sigma = np.array([12.0, 1.0, 1.0])
    c = np.array([0.35, 1.0, 1.0])
    xy = clean + rng.normal(size=clean.shape) * sigma[None, :, None, None]
    conf = np.broadcast_to(c[None, :, None], (T, V, J))
    weighted = triangulate(P, xy, conf, NO_REJECT).points
    unweighted = triangulate_loop(P, xy, conf, min_conf=0.3)
    mse_w = np.mean(np.sum((weighted - X) ** 2, -1))
    mse_u = np.mean(np.sum((unweighted - X) ** 2, -1))
    assert 0.85 < mse_w / np.mean(expected_sq_error(P, X, sigma, c)) < 1.15
    assert 0.85 < mse_u / np.mean(expected_sq_error(P, X, sigma)) < 1.15
    assert mse_w < 0.25 * mse_u, (mse_w, mse_u)  # measured 0.10


@pytest.mark.parametrize("V", [3, 4])
def test_outlier_view_is_rejected(V):
    rng = np.random.default_rng(11 + V)
    T, J = 60, 17
    P = projection_matrices(K, ring_cameras(V, T))
    X = body_points(rng, T, J)
    clean = project(P, X)
    xy = clean + rng.normal(size=clean.shape) * 1.0
    bad = xy.copy()
    bad[:, 1] += rng.choice([-1.0, 1.0], size=(T, J, 2)) * 100.0 / np.sqrt(2)  # 100 px off
    conf = np.ones((T, V, J))

    good = triangulate(P, xy, conf)
    fixed = triangulate(P, bad, conf)
    naive = triangulate(P, bad, conf, TriangulationConfig(reject_px=np.inf))
    err = lambda r: np.sqrt(np.mean(np.sum((r.points - X) ** 2, -1)))  # noqa: E731
    assert err(naive) > 5 * err(good)
    assert err(fixed) < 1.5 * err(good)
    assert not fixed.used[:, :, 1].any()  # the corrupted view dropped everywhere
    assert fixed.used.sum(-1).min() == V - 1
    assert np.all(fixed.reproj_err_px[:, :, 1] > 50)  # still reported for the rejected view
    assert np.nanmax(np.delete(fixed.reproj_err_px, 1, axis=-1)) < 15


def test_gap_filling_short_long_and_edge():
    rng = np.random.default_rng(3)
    T, J, V = 60, 4, 2
    P = projection_matrices(K, ring_cameras(V))
    t = np.arange(T)[:, None, None]
    X = body_points(rng, 1, J) + 0.01 * t * rng.normal(size=(1, J, 3))  # linear motion
    xy = project(P, X)
    conf = np.ones((T, V, J))
    conf[10:15, 0, 0] = 0.0  # joint 0: 5 frames seen by one view only -> filled
    conf[20:40, :, 1] = 0.0  # joint 1: 20 frames unseen -> too long
    conf[:3, 1, 2] = 0.1  # joint 2: first 3 frames below min_conf in one view -> edge gap
    res = triangulate(P, xy, conf, TriangulationConfig(max_gap_frames=10))

    np.testing.assert_allclose(res.points[10:15, 0], X[10:15, 0], atol=1e-9)
    assert res.filled[10:15, 0].all() and res.filled.sum() == 5
    assert np.all(res.conf[10:15, 0] == 0)
    assert np.isnan(res.points[20:40, 1]).all() and np.isfinite(res.points[40:, 1]).all()
    assert np.isnan(res.points[:3, 2]).all()
    assert sorted(res.long_gaps) == [(1, 20, 40), (2, 0, 3)]
    # the filled point reprojects onto the view that did see it
    assert np.all(res.reproj_err_px[10:15, 0, 1] < 1e-6)
    assert np.isnan(res.reproj_err_px[10:15, 0, 0]).all()


def test_fill_gaps_direct():
    T = 12
    pts = np.stack([np.arange(T, dtype=float)] * 3, -1)[:, None, :] * [1.0, 2.0, -1.0]
    valid = np.ones((T, 1), bool)
    valid[[0, 3, 4, 8]] = False
    out, filled = fill_gaps(np.where(valid[..., None], pts, 123.0), valid, 2)
    np.testing.assert_array_equal(filled[:, 0], [i in (3, 4, 8) for i in range(T)])
    np.testing.assert_allclose(out[1:], pts[1:])
    assert np.isnan(out[0]).all()
    out1, filled1 = fill_gaps(pts, valid, 1)  # the 2-frame gap is now too long
    assert np.isnan(out1[3:5]).all() and filled1[8, 0] and not filled1[3:5].any()


def test_joint_seen_by_one_view_is_nan():
    rng = np.random.default_rng(5)
    T, J, V = 10, 3, 3
    P = projection_matrices(K, ring_cameras(V))
    X = body_points(rng, T, J)
    xy = project(P, X)
    conf = np.ones((T, V, J))
    conf[:, 1:, 2] = 0.0  # joint 2 only in view 0
    xy[:, 2, 1] = np.nan  # a NaN pixel counts as not seen
    res = triangulate(P, xy, conf)
    assert np.isnan(res.points[:, 2]).all()
    assert np.all(res.conf[:, 2] == 0) and not res.used[:, 2].any()
    assert np.isnan(res.reproj_err_px[:, 2]).all()
    assert res.long_gaps == [(2, 0, T)]
    # joint 1 has two good views left and is exact
    np.testing.assert_allclose(res.points[:, 1], X[:, 1], atol=1e-8)
    assert not res.used[:, 1, 2].any()


@pytest.mark.parametrize("moving", [False, True])
def test_agrees_with_reference_loop_unweighted(moving):
    rng = np.random.default_rng(9)
    T, J, V = 30, 17, 3
    P = projection_matrices(K, ring_cameras(V, T if moving else None))
    X = body_points(rng, T, J)
    xy = project(P, X)
    xy = xy + rng.normal(size=xy.shape) * 3.0
    conf = np.where(rng.uniform(size=(T, V, J)) < 0.2, 0.0, 1.0)  # some views missing
    xy_in, conf_in = xy.copy(), conf.copy()
    ours = triangulate(P, xy, conf, NO_REJECT).points
    ref = triangulate_loop(P, xy, conf, min_conf=0.3)
    np.testing.assert_array_equal(np.isnan(ours), np.isnan(ref))
    assert np.isnan(ref).any()  # some joints had a single view
    np.testing.assert_allclose(ours, ref, atol=1e-9, equal_nan=True)
    np.testing.assert_array_equal(xy, xy_in)  # inputs untouched
    np.testing.assert_array_equal(conf, conf_in)


def test_point_behind_a_camera_is_not_a_triangulation():
    """Projective rays meet behind camera 0: the DLT finds that point, which no camera saw."""
    T_wc = ring_cameras(2)
    P = projection_matrices(K, T_wc)
    c0, fwd0 = T_wc[0, :3, 3], T_wc[0, :3, 2]
    X = np.array([[c0 - 1.5 * fwd0, [0.0, 0.0, 1.0]]])  # joint 0 behind camera 0, joint 1 fine
    xy = project(P, X)
    res = triangulate(P, xy, np.ones((1, 2, 2)))
    assert np.isnan(res.points[0, 0]).all() and res.conf[0, 0] == 0
    np.testing.assert_allclose(res.points[0, 1], X[0, 1], atol=1e-9)
    # the reference loop has no such check and returns the point behind the camera
    np.testing.assert_allclose(triangulate_loop(P, xy, np.ones((1, 2, 2)))[0, 0], X[0, 0], atol=1e-9)


def test_bad_shapes_raise():
    P = projection_matrices(K, ring_cameras(2))
    xy = np.zeros((5, 2, 17, 2))
    conf = np.ones((5, 2, 17))
    with pytest.raises(ValueError, match="points2d"):
        triangulate(P, xy[..., :1], conf)
    with pytest.raises(ValueError, match="conf"):
        triangulate(P, xy, conf[:, :, :16])
    with pytest.raises(ValueError, match="P must be"):
        triangulate(P[:1], xy, conf)
    with pytest.raises(ValueError, match="P must be"):
        triangulate(np.broadcast_to(P, (4, 2, 3, 4)), xy, conf)
    with pytest.raises(ValueError, match="at least 2 views"):
        triangulate(P[:1], xy[:, :1], conf[:, :1])
    with pytest.raises(ValueError, match="min_views"):
        triangulate(P, xy, conf, TriangulationConfig(min_views=1))
    with pytest.raises(ValueError, match="T_world_cam"):
        projection_matrices(K, np.eye(4))
    with pytest.raises(ValueError, match="K must be"):
        projection_matrices(np.stack([K] * 3), ring_cameras(2))
    with pytest.raises(ValueError, match="points must be"):
        fill_gaps(np.zeros((5, 3)), np.ones((5, 3), bool), 2)


def test_rot_z_rigid_motion_of_world_moves_points():
    """Moving the whole world (cameras) by a rigid transform moves the triangulated points."""
    rng = np.random.default_rng(2)
    T_wc = ring_cameras(3)
    X = body_points(rng, 8, 5)
    xy = project(projection_matrices(K, T_wc), X)
    M = make_T(rot_z(0.7), [1.0, -2.0, 0.5])
    res = triangulate(projection_matrices(K, M @ T_wc), xy, np.ones((8, 3, 5)))
    np.testing.assert_allclose(res.points, X @ M[:3, :3].T + M[:3, 3], atol=1e-8)


def test_two_view_point_whose_rays_miss_is_dropped_and_filled():
    """With 2 views no view can be dropped: a point whose rays miss by more than reject_px (one 2D
    keypoint misplaced) is treated as not triangulated and, in a short gap, interpolated."""
    rng = np.random.default_rng(5)
    T, J = 40, 17
    P = projection_matrices(K, ring_cameras(2, T))
    # A body walking at constant velocity, so that interpolation across one frame is exact.
    X = body_points(rng, 1, J)[0][None] + np.arange(T)[:, None, None] * np.array([0.02, 0.01, 0.0])
    xy = project(P, X) + rng.normal(size=(T, 2, J, 2)) * 0.5
    xy[20, 0, 3] += [80.0, 0.0]  # one keypoint of one view 80 px off (a swapped limb, say)
    conf = np.ones((T, 2, J))
    res = triangulate(P, xy, conf)
    kept = triangulate(P, xy, conf, TriangulationConfig(drop_unresolved=False))
    assert kept.reproj_err_px[20, 3].max() > 15 and np.linalg.norm(kept.points[20, 3] - X[20, 3]) > 0.05
    assert res.filled[20, 3] and res.conf[20, 3] == 0.0  # dropped, then filled from frames 19 and 21
    assert np.linalg.norm(res.points[20, 3] - X[20, 3]) < np.linalg.norm(kept.points[20, 3] - X[20, 3]) / 3
    # Nothing else changed.
    others = np.ones((T, J), bool)
    others[20, 3] = False
    np.testing.assert_allclose(res.points[others], kept.points[others])
