"""Mesh metrics on hand-computed cases."""

from __future__ import annotations



import numpy as np
import pytest

from embodmocap.evaluate.mesh_metrics import (
    mesh_accuracy, mesh_completeness, sample_surface, scene_mesh_metrics, surface_distances, visible_surface_samples,
)
from embodmocap.geometry.transforms import make_T
from embodmocap.types import Intrinsics


def square(x0, x1, y0, y1, z):
    """Two triangles covering [x0, x1] x [y0, y1] at height z."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_sampling_is_uniform_and_on_the_surface():
    v, f = square(0, 2, 0, 1, 0.0)
    p = sample_surface(v, f, 40_000, seed=1)
    assert p[:, 0].min() >= 0 and p[:, 0].max() <= 2 and np.all(p[:, 2] == 0)
    assert p.mean(0) == pytest.approx([1.0, 0.5, 0.0], abs=0.01)
    assert np.mean(p[:, 0] < 1) == pytest.approx(0.5, abs=0.01)  # by area, not by face
    np.testing.assert_array_equal(sample_surface(v, f, 10, seed=1), sample_surface(v, f, 10, seed=1))


def test_accuracy_of_a_shifted_copy_is_the_shift():
    gt = square(0, 1, 0, 1, 0.0)
    pred = square(0, 1, 0, 1, 0.03)
    assert mesh_accuracy(*pred, *gt, n_samples=5000) == pytest.approx(0.03, abs=1e-6)
    assert mesh_accuracy(*gt, *gt, n_samples=5000) == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(surface_distances([[0.5, 0.5, 2.0], [2.0, 0.5, 0.0]], *gt), [2.0, 1.0], atol=1e-6)


def test_completeness_of_a_half_covered_plane():
    gt_v, gt_f = square(0, 2, 0, 1, 0.0)
    pred = square(0, 1, 0, 1, 0.0)
    pts = sample_surface(gt_v, gt_f, 40_000, seed=2)
    # Points with x <= 1 + threshold are within reach of the left half.
    assert mesh_completeness(*pred, pts, threshold=0.01) == pytest.approx(0.505, abs=0.01)
    assert mesh_completeness(*pred, pts, threshold=1.5) == 1.0


def test_visibility_handles_occlusion_and_depth_truncation():
    """A 2x2 floor at z = 0 under a 0.5x0.5 plate at z = 1, camera 2 m up looking down: the plate
    hides a 1x1 patch of the floor (its shadow from the camera doubles in size)."""
    floor_v, floor_f = square(-1, 1, -1, 1, 0.0)
    plate_v, plate_f = square(-0.25, 0.25, -0.25, 0.25, 1.0)
    v = np.concatenate([floor_v, plate_v])
    f = np.concatenate([floor_f, plate_f + 4])
    K = Intrinsics(100.0, 100.0, 199.5, 199.5, 400, 400)  # +-63 degrees: sees the whole floor
    down = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float)
    T = make_T(down, [0.0, 0.0, 2.0])[None]
    n = 60_000
    seen = visible_surface_samples(v, f, T, K, depth_trunc=3.0, n=n, seed=3)
    assert len(seen) / n == pytest.approx((0.25 + 3.0) / 4.25, abs=0.01)
    under = (np.abs(seen[:, 0]) < 0.5) & (np.abs(seen[:, 1]) < 0.5) & (seen[:, 2] == 0)
    assert not under.any()
    near = visible_surface_samples(v, f, T, K, depth_trunc=1.5, n=n, seed=3)
    assert len(near) / n == pytest.approx(0.25 / 4.25, abs=0.005) and np.all(near[:, 2] == 1.0)


def test_scene_mesh_metrics_report():
    gt = square(-1, 1, -1, 1, 0.0)
    pred = square(-1, 0, -1, 1, 0.01)  # half the floor, 1 cm high
    K = Intrinsics(100.0, 100.0, 199.5, 199.5, 400, 400)
    T = make_T(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 2.0])[None]
    m = scene_mesh_metrics(*pred, *gt, T, K, depth_trunc=3.0, n_samples=20_000)
    assert m["accuracy_m"] == pytest.approx(0.01, abs=1e-5)
    assert m["completeness"] == pytest.approx(0.5, abs=0.02)
    assert m["seen_samples"] == 20_000
