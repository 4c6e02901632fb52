"""`embodmocap export SESSION --to training`: per-frame training data checked against the session's
own files and the studio's ground truth (the tiny session's fit is the true body, its cameras the
true cameras), the camera-space SMPL round trip, the validity flags, sub-frame resampling of view 2,
resume and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.errors import InputError
from embodmocap.export.training import TRAINING_FORMAT, export_training, params_in_camera, resample_motion
from embodmocap.geometry.transforms import invert_T
from embodmocap.io.atomic import write_json
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.smpl_file import read_smpl_npz, write_smpl_npz
from embodmocap.io.stage_files import read_world_joints
from stage4_session import SYNTH
from training_session import training_export  # noqa: F401  (fixture)


def _labels(out: Path, view: str, seq: str = "seq0") -> dict:
    with np.load(out / seq / view / "labels.npz") as z:
        return {k: z[k] for k in z.files}


def _model(session: Path):
    return load_body_model(load_manifest(SessionLayout(session).manifest).body_model)


def _pose(model, lab: dict) -> tuple[np.ndarray, np.ndarray]:
    """Joints and COCO-17 of the camera-space parameters through the body model, float64."""
    with torch.no_grad():
        out = model.forward(lab["betas"], lab["global_orient"], lab["body_pose"], lab["transl"], dtype=torch.float64)
    return out.joints.numpy(), out.coco17.numpy()


def _move(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(T, 4, 4) transforms applied to (T, J, 3) points."""
    return np.einsum("tij,tkj->tki", T[:, :3, :3], p) + T[:, None, :3, 3]


def _gt(session: Path) -> dict:
    lay = SessionLayout(session)
    with np.load(lay.ground_truth.sequence(SYNTH.sequence_name)) as z:
        return {k: z[k] for k in z.files}


def _copy(training_export, tmp_path: Path) -> Path:
    dst = tmp_path / "session"
    shutil.copytree(training_export["session"], dst, symlinks=True)
    return dst


# ------------------------------------------------------------------------------------------------
# Layout and manifest


