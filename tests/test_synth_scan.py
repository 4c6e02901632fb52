"""The studio's empty-scene scan sees the floor where the performer walks (session 6).

A person scanning a room looks down at the floor as well as at the walls; the studio's scan used
to look only outwards from a loop round the walk area, so the floor inside the loop (where the
performer walks) was never seen and Stage I's mesh had none there. The default scan now turns its
view round relative to the walk once per lap (out at the walls, along the loop, in across the walk
area) while keeping the walls in view.
"""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.geometry.transforms import rotation_angle
from embodmocap.synth import trajectory as tr
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.scene import build_scene

FPS = 30.0
HALF_HFOV = np.radians(SynthConfig().hfov_deg / 2)


def _floor_seen(spec, T: np.ndarray) -> float:
    """Share of the walk area's floor inside some frame's depth frustum (4:3, 5 m)."""
    return tr.walk_area_floor_seen(spec, T, SynthConfig().hfov_deg)


def _top_row_pitch_deg(T: np.ndarray) -> np.ndarray:
    """(T,) elevation of the image's top edge (centre column), degrees (negative = below the horizon)."""
    down = np.degrees(np.arcsin(-T[:, :3, 2][:, 2]))  # optical axis below the horizon
    return np.degrees(np.arctan(0.75 * np.tan(HALF_HFOV))) - down


@pytest.mark.parametrize("room,seed", [("standard", 0), ("standard", 1), ("standard", 2), ("standard", 3),
                                       ("large", 4), ("low_texture", 5)])
def test_default_scan_sees_the_walk_area_floor_and_the_walls(room, seed):
    spec = build_scene("indoor", np.random.default_rng([seed, 1]), room).spec
    rng = lambda: np.random.default_rng([seed, 5])  # noqa: E731 (the studio's scan stream)
    T = tr.scene_walk(spec, 15.0, FPS, rng())
    old = tr.scene_walk(spec, 15.0, FPS, rng(), tr.SceneWalkConfig(turns_per_lap=0.0))
    # The floor where the performer walks: the outward-only scan saw 1-36 % of it.
    assert _floor_seen(spec, T) > 0.75
    assert _floor_seen(spec, old) < 0.4
    # Still a handheld scan: turn rate, never steeply down, level, every heading.
    dR = np.swapaxes(T[:-1, :3, :3], 1, 2) @ T[1:, :3, :3]
    assert np.percentile(np.degrees(rotation_angle(dR)) * FPS, 99) < 120
    assert np.all(np.degrees(np.arcsin(-T[:, :3, 2][:, 2])) < 45)
    assert np.all(np.abs(T[:, 2, 0]) < 0.05)
    z = T[:, :3, 2]
    assert len(np.unique(np.floor((np.arctan2(z[:, 1], z[:, 0]) + np.pi) / (np.pi / 4)))) == 8
    # The walls stay in view: the top of the frame is at most a few degrees below the horizon in
    # most frames (looking in across the loop, the far walls fill the upper part).
    assert np.mean(_top_row_pitch_deg(T) > -5.0) > 0.7


def test_turning_changes_the_view_not_the_path():
    """``turns_per_lap`` draws nothing: the same seed walks the same path (0 = the earlier
    outward-only scan, poses as before) and only the view directions differ."""
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    a = tr.scene_walk(spec, 10.0, FPS, np.random.default_rng(3), tr.SceneWalkConfig(turns_per_lap=0.0))
    b = tr.scene_walk(spec, 10.0, FPS, np.random.default_rng(3), tr.SceneWalkConfig(turns_per_lap=1.0))
    np.testing.assert_allclose(a[:, :3, 3], b[:, :3, 3], atol=1e-12)
    assert np.degrees(rotation_angle(np.swapaxes(a[:, :3, :3], 1, 2) @ b[:, :3, :3])).max() > 90
