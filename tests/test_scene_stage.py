"""Stage I end to end on a small synthetic session: ground truth, resume, bad input."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from embodmocap.errors import InputError
from embodmocap.evaluate.mesh_metrics import mesh_accuracy
from embodmocap.geometry.transforms import apply_T
from embodmocap.io.layout import SessionLayout
from embodmocap.io.stage_files import read_keyframes
from embodmocap.scene import stage
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.mesh import read_mesh_ply
from embodmocap.scene.sfm import SfmConfig, image_poses, sparse_points
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize

SYNTH = SynthConfig(seed=7, seconds=0.5, scene_seconds=6.0, width=320, height=240, depth_width=128, depth_height=96)
CFG = SceneConfig(voxel_m_indoor=0.02, sfm=SfmConfig(max_images=30))


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene") / "s"
    synthesize(SYNTH, out)
    return out


@pytest.fixture(scope="module")
def done(session) -> stage.SceneOutputs:
    return stage.run(CFG, session)


def _gt(session: Path):
    import trimesh

    lay = SessionLayout(session)
    gt = trimesh.load(lay.ground_truth.scene_mesh("scene0"), force="mesh")
    dev = np.load(lay.ground_truth.scene_device("scene0"))
    return np.asarray(gt.vertices), np.asarray(gt.faces), dev["T_scene_vio"]


def test_mesh_and_sparse_model_match_ground_truth(session, done):
    figs = done.figures
    for key in ("keyframes", "mesh_vertices", "mesh_faces", "mesh_area_m2", "sfm_points",
                "sfm_mean_track_length", "sfm_mean_reproj_error_px"):
        assert key in figs, key
    gt_v, gt_f, T_scene_vio = _gt(session)
    v, f, _ = read_mesh_ply(done.layout.mesh_raw)
    # The stage works in the capture's own VIO world; the true T_scene_vio maps it to the scene.
    acc = mesh_accuracy(apply_T(T_scene_vio, v), f, gt_v, gt_f, n_samples=20000, seed=0)
    assert acc < 0.02, f"mesh accuracy {acc:.4f} m"
    assert done.layout.mesh_simplified.is_file()
    assert figs["simplified_faces"] < figs["mesh_faces"]
    # The gravity check: the studio's VIO world is gravity-aligned, so its floor is horizontal.
    assert figs["floor_tilt_deg"] < 1.0 and figs["floor_tilt_ok"] is True
    xyz, _, _, err = sparse_points(done.layout.sfm_dir)
    assert len(xyz) > 500 and figs["sfm_mean_reproj_error_px"] < 1.5
    from embodmocap.evaluate.mesh_metrics import surface_distances

    d = surface_distances(apply_T(T_scene_vio, xyz), gt_v, gt_f)
    assert np.median(d) < 0.03


def _floor_down_share(v, f, T_scene_vio) -> tuple[float, float]:
    """(share of the floor's area facing down, floor area m^2): floor = faces within 3 cm of the true
    floor plane z = 0 and within 25 deg of horizontal, in the scene frame."""
    tri = apply_T(T_scene_vio, v)[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    a = np.linalg.norm(n, axis=1)
    nz = n[:, 2] / np.maximum(a, 1e-18)
    floor = (np.abs(tri[..., 2]).max(axis=1) < 0.03) & (np.abs(nz) > 0.9)
    return float(a[floor & (nz < 0)].sum() / max(a[floor].sum(), 1e-18)), float(a[floor].sum() / 2)


def test_the_simplified_floor_faces_up_and_stays_on_the_surface(session, done):
    # Faces of the scanned floor that point down read as solid above the floor to anything that
    # tests a side by the closest face (sim check); the clustering once left 4-7 % of a studio
    # floor that way, keeping both windings where sheets collapsed.
    gt_v, gt_f, T_scene_vio = _gt(session)
    v, f, _ = read_mesh_ply(done.layout.mesh_simplified)
    down, area = _floor_down_share(v, f, T_scene_vio)
    assert area > 1.0, f"only {area:.2f} m^2 of floor in the simplified mesh"
    assert down < 0.005, f"{100 * down:.2f} % of the simplified floor faces down"  # 0.8 % before the vote
    key = np.sort(f, axis=1)
    assert len(np.unique(key, axis=0)) == len(f)  # one face per triangle, never both windings
    acc = mesh_accuracy(apply_T(T_scene_vio, v), f, gt_v, gt_f, n_samples=20000, seed=0)
    assert acc < 0.03, f"simplified mesh accuracy {acc:.4f} m"


def test_sparse_model_key_frames_are_the_capture_poses_or_their_drift_correction(session, done):
    """The model's key frames are the capture's poses, or (drift correction accepted) those poses
    moved by at most ``max_pose_change_m`` and no farther from the truth; the mesh's frames get the
    same correction (what ``corrected_poses`` gives at a key frame's time is the model's pose)."""
    from embodmocap.geometry.transforms import invert_T
    from embodmocap.scene.adjust import corrected_poses

    kf = read_keyframes(done.layout.keyframes)
    poses = image_poses(done.layout.sfm_dir)
    summary = json.loads((done.layout.sfm_dir / "summary.json").read_text())
    drift = summary.get("drift_correction")
    assert drift is not None  # on by default, and Stage I passes the key frames' times
    by_frame = {int(f): T for f, T in zip(kf["frame_ids"], kf["T_world_cam"])}
    names = summary["image_names"]
    frames = [int(Path(n).stem.split("_")[1]) for n in names]
    T_model = np.stack([poses[n] for n in names])
    T_capture = np.stack([by_frame[f] for f in frames])
    assert len(poses) >= 10
    if not drift["accepted"]:
        np.testing.assert_allclose(T_model, T_capture, atol=1e-9)
        return
    moved = np.linalg.norm(T_model[:, :3, 3] - T_capture[:, :3, 3], axis=1)
    assert moved.max() <= CFG.sfm.max_pose_change_m
    dev = np.load(SessionLayout(session).ground_truth.scene_device("scene0"))
    T_true = invert_T(dev["T_scene_vio"]) @ dev["T_scene_cam"][frames]
    err = lambda T: np.median(np.linalg.norm(T[:, :3, 3] - T_true[:, :3, 3], axis=1))  # noqa: E731
    assert err(T_model) <= err(T_capture) + 1e-3
    np.testing.assert_allclose(corrected_poses(done.layout.sfm_dir, np.asarray(drift["times_s"]), T_capture),
                               T_model, atol=1e-6)


def test_second_run_skips_everything(session, done):
    again = stage.run(CFG, session)
    assert set(again.skipped) == {"keyframes", "mesh", "floor", "simplify", "sfm"}


def test_interrupted_run_resumes_and_config_changes_redo_only_what_depends(session, tmp_path, monkeypatch):
    work = tmp_path / "s"
    shutil.copytree(session, work)
    shutil.rmtree(work / "scenes", ignore_errors=True)

    def crash(*a, **k):
        raise KeyboardInterrupt("simulated crash before the sparse model")

    monkeypatch.setattr(stage, "build_sparse_model", crash)
    with pytest.raises(KeyboardInterrupt):
        stage.run(CFG, work)
    lay = SessionLayout(work).scene("scene0")
    done_steps = json.loads(lay.manifest.read_text())["steps"]
    # The sparse model comes before the mesh (the mesh is fused with its drift correction).
    assert set(done_steps) == {"keyframes"}
    kf_mtime = lay.keyframes.stat().st_mtime_ns
    monkeypatch.undo()

    resumed = stage.run(CFG, work)
    assert set(resumed.skipped) == {"keyframes"}
    assert lay.keyframes.stat().st_mtime_ns == kf_mtime
    assert (lay.sfm_dir / "database.db").is_file() and lay.mesh_raw.is_file()

    # Changing a mesh-only option redoes the mesh and what depends on it, not the key frames or SfM.
    changed = stage.run(replace(CFG, floater_max_extent_m=0.2), work)
    assert set(changed.skipped) == {"keyframes", "sfm"}


def test_no_valid_depth_is_one_clear_error(session, tmp_path):
    work = tmp_path / "s"
    shutil.copytree(session, work, ignore=shutil.ignore_patterns("scenes"))
    for png in (work / "captures" / "scene0" / "depth").glob("*.png"):
        Image.fromarray(np.zeros((SYNTH.depth_height, SYNTH.depth_width), np.uint16)).save(png)
    with pytest.raises(InputError) as err:
        stage.run(CFG, work)
    msg = str(err.value)
    assert "no valid depth" in msg and "scene0" in msg and len(msg.splitlines()) == 1


def test_too_few_keyframes_is_one_clear_error(session, tmp_path):
    work = tmp_path / "s"
    shutil.copytree(session, work, ignore=shutil.ignore_patterns("scenes"))
    # Freeze the camera: every pose row equal to the first, so motion never makes a key frame.
    odo = work / "captures" / "scene0" / "odometry.csv"
    lines = odo.read_text().splitlines()
    first = lines[1].split(",")
    frozen = [lines[0]] + [",".join(line.split(",")[:2] + first[2:]) for line in lines[1:]]
    odo.write_text("\n".join(frozen) + "\n")
    with pytest.raises(InputError) as err:
        stage.run(CFG, work)
    assert "key frame" in str(err.value) and "scene0" in str(err.value)


def test_unknown_scene_name(session):
    with pytest.raises(InputError, match="no scene named"):
        stage.run(CFG, session, "kitchen")


class _MemoryFrames:
    """A capture's frames held in memory (a :class:`embodmocap.types.FrameSource`)."""

    def __init__(self, frames) -> None:
        n = len(frames)
        self.rgb_, self.depth_, self.conf_ = ([getattr(frames, k)(i) for i in range(n)]
                                              for k in ("rgb", "depth_m", "confidence"))

    def __len__(self) -> int:
        return len(self.rgb_)

    def rgb(self, index: int):
        return self.rgb_[index]

    def depth_m(self, index: int):
        return self.depth_[index]

    def confidence(self, index: int):
        return self.conf_[index]


def test_solve_in_memory_gives_the_run_s_files(session, done, tmp_path):
    """Stage I's pure solve, on the scene capture read into memory from a copy of the session that
    is then deleted (so it can open no file), gives the run's key frames and the same mesh files."""
    from embodmocap.io.atomic import _json_default
    from embodmocap.io.captures import open_capture
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.mesh_file import write_mesh_ply
    from embodmocap.scene import solve
    from embodmocap.scene.adjust import read_drift_correction

    work = tmp_path / "s"
    shutil.copytree(session, work)
    entry = load_manifest(SessionLayout(work).manifest).scene(None)
    cap = open_capture(entry.capture)
    capture = replace(cap, frames=_MemoryFrames(cap.frames))
    # The sparse model's drift correction (COLMAP builds the model in files: the run's is read).
    drift = read_drift_correction(SessionLayout(work).scene(entry.name).sfm_dir) if CFG.sfm.refine_poses else None
    shutil.rmtree(work)  # nothing of the session is left to read
    res = solve.solve(capture, CFG, entry.indoor, "scene0", drift=drift)

    lay = SessionLayout(session).scene("scene0")
    want = json.loads(lay.keyframes.read_text())
    got = json.loads(json.dumps(res.keyframes.record, default=_json_default))
    assert got == {k: x for k, x in want.items() if k != "capture"}
    write_mesh_ply(tmp_path / "raw.ply", res.mesh.vertices, res.mesh.faces, res.mesh.colors)
    assert (tmp_path / "raw.ply").read_bytes() == lay.mesh_raw.read_bytes()
    simple = solve.simplified(*read_mesh_ply(tmp_path / "raw.ply"), CFG)  # the stage simplifies the stored mesh
    write_mesh_ply(tmp_path / "simple.ply", simple.vertices, simple.faces, simple.colors)
    assert (tmp_path / "simple.ply").read_bytes() == lay.mesh_simplified.read_bytes()
