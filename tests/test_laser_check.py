"""The same-dot check of the two views' laser events (Stage III): geometry against known wall points,
and what the sync choice does with a failed check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.sequence.geosync import GeoSyncConfig
from embodmocap.sequence.laser_check import check_same_dot, dot_sighting, laser_dot_check, ray_gap
from embodmocap.sequence.sync_record import decide
from embodmocap.types import CameraTrajectory, Capture, Intrinsics

W, H, DW, DH = 640, 480, 256, 192


class _DepthFrames:
    """In-memory frames whose depth is one fronto-parallel wall at ``z`` metres (0: no depth)."""

    def __init__(self, n: int, z: float) -> None:
        self.n, self.z = n, z

    def __len__(self) -> int:
        return self.n

    def rgb(self, index: int) -> np.ndarray:
        return np.zeros((H, W, 3), np.uint8)

    def depth_m(self, index: int) -> np.ndarray:
        return np.full((DH, DW), self.z, np.float32)

    def confidence(self, index: int):
        return None


def _yaw(deg: float, t) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def _facing_wall(centre, yaw_deg: float) -> np.ndarray:
    """T_world_cam of an OpenCV camera at ``centre`` looking horizontally along world yaw ``yaw_deg``
    (x right, y down, z forward)."""
    fwd = np.array([np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg)), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, fwd)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], axis=1)
    T[:3, 3] = centre
    return T


def _view(T_world_cam: np.ndarray, T_world_vio: np.ndarray, dot_world, depth: bool = True, frame: int = 30):
    """A capture whose VIO pose at ``frame`` puts the camera at ``T_world_cam`` once taken to the world
    by ``T_world_vio``, and the pixel of ``dot_world`` in it. With ``depth``, every depth map is the
    dot's depth (a fronto-parallel wall); without, no valid depth."""
    K = Intrinsics(500.0, 500.0, (W - 1) / 2, (H - 1) / 2, W, H)
    p_cam = np.linalg.inv(T_world_cam) @ np.append(dot_world, 1.0)
    xy = (K.fx * p_cam[0] / p_cam[2] + K.cx, K.fy * p_cam[1] / p_cam[2] + K.cy)
    T_vio_cam = np.linalg.inv(T_world_vio) @ T_world_cam
    n = frame + 10
    traj = CameraTrajectory(np.arange(n) / 30.0, np.arange(n), np.tile(T_vio_cam, (n, 1, 1)))
    cap = Capture(Path("mem/view"), "strayscanner", n, 30.0, K, K.scaled(DW, DH), traj,
                  _DepthFrames(n, float(p_cam[2]) if depth else 0.0))
    return cap, xy


# Both cameras face the wall x = 3 (fronto-parallel, so a constant depth map is exact).
DOT = np.array([3.0, 0.4, 1.3])
T1 = _facing_wall([0.2, -0.5, 1.4], 0.0)
T2 = _facing_wall([0.6, 1.1, 1.2], 0.0)
V1 = _yaw(35.0, [1.0, -2.0, 0.0])  # each view's own VIO world, unrelated to the scene's
V2 = _yaw(-120.0, [-0.5, 0.7, 0.1])


def test_a_sighting_with_depth_lands_on_the_dot_in_the_world():
    cap, xy = _view(T1, V1, DOT)
    s = dot_sighting(cap, 30, xy, V1)
    assert s is not None and s.point is not None
    assert np.linalg.norm(s.point - DOT) < 1e-6
    assert np.allclose(s.origin, T1[:3, 3]) and np.linalg.norm(s.direction @ (DOT - s.origin)) > 0


def test_one_dot_seen_by_both_views_passes_and_two_spots_fail():
    cap1, xy1 = _view(T1, V1, DOT)
    cap2, xy2 = _view(T2, V2, DOT)
    a, b = dot_sighting(cap1, 30, xy1, V1), dot_sighting(cap2, 30, xy2, V2)
    same = check_same_dot(a, b, 0.15)
    assert same.method == "depth" and same.gap_m < 1e-6 and same.same_dot is True
    # View 2 took a speck 40 cm along the wall for the dot.
    other = DOT + np.array([0.0, 0.4, 0.0])
    cap2b, xy2b = _view(T2, V2, other)
    diff = check_same_dot(a, dot_sighting(cap2b, 30, xy2b, V2), 0.15)
    assert diff.same_dot is False and diff.gap_m == pytest.approx(0.4, abs=1e-6)


