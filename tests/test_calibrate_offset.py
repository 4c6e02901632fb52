"""Yaw-only offset: closed form, hand-computed case, free scale, RANSAC + IRLS with gross outliers."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.calibrate.offset import (
    RobustOffsetConfig,
    YawOffset,
    fit_yaw_offset,
    residuals,
    robust_yaw_offset,
)
from embodmocap.geometry.transforms import make_T, rot_x, rot_z


def _walk(n: int, seed: int) -> np.ndarray:
    """(n, 3) camera centres of a wandering handheld path, metres."""
    rng = np.random.default_rng(seed)
    xy = np.cumsum(rng.normal(0, 0.05, (n, 2)), axis=0) + rng.uniform(-1, 1, 2)
    z = 1.4 + 0.1 * np.sin(np.linspace(0, 6, n))
    return np.column_stack([xy, z])


def _yaw_err(a: float, b: float) -> float:
    return abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def test_hand_computed_quarter_turn():
    # VIO points (1,0,0), (0,1,0) -> world (0,1,0)+t, (-1,0,0)+t: a +90 degree yaw, t = (2, 3, 0.5).
    v = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    w = np.array([[2.0, 4, 0.5], [1.0, 3, 0.5], [2.0, 3, 1.5]])
    off = fit_yaw_offset(v, w)
    assert off.yaw_rad == pytest.approx(np.pi / 2, abs=1e-12)
    np.testing.assert_allclose(off.t, [2, 3, 0.5], atol=1e-12)
    assert off.scale == 1.0
    np.testing.assert_allclose(off.T, make_T(rot_z(np.pi / 2), np.array([2, 3, 0.5])), atol=1e-12)


@pytest.mark.parametrize("yaw", [-3.0, -0.7, 0.0, 0.4, 2.9])
def test_closed_form_is_exact_on_noise_free_data(yaw):
    v = _walk(50, 1)
    true = YawOffset(yaw, np.array([0.3, -2.0, 0.25]))
    off = fit_yaw_offset(v, true.apply_points(v))
    assert _yaw_err(off.yaw_rad, yaw) < 1e-10
    np.testing.assert_allclose(off.t, true.t, atol=1e-10)
    assert np.max(residuals(off, v, true.apply_points(v))) < 1e-10


def test_weights_select_the_points_that_count():
    v = _walk(40, 2)
    true = YawOffset(1.1, np.array([1.0, 2.0, 0.0]))
    w = true.apply_points(v)
    w[:10] += np.array([0.5, -0.4, 0.2])  # corrupted, but given zero weight
    wt = np.r_[np.zeros(10), np.ones(30)]
    off = fit_yaw_offset(v, w, wt)
    assert _yaw_err(off.yaw_rad, 1.1) < 1e-10
    np.testing.assert_allclose(off.t, true.t, atol=1e-10)


def test_free_scale_recovers_a_known_scale():
    v = _walk(60, 3)
    true = YawOffset(-0.8, np.array([-1.0, 0.5, 0.1]), scale=1.07)
    w = true.apply_points(v)
    off = fit_yaw_offset(v, w, free_scale=True)
    assert off.scale == pytest.approx(1.07, abs=1e-10)
    assert _yaw_err(off.yaw_rad, -0.8) < 1e-10
    np.testing.assert_allclose(off.t, true.t, atol=1e-10)
    # With the scale fixed the fit is worse, not the same.
    assert np.max(residuals(fit_yaw_offset(v, w), v, w)) > 1e-3
    robust = robust_yaw_offset(v, w, RobustOffsetConfig(free_scale=True))
    assert robust.offset.scale == pytest.approx(1.07, abs=1e-8)


def test_apply_maps_poses_like_the_matrix():
    off = YawOffset(0.6, np.array([1.0, -1.0, 0.2]))
    T_vio_cam = np.stack([make_T(rot_z(a) @ rot_x(-1.4), np.array([a, 2 * a, 1.5])) for a in (0.1, 0.5, 1.0)])
    np.testing.assert_allclose(off.apply(T_vio_cam), off.T @ T_vio_cam, atol=1e-12)
    scaled = YawOffset(0.6, np.array([1.0, -1.0, 0.2]), scale=2.0)
    out = scaled.apply(T_vio_cam)
    np.testing.assert_allclose(out[:, :3, 3], scaled.apply_points(T_vio_cam[:, :3, 3]))
    np.testing.assert_allclose(np.einsum("nba,nbc->nac", out[:, :3, :3], out[:, :3, :3]),
                               np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ransac_survives_30_percent_gross_outliers(seed):
    rng = np.random.default_rng(seed)
    n = 120
    v = _walk(n, 10 + seed)
    true = YawOffset(rng.uniform(-np.pi, np.pi), rng.uniform(-3, 3, 3))
    w = true.apply_points(v) + rng.normal(0, 0.01, (n, 3))  # registration noise, 1 cm
    bad = rng.permutation(n)[: int(0.3 * n)]
    # Wrong registrations: 0.4 to 2.5 m off, mostly towards one side (a repeated structure).
    side = _unit(rng.normal(size=(1, 3)))
    w[bad] += rng.uniform(0.4, 2.5, (len(bad), 1)) * _unit(side + 0.5 * rng.normal(size=(len(bad), 3)))
    # Plain least squares is pulled off by the outliers ...
    plain = fit_yaw_offset(v, w)
    assert np.linalg.norm(plain.t - true.t) > 0.1
    # ... the robust fit is not: it matches the least-squares fit on the clean frames alone (the
    # statistical floor set by the 1 cm noise) and flags exactly the corrupted frames.
    expected = np.ones(n, bool)
    expected[bad] = False
    oracle = fit_yaw_offset(v[expected], w[expected])
    fit = robust_yaw_offset(v, w)
    assert _yaw_err(fit.offset.yaw_rad, oracle.yaw_rad) < np.radians(0.1)
    assert np.linalg.norm(fit.offset.t - oracle.t) < 0.005
    assert _yaw_err(fit.offset.yaw_rad, true.yaw_rad) < np.radians(0.6)
    assert np.linalg.norm(fit.offset.t - true.t) < 0.02
    np.testing.assert_array_equal(fit.inliers, expected)
    assert np.all(fit.weights[bad] == 0)
    assert np.median(fit.residuals_m[fit.inliers]) < 0.03


def test_huber_kernel_also_converges():
    rng = np.random.default_rng(5)
    v = _walk(80, 5)
    true = YawOffset(2.0, np.array([0.5, 0.5, 0.0]))
    w = true.apply_points(v) + rng.normal(0, 0.005, (80, 3))
    w[:20] += 1.0
    fit = robust_yaw_offset(v, w, RobustOffsetConfig(kernel="huber"))
    assert _yaw_err(fit.offset.yaw_rad, 2.0) < np.radians(0.3)
    assert fit.num_inliers == 60


def test_degenerate_inputs_raise():
    v = np.tile([[1.0, 2.0, 0.0]], (5, 1))
    v[:, 2] = np.arange(5)  # a vertical line: no horizontal spread
    with pytest.raises(ValueError, match="horizontal spread"):
        fit_yaw_offset(v, v)
    with pytest.raises(ValueError, match="apart horizontally"):
        robust_yaw_offset(v, v)
    with pytest.raises(ValueError, match="at least 2"):
        robust_yaw_offset(v[:1], v[:1])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fit_yaw_offset(v, v[:3])


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=1, keepdims=True)
