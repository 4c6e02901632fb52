"""Weighted Umeyama and similarity helpers (embodmocap.geometry.similarity) against known answers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embodmocap.evaluate.metrics import umeyama
from embodmocap.geometry.similarity import (apply_similarity, mean_rotation, robust_umeyama, rotation_between,
                                            similarity_matrix, similarity_parts, transform_poses, weighted_umeyama)


def _random_similarity(rng):
    return rng.uniform(0.2, 5.0), Rotation.random(random_state=rng.integers(1 << 30)).as_matrix(), rng.normal(size=3) * 3


def test_known_similarity_is_recovered_exactly():
    rng = np.random.default_rng(0)
    for _ in range(20):
        s, R, t = _random_similarity(rng)
        x = rng.normal(size=(50, 3))
        y = s * x @ R.T + t
        w = rng.uniform(0.1, 2.0, size=50)
        s2, R2, t2 = weighted_umeyama(x, y, w)
        assert abs(s2 - s) < 1e-9 * s and np.allclose(R2, R, atol=1e-9) and np.allclose(t2, t, atol=1e-8)
        assert abs(np.linalg.det(R2) - 1) < 1e-9


def test_equal_weights_match_the_unweighted_umeyama():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(4, 30, 3))
    y = x @ Rotation.random(4, random_state=2).as_matrix().transpose(0, 2, 1) * 1.7 + 0.3 + rng.normal(size=(4, 30, 3)) * 0.1
    s, R, t = weighted_umeyama(x, y, np.full((4, 30), 3.0))
    s0, R0, t0 = umeyama(x, y)
    assert np.allclose(s, s0) and np.allclose(R, R0) and np.allclose(t, t0)


def test_reflection_is_never_returned():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(40, 3))
    y = x * np.array([1.0, 1.0, -1.0])  # a mirror image: the best rotation, not the reflection
    s, R, t = weighted_umeyama(x, y)
    assert np.linalg.det(R) > 0.99


def test_weights_down_weight_outliers():
    rng = np.random.default_rng(4)
    s, R, t = _random_similarity(rng)
    x = rng.normal(size=(200, 3))
    y = s * x @ R.T + t
    y[:40] += rng.normal(size=(40, 3)) * 3 * s  # 20 % gross outliers
    plain = weighted_umeyama(x, y)
    w = np.ones(200)
    w[:40] = 1e-6
    weighted = weighted_umeyama(x, y, w)
    assert abs(plain[0] / s - 1) > 0.05  # the outliers ruin the plain fit ...
    assert abs(weighted[0] / s - 1) < 1e-5 and np.allclose(weighted[1], R, atol=1e-5)  # ... not the weighted one
    # Without knowing which points are bad, the re-weighted fit finds them.
    s3, R3, t3, w3 = robust_umeyama(x, y)
    assert abs(s3 / s - 1) < 0.01 and np.allclose(R3, R, atol=0.01)
    assert w3[:40].mean() < 0.2 * w3[40:].mean()


def test_zero_weights_and_bad_input():
    x = np.random.default_rng(5).normal(size=(10, 3))
    s, R, t = weighted_umeyama(x, x + 1, np.zeros(10))
    assert s == 1.0 and np.allclose(R, np.eye(3))
    with pytest.raises(ValueError):
        weighted_umeyama(x, x, -np.ones(10))
    with pytest.raises(ValueError):
        weighted_umeyama(x, x[:5])


def test_matrix_helpers_round_trip_and_compose():
    rng = np.random.default_rng(6)
    a, b = _random_similarity(rng), _random_similarity(rng)
    A, B = similarity_matrix(*a), similarity_matrix(*b)
    s, R, t = similarity_parts(A @ B)
    assert np.isclose(s, a[0] * b[0]) and np.allclose(R, a[1] @ b[1])
    p = rng.normal(size=(7, 3))
    assert np.allclose(apply_similarity(A @ B, p), apply_similarity(A, apply_similarity(B, p)))
    # A pose moved by a similarity: points seen in the camera (scaled by s) land where the moved
    # world points are.
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=7).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    q_cam = rng.normal(size=(5, 3))
    q_world = q_cam @ T[:3, :3].T + T[:3, 3]
    T2 = transform_poses(A, T)
    assert np.allclose((a[0] * q_cam) @ T2[:3, :3].T + T2[:3, 3], apply_similarity(A, q_world))


def test_rotation_between_and_mean_rotation():
    rng = np.random.default_rng(8)
    for _ in range(5):
        a, b = rng.normal(size=3), rng.normal(size=3)
        R = rotation_between(a, b)
        assert np.allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b)) and np.isclose(np.linalg.det(R), 1)
    R = rotation_between(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    assert np.allclose(R @ [0, 0, 1.0], [0, 0, -1.0])
    R0 = Rotation.random(random_state=9).as_matrix()
    noisy = np.stack([Rotation.from_rotvec(rng.normal(size=3) * 0.01).as_matrix() @ R0 for _ in range(50)])
    assert np.allclose(mean_rotation(noisy), R0, atol=0.01)
