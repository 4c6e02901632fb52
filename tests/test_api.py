"""The notebook API: ``embodmocap.load`` on a finished session returns what the stages wrote (here
the studio's truth, so every array is checked against the ground truth), read lazily;
``embodmocap.run`` runs the pipeline and returns the same result (slow)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import embodmocap
from embodmocap.api import SessionResult, SmplMotion
from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.mesh_file import read_mesh_ply
from embodmocap.io.smpl_file import read_smpl_npz, write_smpl_npz
from stage4_session import SYNTH, make_stage4_session

SEQ = SYNTH.sequence_name


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("api") / "session"
    facts = make_stage4_session(root, stage1_world=True)
    lay = SessionLayout(root)
    # One frame flagged as filled in, as Stage IV flags frames it could not place.
    params, frames = read_smpl_npz(lay.sequence(SEQ).smpl_world)
    valid = np.ones(len(params), bool)
    valid[2] = False
    write_smpl_npz(lay.sequence(SEQ).smpl_world, params, frames, valid=valid)
    return root, facts


def test_load_returns_the_sessions_outputs(session):
    root, facts = session
    lay = SessionLayout(root)
    gt = np.load(lay.ground_truth.sequence(SEQ))
    res = embodmocap.load(root)
    assert isinstance(res, SessionResult) and res.root == root and res.pipeline is None
    assert set(res.sequences) == {SEQ} and set(res.scenes) == {SYNTH.scene_name}
    seq = res.sequence()
    assert seq is res.sequence(SEQ) and seq.scene == SYNTH.scene_name and seq.done
    # Nothing large is read until asked for.
    assert "motion" not in seq.__dict__ and "mesh" not in res.scene().__dict__

    motion = seq.motion
    assert isinstance(motion, SmplMotion) and len(motion) == facts["T"] and motion.fps == SYNTH.fps
    m = np.arange(facts["motion"], facts["motion"] + facts["T"])
    np.testing.assert_allclose(motion.params.betas, gt["betas"])
    np.testing.assert_allclose(motion.params.body_pose, gt["body_pose"][m])
    assert motion.valid.dtype == bool and not motion.valid[2] and motion.valid.sum() == facts["T"] - 1
    np.testing.assert_array_equal(motion.frames, np.arange(facts["T"]))
    assert seq.motion is motion  # read once

    T_ws = facts["T_world_scene"]
    true_joints = gt["joints_smpl24"][m] @ T_ws[:3, :3].T + T_ws[:3, 3]
    np.testing.assert_allclose(seq.joints, true_joints, atol=1e-9)
    for v in VIEWS:
        cams = seq.cameras[v]
        raw = m - facts["start"][v]
        np.testing.assert_allclose(cams.T_world_cam, T_ws @ gt[f"{v}_T_scene_cam"][raw], atol=1e-9)
        np.testing.assert_allclose(cams.K, facts["K"].K)
        np.testing.assert_array_equal(cams.raw_frames, raw)

    mesh = res.scene(seq.scene).mesh
    ref_v, ref_f, _ = read_mesh_ply(lay.scene(SYNTH.scene_name).mesh_raw)
    np.testing.assert_allclose(mesh.vertices, ref_v)
    np.testing.assert_array_equal(mesh.faces, ref_f)
    assert seq.quality["sequence"] == {"fps": float(SYNTH.fps), "frames": facts["T"]}
    assert "motion" not in seq.quality  # Stage IV's manifest is absent in this session
    assert seq.paths.smpl_world == lay.sequence(SEQ).smpl_world and seq.paths.smpl_world.is_file()
    assert res.evaluation is None


def test_load_reads_the_evaluation_and_names_missing_files(session, tmp_path):
    import shutil

    root, _ = session
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    SessionLayout(copy).evaluation.write_text(json.dumps({"sequences": {SEQ: {"w_mpjpe_mm": 1.5}}}))
    res = embodmocap.load(copy)
    assert res.evaluation["sequences"][SEQ]["w_mpjpe_mm"] == 1.5
    SessionLayout(copy).sequence(SEQ).joints_world.unlink()
    with pytest.raises(InputError, match="joints_world"):
        res.sequence().joints
    with pytest.raises(InputError, match="no sequence 'nope'"):
        res.sequence("nope")
    with pytest.raises(InputError, match="session.toml"):
        embodmocap.load(tmp_path / "not_a_session")


def test_run_raises_one_error_listing_the_failed_stages(session, tmp_path):
    import shutil

    from embodmocap.errors import EmbodMocapError

    root, _ = session
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    # The tiny session's scene capture is too short for Stage I: the scene fails, and its sequence.
    with pytest.raises(EmbodMocapError, match=r"2 stage\(s\) failed: scene .*key frames.*; sequence .*its scene .* failed"
                       r".*call run again to resume"):
        embodmocap.run(copy)


@pytest.mark.slow
def test_run_processes_a_session_with_a_settings_file(tmp_path):
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    root = tmp_path / "s"
    synthesize(SynthConfig(seed=0, seconds=3.0, scene_seconds=15.0), root)  # as tests/test_pipeline.py
    settings = tmp_path / "settings.toml"
    settings.write_text("[motion.smplify]\nphase2_iterations = 40\n")
    res = embodmocap.run(root, settings)
    assert res.pipeline.ok and res.sequence().done
    seq = res.sequence()
    assert seq.motion.params.body_pose.shape == (len(seq.motion), 69) and seq.joints.shape == (len(seq.motion), 24, 3)
    assert set(seq.quality) == {"sequence", "calibrate", "motion"}
    # The settings file reached Stage IV: its manifest records the resolved config.
    manifest = json.loads(seq.paths.motion_manifest.read_text())
    assert manifest["config"]["smplify"]["phase2_iterations"] == 40
    # A second call resumes: nothing is redone (the fit's file is not written again).
    before = seq.paths.smpl_world.stat().st_mtime_ns
    again = embodmocap.run(root, settings)
    assert again.pipeline.ok and seq.paths.smpl_world.stat().st_mtime_ns == before
