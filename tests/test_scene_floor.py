"""The Stage I gravity check: the floor's tilt in the mesh, against known tilts; and Stage I on every
app version's export of the studio room, with the floor horizontal (slow)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from embodmocap.geometry.planes import find_floor
from embodmocap.geometry.transforms import rot_x, rot_z
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.sfm import SfmConfig
from embodmocap.scene.stage import floor_figures
from embodmocap.synth.scene import build_scene

CFG = SceneConfig(voxel_m_indoor=0.02, sfm=SfmConfig(max_images=30))


def _tilted(vertices: np.ndarray, tilt_deg: float, yaw: float) -> np.ndarray:
    return vertices @ (rot_z(yaw) @ rot_x(np.deg2rad(tilt_deg))).T


@pytest.mark.parametrize("preset", ["indoor", "outdoor"])
@pytest.mark.parametrize("tilt", [0.0, 0.7, 2.5, 10.0, 25.0])
def test_floor_tilt_of_a_rotated_room(preset, tilt):
    built = build_scene(preset, np.random.default_rng([5, 1]))
    floor = find_floor(_tilted(built.vertices, tilt, 0.9), built.faces)
    assert floor is not None
    assert floor.tilt_deg == pytest.approx(tilt, abs=0.02)
    assert floor.area_m2 > 10.0  # the room's floor, not a table top


def test_floor_found_under_furniture_and_clutter():
    """Table tops are horizontal and higher; stray faces below the floor are few: the floor is the
    lowest plane holding a large share of the horizontal area."""
    built = build_scene("indoor", np.random.default_rng([6, 1]))
    v, f = _tilted(built.vertices, 1.2, -0.4), built.faces
    rng = np.random.default_rng(0)
    junk = rng.normal([0, 0, -0.6], 0.05, (30, 3))  # a few floaters below the floor
    v2 = np.concatenate([v, junk])
    f2 = np.concatenate([f, len(v) + np.arange(30).reshape(10, 3)])
    floor = find_floor(v2, f2)
    assert floor is not None and floor.tilt_deg == pytest.approx(1.2, abs=0.02)
    top = find_floor(v, f)
    assert floor.height_m == pytest.approx(top.height_m, abs=1e-9)


def test_no_floor_in_a_mesh_of_walls():
    # Two vertical squares: nothing horizontal.
    v = np.array([[0, 0, 0], [2, 0, 0], [2, 0, 2], [0, 0, 2], [0, 0, 0], [0, 2, 0], [0, 2, 2], [0, 0, 2]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    assert find_floor(v, f) is None
    figs = floor_figures(v, f, CFG)
    assert figs["floor_tilt_deg"] is None and figs["floor_tilt_ok"] is None


def test_floor_figures_flag_a_tilt_over_the_threshold():
    built = build_scene("indoor", np.random.default_rng([5, 1]))
    ok = floor_figures(_tilted(built.vertices, 1.5, 0.0), built.faces, CFG)
    bad = floor_figures(_tilted(built.vertices, 2.6, 0.0), built.faces, CFG)
    assert ok["floor_tilt_ok"] is True and ok["floor_tilt_deg"] == pytest.approx(1.5, abs=0.02)
    assert bad["floor_tilt_ok"] is False and bad["floor_tilt_deg"] == pytest.approx(2.6, abs=0.02)


# --------------------------------------------------------------------------- Stage I (slow)


def _session(tmp_path: Path, name: str, walk, big_video=None) -> Path:
    from capture_variants import write_variant

    from embodmocap.io.manifest import SceneEntry, SessionManifest, write_manifest

    root = tmp_path / name
    root.mkdir()
    cap = write_variant(name, root / "capture", walk, big_video=big_video)
    write_manifest(SessionManifest(root=root, scenes={"room": SceneEntry("room", cap, True)}), root / "session.toml")
    return root


def _walk(name: str, tilt_deg: float = 0.0):
    from capture_variants import VARIANTS, render_walk

    if name == "stray15":  # 60 fps, 1920x1440 video (upscaled render), a shorter walk
        return render_walk(160, 120, (64, 48), 4.0, 60.0, tilt_deg=tilt_deg)
    return render_walk(160, 120, (64, 48), 6.0, 30.0, portrait=VARIANTS[name][1], tilt_deg=tilt_deg)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["stray7", "stray9", "stray15", "r3d_new_zip", "r3d_new_dir", "r3d_old_zip",
                                  "r3d_old_dir", "r3d_exr", "spectacular", "spectacular_sdk"])
def test_stage1_floor_is_horizontal_for_every_variant(tmp_path, name, caplog):
    from embodmocap.check.inspect import inspect_path
    from embodmocap.scene import stage

    walk = _walk(name)
    root = _session(tmp_path, name, walk, big_video=(1920, 1440) if name == "stray15" else None)
    _, problems = inspect_path(root)
    assert problems == []
    with caplog.at_level(logging.WARNING, logger="embodmocap.scene.stage"):
        out = stage.run(CFG, root)
    figs = out.figures
    assert figs["floor_tilt_deg"] < 1.0 and figs["floor_tilt_ok"] is True
    assert figs["floor_z_m"] == pytest.approx(walk.floor_z_vio, abs=0.03)
    assert figs["floor_area_m2"] > 1.0
    assert not [r for r in caplog.records if "off horizontal" in r.getMessage() or "no dominant floor" in r.getMessage()]


@pytest.mark.slow
def test_stage1_warns_when_the_capture_gravity_is_tilted(tmp_path, caplog):
    """A capture whose world is tilted 3 deg (what an app's relative poses read without their
    initPose give) warns once per run, fresh or resumed, with the figure in the manifest."""
    import json

    from embodmocap.scene import stage

    root = _session(tmp_path, "stray9", _walk("stray9", tilt_deg=3.0))
    with caplog.at_level(logging.WARNING, logger="embodmocap.scene.stage"):
        out = stage.run(CFG, root)
    warned = [r for r in caplog.records if "deg off horizontal" in r.getMessage()]
    assert len(warned) == 1 and "3.0 deg" in warned[0].getMessage()
    assert out.figures["floor_tilt_deg"] == pytest.approx(3.0, abs=0.3) and out.figures["floor_tilt_ok"] is False
    manifest = json.loads(out.layout.manifest.read_text())
    assert manifest["figures"]["floor_tilt_deg"] == out.figures["floor_tilt_deg"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="embodmocap.scene.stage"):
        again = stage.run(CFG, root)
    assert "floor" in again.skipped
    assert len([r for r in caplog.records if "deg off horizontal" in r.getMessage()]) == 1