def test_layout_and_manifest(training_export):
    out = training_export["out"]
    index = json.loads((out / "manifest.json").read_text())
    assert index["format"] == TRAINING_FORMAT
    assert [(v["sequence"], v["view"]) for v in index["views"]] == [("seq0", "v1"), ("seq0", "v2")]
    T = training_export["info"]["T"]
    for v in index["views"]:
        d = out / v["path"]
        assert v["frames"] == T and (v["width"], v["height"]) == (SYNTH.width, SYNTH.height)
        assert (v["depth_width"], v["depth_height"]) == (SYNTH.depth_width, SYNTH.depth_height)
        assert sorted(p.name for p in (d / "rgb").iterdir()) == [f"{t:06d}.jpg" for t in range(T)]
        assert np.load(d / "depth.npy", mmap_mode="r").shape == (T, SYNTH.depth_height, SYNTH.depth_width)
        assert np.load(d / "masks.npy", mmap_mode="r").shape == (T, SYNTH.height, (SYNTH.width + 7) // 8)
    assert index["frames"] == 2 * T and index["valid_frames"] == 2 * T
    # No absolute path and no clock in the index: a rerun or a moved session writes the same bytes.
    text = (out / "manifest.json").read_text()
    assert str(training_export["session"]) not in text


# ------------------------------------------------------------------------------------------------
# Camera-space SMPL


def test_params_in_camera_rotates_about_the_pelvis(training_export):
    """Random bodies and cameras: the camera-space parameters through the body model give the world
    body moved by T_cam_world; moving transl as if SMPL rotated about the origin does not."""
    model = _model(training_export["session"])
    rng = np.random.default_rng(3)
    T = 6
    betas = rng.normal(0, 1, 10)
    go = Rotation.random(T, random_state=4).as_rotvec()
    go.setflags(write=False)  # as SmplParams hold them
    pose = rng.normal(0, 0.3, (T, 69))
    transl = rng.normal(0, 2, (T, 3))
    T_cw = np.tile(np.eye(4), (T, 1, 1))
    T_cw[:, :3, :3] = Rotation.random(T, random_state=5).as_matrix()
    T_cw[:, :3, 3] = rng.normal(0, 3, (T, 3))
    go_c, tr_c = params_in_camera(go, transl, betas, T_cw, model)
    with torch.no_grad():
        world = model.forward(betas, go, pose, transl, dtype=torch.float64).joints.numpy()
        cam = model.forward(betas, go_c, pose, tr_c, dtype=torch.float64).joints.numpy()
        naive = model.forward(betas, go_c, pose, np.einsum("tij,tj->ti", T_cw[:, :3, :3], transl) + T_cw[:, :3, 3],
                              dtype=torch.float64).joints.numpy()
    assert np.abs(cam - _move(T_cw, world)).max() < 1e-7  # rounding of the axis-angle conversions
    assert np.linalg.norm(naive - _move(T_cw, world), axis=-1).max() > 0.01


def test_camera_space_smpl_round_trip_against_world_fit_and_truth(training_export):
    """Through the body model, each view's camera-space SMPL gives the world fit's joints
    (joints_world.npz) moved by T_cam_world within 1e-5 m, and the studio's true joints seen from
    its true camera; its projected COCO-17 are the studio's true 2D keypoints."""
    session, out, info = training_export["session"], training_export["out"], training_export["info"]
    model = _model(session)
    sl = SessionLayout(session).sequence(SYNTH.sequence_name)
    world = np.asarray(read_world_joints(sl.joints_world).joints)
    gt = _gt(session)
    m = np.arange(info["motion"], info["motion"] + info["T"])
    for v in VIEWS:
        lab = _labels(out, v)
        joints, coco = _pose(model, lab)
        T_cw = invert_T(lab["T_world_cam"])
        assert np.abs(joints - _move(T_cw, world)).max() < 1e-5
        assert np.abs(joints - lab["joints_cam"]).max() < 1e-9
        # The truth: the studio's joints in its scene frame, seen from its true camera.
        raw = m - info["start"][v]
        assert np.array_equal(lab["raw_frames"], raw)
        T_cam_scene = invert_T(gt[f"{v}_T_scene_cam"][raw])
        assert np.abs(joints - _move(T_cam_scene, gt["joints_smpl24"][m])).max() < 1e-5
        vis = gt[f"{v}_visibility"][raw] > 0
        err = np.linalg.norm(lab["keypoints_fit"] - gt[f"{v}_keypoints2d_gt"][raw][..., :2], axis=-1)
        assert err[vis].max() < 1e-3
        # Body pose and shape are the world fit's, untouched.
        params, _ = read_smpl_npz(sl.smpl_world)
        assert np.array_equal(lab["body_pose"], params.body_pose) and np.array_equal(lab["betas"], params.betas)


# ------------------------------------------------------------------------------------------------
# Cameras, depth, RGB, masks, keypoints against the session's files and the truth


def test_cameras_and_intrinsics_are_the_truth(training_export):
    session, out, info = training_export["session"], training_export["out"], training_export["info"]
    gt = _gt(session)
    m = np.arange(info["motion"], info["motion"] + info["T"])
    for v in VIEWS:
        lab = _labels(out, v)
        assert np.allclose(lab["K"], SYNTH.intrinsics().K)
        assert np.allclose(lab["K_depth"], SYNTH.depth_intrinsics().K)
        T_true = info["T_world_scene"] @ gt[f"{v}_T_scene_cam"][m - info["start"][v]]
        assert np.abs(lab["T_world_cam"] - T_true).max() < 1e-9


def test_depth_is_metric_on_the_true_scene(training_export):
    """The exported depth is Stage II's, byte for byte; unprojected with K_depth and T_world_cam,
    the pixels off the person land on the studio's true scene mesh (moved into Stage I's world)
    within the simulated LiDAR's noise (0.5 cm + 1 % of the depth), where a 10 % focal error does not."""
    import trimesh

    from embodmocap.io.mesh_file import read_mesh_ply

    session, out, info = training_export["session"], training_export["out"], training_export["info"]
    lay = SessionLayout(session)
    v_mesh, f_mesh, _ = read_mesh_ply(lay.ground_truth.scene_mesh(SYNTH.scene_name))
    Tws = info["T_world_scene"]
    mesh = trimesh.Trimesh(np.asarray(v_mesh) @ Tws[:3, :3].T + Tws[:3, 3], f_mesh, process=False)
    for v in VIEWS:
        lab = _labels(out, v)
        depth = np.load(out / "seq0" / v / "depth.npy")
        assert np.array_equal(depth, np.load(lay.sequence("seq0").view(v).depth))
        masks = np.load(out / "seq0" / v / "masks.npy")
        h, w = depth.shape[1:]
        u, r = np.meshgrid(np.arange(w), np.arange(h))

        def relative_error(K: np.ndarray) -> tuple[float, float]:
            pts, zs = [], []
            for t in range(0, len(depth), 4):
                person = np.unpackbits(masks[t], axis=-1, count=SYNTH.width).astype(np.uint8)
                person = cv2.dilate(person, np.ones((9, 9), np.uint8))
                person = cv2.resize(person, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
                z = depth[t].astype(np.float64) / 1000.0
                keep = (z > 0) & ~person
                ray = np.linalg.solve(K, np.stack([u[keep], r[keep], np.ones(keep.sum())]))
                T = lab["T_world_cam"][t]
                pts.append((ray * z[keep]).T @ T[:3, :3].T + T[:3, 3])
                zs.append(z[keep])
            pts, zs = np.concatenate(pts), np.concatenate(zs)
            pick = slice(None, None, max(1, len(pts) // 1500))
            _, dist, _ = trimesh.proximity.closest_point(mesh, pts[pick])
            rel = dist / zs[pick]
            return float(np.median(rel)), float(np.percentile(rel, 90))

        med, p90 = relative_error(lab["K_depth"])
        assert med < 0.012 and p90 < 0.03, (med, p90)
        wrong = lab["K_depth"].copy()
        wrong[:2, :2] *= 1.1
        assert relative_error(wrong)[0] > 2 * med


def test_rgb_masks_and_keypoints_round_trip(training_export):
    from embodmocap.io.captures import open_capture
    from embodmocap.io.stage_files import read_keypoints2d

    session, out = training_export["session"], training_export["out"]
    lay = SessionLayout(session)
    entry = load_manifest(lay.manifest).sequence("seq0")
    for v in VIEWS:
        lab = _labels(out, v)
        vl = lay.sequence("seq0").view(v)
        cap = open_capture(entry.views[v].capture)
        for t in (0, len(lab["frames"]) // 2, len(lab["frames"]) - 1):
            jpg = cv2.cvtColor(cv2.imread(str(out / "seq0" / v / "rgb" / f"{t:06d}.jpg")), cv2.COLOR_BGR2RGB)
            src = np.asarray(cap.frames.rgb(int(lab["raw_frames"][t])))
            assert np.abs(jpg.astype(int) - src.astype(int)).mean() < 2.5  # JPEG quality 95
        assert np.array_equal(np.load(out / "seq0" / v / "masks.npy"), np.load(vl.masks))
        kp = read_keypoints2d(vl.keypoints)
        assert np.array_equal(lab["keypoints"], kp.keypoints) and np.array_equal(lab["seen"], kp.seen)


# ------------------------------------------------------------------------------------------------
# Validity flags and view 2's own instants


def test_validity_flags_follow_stage4_sync_and_depth(training_export, tmp_path):
    session = _copy(training_export, tmp_path)
    lay = SessionLayout(session)
    sl = lay.sequence("seq0")
    params, frames = read_smpl_npz(sl.smpl_world)
    valid = np.ones(len(frames), bool)
    valid[3] = False
    suspect = np.zeros(len(frames), bool)
    suspect[4] = True  # the fit's suspect flag travels as smpl_suspect, apart from valid
    T0 = len(frames)
    quality = {"suspect": suspect, "limb_off_m": np.zeros(T0), "reproj_px": np.zeros((T0, 2)), "kp3d_err_m": np.zeros(T0),
               "quality_views": np.array(["v1", "v2"])}
    write_smpl_npz(sl.smpl_world, params, frames, valid, quality=quality)
    depth = np.load(sl.view("v1").depth)
    depth[5] = 0
    np.save(sl.view("v1").depth, depth)
    fm = json.loads(sl.view("v1").frame_map.read_text())
    fm["dropped"][7] = True
    write_json(sl.view("v1").frame_map, fm)
    out = export_training(session, out=tmp_path / "export")
    lab = _labels(out, "v1")
    T = len(frames)
    want = np.ones(T, bool)
    want[[3, 5, 7]] = False
    assert np.array_equal(lab["valid"], want)
    assert np.flatnonzero(~lab["smpl_valid"]).tolist() == [3]
    assert np.flatnonzero(~lab["depth_present"]).tolist() == [5]
    assert np.flatnonzero(~lab["in_sync"]).tolist() == [7]
    assert np.flatnonzero(lab["smpl_suspect"]).tolist() == [4]
    assert np.flatnonzero(~_labels(out, "v2")["valid"]).tolist() == [3]


def test_a_gap_in_the_fit_is_not_filled(training_export, tmp_path):
    """A sequence frame without a row in smpl_world.npz (a gap) is flagged, not interpolated over."""
    import dataclasses

    session = _copy(training_export, tmp_path)
    sl = SessionLayout(session).sequence("seq0")
    params, frames = read_smpl_npz(sl.smpl_world)
    keep = frames != 6
    cut = dataclasses.replace(params, global_orient=params.global_orient[keep], body_pose=params.body_pose[keep],
                              transl=params.transl[keep])
    write_smpl_npz(sl.smpl_world, cut, frames[keep])
    out = export_training(session, out=tmp_path / "export")
    for v in VIEWS:
        lab = _labels(out, v)
        assert np.flatnonzero(~lab["smpl_valid"]).tolist() == [6]
        assert np.flatnonzero(~lab["valid"]).tolist() == [6]


@pytest.mark.parametrize("frames_late", [1.0, 0.5])
def test_view2_body_is_taken_at_its_own_frame_times(training_export, tmp_path, frames_late):
    """With view 2 a whole frame behind view 1 (the final sync's residual), its frame k shows the body of
    row k - 1 exactly and its frame 0 lies outside the fit; half a frame behind, the body is
    between rows k - 1 and k."""
    session = _copy(training_export, tmp_path)
    sl = SessionLayout(session).sequence("seq0")
    fps = float(SYNTH.fps)
    write_json(sl.final_sync, {"version": 2, "views": {}, "chosen": {"residual_s": frames_late / fps}})
    out = export_training(session, out=tmp_path / "export")
    lab = _labels(out, "v2")
    world = np.asarray(read_world_joints(sl.joints_world).joints)
    joints, _ = _pose(_model(session), lab)
    moved = _move(lab["T_world_cam"], joints)  # back into the world
    assert not lab["in_sync"][0] and not lab["valid"][0] and lab["valid"][1:].all()
    if frames_late == 1.0:
        assert np.abs(moved[1:] - world[:-1]).max() < 1e-5
    else:
        mid = (world[:-1] + world[1:]) / 2
        step = np.linalg.norm(world[1:] - world[:-1], axis=-1).max()
        assert np.linalg.norm(moved[1:] - mid, axis=-1).max() < 0.1 * step + 1e-4
        assert np.allclose(lab["body_weight"][1:], 0.5)
    assert np.abs(_labels(out, "v1")["joints_cam"] - _labels(training_export["out"], "v1")["joints_cam"]).max() == 0


def test_resample_motion_on_rows_is_exact_and_between_rows_slerps():
    rng = np.random.default_rng(0)
    poses = Rotation.random(3 * 24, random_state=1).as_rotvec().reshape(3, 72) * 0.5
    transl = rng.normal(0, 1, (3, 3))
    t = np.array([0.0, 0.1, 0.2])
    p, tr, i0, i1, w, inside = resample_motion(poses, transl, t, np.array([0.1, 0.15, 0.3]))
    assert np.array_equal(p[0], poses[1]) and np.array_equal(tr[0], transl[1]) and i0[0] == i1[0] == 1
    r0, r1 = (Rotation.from_rotvec(poses[k].reshape(24, 3)) for k in (1, 2))
    mid = Rotation.from_rotvec(p[1].reshape(24, 3))
    assert np.allclose((r0.inv() * mid).magnitude(), (mid.inv() * r1).magnitude(), atol=1e-9)
    assert np.allclose(tr[1], (transl[1] + transl[2]) / 2)
    assert inside.tolist() == [True, True, False]


# ------------------------------------------------------------------------------------------------
# Resume, CLI, bad input


def _bytes(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != "export_manifest.json"}


def test_rerun_redoes_nothing_and_writes_the_same_bytes(training_export, tmp_path):
    session = _copy(training_export, tmp_path)
    out = tmp_path / "export"
    export_training(session, out=out)
    before = _bytes(out)
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*.jpg")}
    export_training(session, out=out)
    assert _bytes(out) == before
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.jpg")} == mtimes  # not rewritten
    sm = json.loads((out / "export_manifest.json").read_text())
    assert sm["status"] == "ok" and sorted(sm["steps"]) == ["seq0/v1", "seq0/v2"]
    # A second export of the same session elsewhere gives the same bytes (deterministic).
    assert _bytes(export_training(session, out=tmp_path / "again")) == before
    # A changed input redoes only the views that read it.
    sl = SessionLayout(session).sequence("seq0")
    kp = dict(np.load(sl.view("v2").keypoints))
    kp["keypoints"][0, 0, 0] += 1.0
    np.savez(sl.view("v2").keypoints, **kp)
    export_training(session, out=out)
    assert {p: p.stat().st_mtime_ns for p in (out / "seq0" / "v1").rglob("*.jpg")} == \
        {p: t for p, t in mtimes.items() if "/v1/" in p.as_posix()}
    assert _labels(out, "v2")["keypoints"][0, 0, 0] == kp["keypoints"][0, 0, 0]


def test_a_killed_run_leaves_no_half_view_and_resumes(training_export, tmp_path, monkeypatch):
    import embodmocap.export.training as training

    session = _copy(training_export, tmp_path)
    out = tmp_path / "export"
    real = training._write_view
    calls = []

    def dies_on_v2(layout, inp, *a, **k):
        calls.append(inp.view)
        if inp.view == "v2":
            raise KeyboardInterrupt
        return real(layout, inp, *a, **k)

    monkeypatch.setattr(training, "_write_view", dies_on_v2)
    with pytest.raises(KeyboardInterrupt):
        export_training(session, out=out)
    assert (out / "seq0" / "v1" / "labels.npz").is_file() and not (out / "seq0" / "v2").exists()
    assert not (out / "manifest.json").exists()
    assert json.loads((out / "export_manifest.json").read_text())["status"] == "interrupted"
    monkeypatch.setattr(training, "_write_view", lambda layout, inp, *a, **k: (calls.append(inp.view), real(layout, inp, *a, **k))[1])
    calls.clear()
    export_training(session, out=out)
    assert calls == ["v2"]  # v1 was done
    assert _bytes(out) == _bytes(training_export["out"])


def test_cli_export_to_training(training_export, tmp_path):
    from embodmocap.cli import main

    session = _copy(training_export, tmp_path)
    assert main(["export", str(session), "--to", "training"]) == 0
    out = SessionLayout(session).training_dir
    assert _bytes(out) == _bytes(training_export["out"])
    assert main(["export", str(session), "--to", "training", "--seq", "seq0", "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "manifest.json").is_file()


def test_missing_stage2_depth_names_the_file_and_the_command(training_export, tmp_path):
    session = _copy(training_export, tmp_path)
    depth = SessionLayout(session).sequence("seq0").view("v2").depth
    depth.unlink()
    with pytest.raises(InputError) as err:
        export_training(session, out=tmp_path / "export")
    assert str(depth) in str(err.value) and "embodmocap sequence" in str(err.value)


def test_short_stage2_stack_is_one_clear_error(training_export, tmp_path):
    session = _copy(training_export, tmp_path)
    masks = SessionLayout(session).sequence("seq0").view("v1").masks
    np.save(masks, np.load(masks)[:-2])
    with pytest.raises(InputError) as err:
        export_training(session, out=tmp_path / "export")
    assert "masks.npy" in str(err.value) and "frames" in str(err.value)


def test_smaller_rgb_width_scales_images_masks_and_every_pixel_quantity(training_export, tmp_path):
    """--training-rgb-width 160 on the 320x240 session: K, the fitted keypoints (against the
    studio's true 2D keypoints scaled), the detections, masks and JPEGs follow; depth does not."""
    from embodmocap.export.config import ExportConfig

    session, info = training_export["session"], training_export["info"]
    out = export_training(session, out=tmp_path / "small", config=ExportConfig(training_rgb_width=160))
    full = training_export["out"]
    gt = _gt(session)
    m = np.arange(info["motion"], info["motion"] + info["T"])
    for v in VIEWS:
        lab, ref = _labels(out, v), _labels(full, v)
        assert (int(lab["width"]), int(lab["height"])) == (160, 120)
        assert np.allclose(lab["K"], SYNTH.intrinsics().scaled(160, 120).K)
        assert np.array_equal(lab["K_depth"], ref["K_depth"]) and np.array_equal(lab["transl"], ref["transl"])
        raw = m - info["start"][v]
        vis = gt[f"{v}_visibility"][raw] > 0
        true_px = (gt[f"{v}_keypoints2d_gt"][raw][..., :2] + 0.5) * 0.5 - 0.5
        assert np.linalg.norm(lab["keypoints_fit"] - true_px, axis=-1)[vis].max() < 1e-3
        assert np.allclose(lab["keypoints"][..., :2], (ref["keypoints"][..., :2] + 0.5) * 0.5 - 0.5)
        assert np.array_equal(lab["keypoints"][..., 2], ref["keypoints"][..., 2])
        img = cv2.imread(str(out / "seq0" / v / "rgb" / "000003.jpg"))
        assert img.shape == (120, 160, 3)
        masks = np.load(out / "seq0" / v / "masks.npy")
        assert masks.shape == (info["T"], 120, 20)
        small = np.unpackbits(masks[3], axis=-1, count=160).astype(bool)
        big = np.unpackbits(np.load(full / "seq0" / v / "masks.npy")[3], axis=-1, count=320).astype(bool)
        assert small.any() and abs(small.mean() - big.mean()) < 0.01
        assert np.array_equal(np.load(out / "seq0" / v / "depth.npy"), np.load(full / "seq0" / v / "depth.npy"))
    with pytest.raises(InputError, match="larger than"):
        export_training(session, out=tmp_path / "big", config=ExportConfig(training_rgb_width=640))