def test_without_depth_rays_can_only_show_a_disagreement():
    cap1, xy1 = _view(T1, V1, DOT, depth=False)
    cap2, xy2 = _view(T2, V2, DOT, depth=False)
    a, b = dot_sighting(cap1, 30, xy1, V1), dot_sighting(cap2, 30, xy2, V2)
    assert a.point is None and b.point is None
    meet = check_same_dot(a, b, 0.15)
    assert meet.method == "rays" and meet.gap_m < 1e-6 and meet.same_dot is None  # unconfirmed, not rejected
    # A speck high on the wall: view 2's ray passes 0.5 m above view 1's.
    cap, xy = _view(T2, V2, DOT + np.array([0.0, 0.0, 0.5]), depth=False)
    miss = check_same_dot(a, dot_sighting(cap, 30, xy, V2), 0.15)
    assert miss.same_dot is False and miss.gap_m > 0.3


def test_ray_gap_of_skew_and_parallel_rays():
    assert ray_gap(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), np.array([0, 1.0, 0])) == pytest.approx(1.0)
    assert ray_gap(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 2.0, 0]), np.array([1.0, 0, 0])) == pytest.approx(2.0)
    # Rays pointing away from each other meet only behind their origins: not on the rays.
    assert ray_gap(np.zeros(3), np.array([-1.0, 0, 0]), np.array([1.0, 0, 0]), np.array([1.0, 0, 0])) == pytest.approx(1.0)


def _record(dots: dict, slicing_offset_s: float = 1.0) -> dict:
    lv = {v: {"found": True, "frame": 31, "confidence": 0.8, "dot_xy_before": list(xy)} for v, xy in dots.items()}
    return {"version": 2, "views": {v: {"frame": 31, "confidence": 0.8} for v in dots},
            "slicing": {"source": "laser", "offset_s": slicing_offset_s},
            "sources": {"laser": {"views": lv, "offset_s": slicing_offset_s}}, "agreement": None,
            "chosen": {"source": "laser", "offset_s": slicing_offset_s, "residual_s": 0.0, "residual_frames": 0.0,
                       "final": False}, "warnings": []}


def test_the_choice_drops_a_laser_offset_whose_dots_are_different_places():
    from tests.test_geosync import FPS, _geo

    cap1, xy1 = _view(T1, V1, DOT)
    cap2, xy2 = _view(T2, V2, DOT + np.array([0.0, 0.6, 0.0]))
    rec = _record({"v1": xy1, "v2": xy2})
    check = laser_dot_check(rec, {"v1": lambda: cap1, "v2": lambda: cap2}, {"v1": V1, "v2": V2}, 0.15)
    assert check.same_dot is False and check.gap_m == pytest.approx(0.6, abs=1e-6)
    # The geometric sync is confident: it is chosen although the laser is more confident (0.8 > 0.5).
    out = decide(rec, _geo(3.0, confidence=0.5), GeoSyncConfig(), FPS, {"v1": "/x/sync_v1.png"}, "s", check)
    assert out["chosen"]["source"] == "geometric" and "different spots" in out["chosen"]["reason"]
    assert out["laser_dot_check"]["same_dot"] is False and out["sources"]["laser"]["offset_s"] == 1.0
    assert any("0.60 m apart" in w and "/x/sync_v1.png" in w for w in out["warnings"])
    # Without it the same record chose the laser, and with no confident geometric sync it is an error.
    assert decide(rec, _geo(3.0, confidence=0.5), GeoSyncConfig(), FPS, {}, "s")["chosen"]["source"] == "laser"
    with pytest.raises(InputError, match="0.60 m apart"):
        decide(rec, _geo(0.3, confidence=0.1), GeoSyncConfig(), FPS, {}, "s", check)
    # One dot: the check is recorded and the choice is what it was.
    cap2s, xy2s = _view(T2, V2, DOT)
    rec = _record({"v1": xy1, "v2": xy2s})
    ok = laser_dot_check(rec, {"v1": lambda: cap1, "v2": lambda: cap2s}, {"v1": V1, "v2": V2}, 0.15)
    out = decide(rec, _geo(0.3, confidence=0.1), GeoSyncConfig(), FPS, {}, "s", ok)
    assert out["chosen"]["source"] == "laser" and out["laser_dot_check"]["same_dot"] is True
