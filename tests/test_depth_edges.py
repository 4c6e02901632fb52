"""Depth edges from the depth alone (geometry.depth_edges), the stand-in for a missing LiDAR
confidence map: known spreads on a step, and on the studio's LiDAR model the pixels it drops are
those its confidence map marks low."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.geometry.depth_edges import drop_depth_edges, relative_spread3
from embodmocap.sequence.config import SequenceConfig
from embodmocap.errors import InputError


def test_spread_of_a_step_is_the_jump_over_the_depth():
    d = np.full((6, 8), 2.0, np.float32)
    d[:, 4:] = 3.0  # a 1 m step between columns 3 and 4
    s = relative_spread3(d)
    np.testing.assert_allclose(s[:, :3], 0.0)
    np.testing.assert_allclose(s[:, 5:], 0.0)
    np.testing.assert_allclose(s[:, 3], 1.0 / 2.0)
    np.testing.assert_allclose(s[:, 4], 1.0 / 3.0)


def test_holes_are_left_out_not_edges():
    d = np.full((5, 5), 2.0, np.float32)
    d[2, 2] = 0.0
    d[0, 0] = np.nan
    s = relative_spread3(d)
    assert np.isinf(s[2, 2]) and np.isinf(s[0, 0])
    np.testing.assert_allclose(s[np.isfinite(s)], 0.0)
    out = drop_depth_edges(d, 0.1)
    assert out[2, 2] == 0 and out[0, 0] == 0 and (out[1:4, 1:4] > 0).sum() == 8
    assert np.isfinite(drop_depth_edges(d, 0.0)).all()  # off: only the non-finite value goes
    assert np.isnan(d[0, 0])  # the input is not modified


def _scene_depth(h: int = 192, w: int = 256) -> np.ndarray:
    """A wall, a floor sloping toward the camera, a box and a person-like slab: depth edges
    and a grazing floor, all within the sensor's range."""
    yy = np.mgrid[0:h, 0:w][0].astype(np.float32)
    d = np.full((h, w), 3.0, np.float32)
    d[h // 2:] = 3.0 - (yy[h // 2:] - h // 2) / (h / 2) * 1.6
    d[40:140, 60:120] = 1.5
    d[30:170, 170:200] = 1.1
    return d


@pytest.mark.parametrize("seed", [0, 1])
def test_on_the_studio_lidar_the_edges_are_what_its_confidence_marks_low(seed):
    from embodmocap.synth.lidar import simulate_lidar

    truth = _scene_depth()
    depth_mm, conf = simulate_lidar(truth, np.random.default_rng(seed))
    d = depth_mm.astype(np.float32) / 1000.0
    kept = drop_depth_edges(d, SequenceConfig().no_confidence_edge_spread) > 0
    confident = (d > 0) & (conf >= 1)
    assert (kept == confident).mean() > 0.98
    edges = (d > 0) & (conf == 0)  # the studio marks depth jumps and grazing angles low
    assert edges.sum() > 500 and (~kept[edges]).mean() > 0.6  # most of them dropped
    assert kept[confident].mean() > 0.98  # little good depth lost
    # what is kept is as accurate as what the confidence keeps
    err_kept = np.abs(d[kept] - truth[kept]).mean()
    err_conf = np.abs(d[confident] - truth[confident]).mean()
    assert err_kept < 1.02 * err_conf


def test_the_setting_is_checked():
    with pytest.raises(InputError, match="no_confidence_edge_spread"):
        SequenceConfig(no_confidence_edge_spread=-0.1)
