"""Stage IV as a whole (`embodmocap motion`): on a session whose Stage II/III outputs are the truth
plus keypoint noise, the fitted world motion lands on the true joints; the stage resumes, aligns to
contact markers and rejects bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.evaluate.session import sequence_truth
from embodmocap.io.atomic import write_npz
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import ContactMarker, load_manifest, write_manifest
from embodmocap.io.smpl_file import read_smpl_npz
from embodmocap.motion import stage as stage4
from stage4_session import SYNTH, make_stage4_session

SEQ = SYNTH.sequence_name


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("motion") / "s"
    make_stage4_session(root, stage1_world=True)
    lay = SessionLayout(root)
    # Detector-like keypoints: 2 px noise (fixed seed), and occluded joints still reported at their
    # true place with lower confidence (as ViTPose-like detectors do). The final outputs of the
    # truth session are removed so that the stage writes them.
    rng = np.random.default_rng(0)
    for v in VIEWS:
        kp = dict(np.load(lay.sequence(SEQ).view(v).keypoints))
        kp["keypoints"] = kp["keypoints"].copy()
        kp["keypoints"][..., :2] += rng.normal(0, 2.0, kp["keypoints"][..., :2].shape)
        kp["keypoints"][..., 2] = 0.5 + 0.5 * kp["keypoints"][..., 2]
        write_npz(lay.sequence(SEQ).view(v).keypoints, **kp)
        lay.sequence(SEQ).view(v).cameras_final.unlink()
    for p in (lay.sequence(SEQ).smpl_world, lay.sequence(SEQ).joints_world, lay.sequence(SEQ).keypoints3d):
        p.unlink()
    return root


def test_fit_lands_on_the_truth_and_resumes(session):
    lay = SessionLayout(session)
    out = stage4.run(stage4.MotionConfig(), session)
    sl = lay.sequence(SEQ)
    for p in (sl.keypoints3d, sl.smpl_fit, sl.smpl_world, sl.joints_world, sl.motion_manifest,
              *[sl.view(v).cameras_final for v in VIEWS]):
        assert p.is_file(), p
    truth = sequence_truth(lay, SYNTH.scene_name, SEQ)
    joints = np.load(sl.joints_world)["joints"]
    # COCO-17 pins the limbs; spine and hand joints are free (see test_smplify): limbs only.
    limbs = [1, 2, 4, 5, 7, 8, 16, 17, 18, 19, 20, 21]
    err = np.linalg.norm(joints[:, limbs] - truth.joints[:, limbs], axis=-1)
    assert np.median(err) < 0.03
    k3 = np.load(sl.keypoints3d)
    assert k3["points"].shape == (len(joints), 17, 3)
    assert out.figures["init"] == "keypoints"  # no body prior in this session
    assert out.figures["contact_alignment"].startswith("none")
    # The label tracking and the temporal check report what they changed (clean studio keypoints:
    # a few frames at most).
    assert set(out.figures["limb_labels_tracked"]) == {f"{v}_{g}" for v in VIEWS for g in ("arms", "legs")}
    assert sum(out.figures["limb_labels_tracked"].values()) <= 0.1 * len(joints)
    assert 0 <= out.figures["keypoints_dropped_temporal"] <= 0.02 * len(joints) * 17
    # Without contacts the final cameras are Stage III's.
    for v in VIEWS:
        np.testing.assert_array_equal(np.load(sl.view(v).cameras_final)["T_world_cam"],
                                      np.load(sl.view(v).cameras_world)["T_world_cam"])
    # The run recorded that it finished: a downstream stage (evaluate, exports) refuses "running".
    assert json.loads(sl.motion_manifest.read_text())["status"] == "ok"
    again = stage4.run(stage4.MotionConfig(), session)
    assert set(again.skipped) == {"triangulate", "fit", "align"}


def test_contacts_align_and_bad_frames_are_rejected(session, tmp_path):
    import shutil

    from embodmocap.body.model import load_body_model
    from embodmocap.motion.contact import contact_points

    copy = tmp_path / "s"
    shutil.copytree(session, copy)
    lay = SessionLayout(copy)
    stage4.run(stage4.MotionConfig(), copy)
    params, frames = read_smpl_npz(lay.sequence(SEQ).smpl_fit)
    # Markers where the fitted feet are, shifted 8 cm along x: the alignment must move everything 8 cm.
    feet = contact_points(load_body_model(None), params, np.array([0, len(frames) - 1]))
    m = load_manifest(lay.manifest)
    marks = tuple(ContactMarker(int(f), tuple(p + [0.08, 0.0, 0.0])) for f, p in zip([0, len(frames) - 1], feet))
    write_manifest(dataclasses.replace(m, sequences={SEQ: dataclasses.replace(m.sequences[SEQ], contacts=marks)}))
    out = stage4.run(stage4.MotionConfig(), copy)
    assert out.skipped == ("triangulate", "fit")  # only the alignment is redone
    assert out.figures["contact_alignment"] == "applied"
    T = np.asarray(out.figures["T_align"])
    np.testing.assert_allclose(T[:3, 3], [0.08, 0.0, 0.0], atol=2e-3)
    moved = np.load(lay.sequence(SEQ).view("v1").cameras_final)["T_world_cam"]
    np.testing.assert_allclose(moved, T @ np.load(lay.sequence(SEQ).view("v1").cameras_world)["T_world_cam"], atol=1e-9)
    # A contact frame outside the sequence names the manifest and the frames.
    bad = (ContactMarker(10_000, (0.0, 0.0, 0.0)),)
    write_manifest(dataclasses.replace(m, sequences={SEQ: dataclasses.replace(m.sequences[SEQ], contacts=bad)}))
    with pytest.raises(InputError, match="session.toml.*contact frames \\[10000\\]"):
        stage4.run(stage4.MotionConfig(), copy)


def test_missing_stage3_outputs(session, tmp_path):
    import shutil

    copy = tmp_path / "s"
    shutil.copytree(session, copy)
    SessionLayout(copy).sequence(SEQ).view("v2").cameras_world.unlink()
    with pytest.raises(InputError, match="Stage III outputs are missing.*embodmocap calibrate"):
        stage4.run(stage4.MotionConfig(), copy)


def test_unplaceable_body_is_a_clear_error(session, tmp_path):
    import shutil

    copy = tmp_path / "s"
    shutil.copytree(session, copy)
    vl = SessionLayout(copy).sequence(SEQ).view("v2")
    kp = dict(np.load(vl.keypoints))
    kp["keypoints"] = kp["keypoints"].copy()
    kp["keypoints"][:, [5, 6, 11, 12], 2] = 0.0  # v2 never sees the shoulders and hips
    write_npz(vl.keypoints, **kp)
    with pytest.raises(InputError, match="keypoints3d.npz: cannot place a starting body"):
        stage4.run(stage4.MotionConfig(), copy)


def test_solve_in_memory_gives_the_run_s_files(session, tmp_path):
    """Stage IV's pure solve, on inputs read into memory from a copy of the session that is then
    deleted (so it can open no file), gives exactly what the run wrote."""
    import shutil

    from embodmocap.body.model import load_body_model
    from embodmocap.io.body_prior import body_priors_by_frame
    from embodmocap.io.stage_files import (read_cameras, read_keypoints2d, read_keypoints3d, read_smpl_valid,
                                           read_world_joints, sequence_fps)
    from embodmocap.motion import solve
    from embodmocap.motion.floor import scene_floor_z
    from embodmocap.sequence.subframe import synced_views

    work = tmp_path / "s"
    shutil.copytree(session, work)
    cfg = stage4.MotionConfig()
    stage4.run(cfg, work, force=True)
    lay = SessionLayout(work)
    manifest = load_manifest(lay.manifest)
    entry = manifest.sequence(None)
    sl = lay.sequence(entry.name)
    cams = {v: read_cameras(sl.view(v).cameras_world) for v in VIEWS}
    kps = {v: read_keypoints2d(sl.view(v).keypoints).keypoints for v in VIEWS}
    synced_cams, synced_kps = synced_views(sl, cams, kps)
    T = min(len(synced_kps[v]) for v in VIEWS)
    inputs = solve.MotionInputs(
        sequence=entry.name, model=load_body_model(manifest.body_model), cameras=cams, keypoints=kps,
        fps=sequence_fps(sl), synced_cameras=synced_cams, synced_keypoints=synced_kps,
        priors=body_priors_by_frame({v: sl.view(v).body_prior for v in VIEWS}, T, cfg.min_prior_fraction),
        layout=stage4.keypoint_layout(sl, entry.name), gender=manifest.gender,
        contacts=[(c.frame, np.asarray(c.xyz)) for c in entry.contacts],
        floor_z=scene_floor_z(stage4.scene_mesh(cfg, lay, entry.scene), cfg.smplify.floor_max_tilt_deg))
    # What the run wrote, read before the session goes.
    k3, joints = read_keypoints3d(sl.keypoints3d), read_world_joints(sl.joints_world)
    fit, _ = read_smpl_npz(sl.smpl_fit)
    final, frames = read_smpl_npz(sl.smpl_world)
    valid = read_smpl_valid(sl.smpl_world)
    cams_final = {v: read_cameras(sl.view(v).cameras_final) for v in VIEWS}
    shutil.rmtree(work)  # nothing of the session is left to read
    res = solve.solve(cfg, inputs)

    assert res.keypoints3d.files == k3.files
    for k in k3.files:
        assert np.array_equal(res.keypoints3d[k], k3[k], equal_nan=k3[k].dtype.kind == "f"), k
    for got, want in ((res.fit.params, fit), (res.final.params, final)):
        for k in ("betas", "global_orient", "body_pose", "transl"):
            assert np.array_equal(np.asarray(getattr(got, k)), np.asarray(getattr(want, k))), k
        assert got.fps == want.fps and got.gender == want.gender
    assert np.array_equal(res.final.frames, frames) and np.array_equal(res.final.valid, valid)
    for k in joints.files:
        assert np.array_equal(res.final.joints[k], joints[k]), k
    for v in VIEWS:
        assert res.final.cameras_final[v].files == cams_final[v].files
        for k in cams_final[v].files:
            assert np.array_equal(res.final.cameras_final[v][k], cams_final[v][k]), (v, k)
